"""What a long import tells its caller while it runs, and how the caller stops it.

An importer that takes minutes (structure from motion, a video's frames) calls ``monitor.report(step, fraction)``
as it goes: ``step`` a few words for people ("matching features: 120 of 450 image pairs"), ``fraction`` the share
of the importer's work done, in [0, 1]. At its safe points it calls ``monitor.check()``, which raises
:class:`ImportCancelled` once ``should_stop()`` answers yes; the importer then leaves nothing at its output, as on
any error. ``monitor.within(start, end)`` is the same monitor for a part of the work that spans ``start..end`` of
the whole (a video's decoding, then its structure from motion).

:class:`CountWatch` follows work that pycolmap does in one blocking call: it reports the count of work done when
the call starts and, read from the call's database, when it returns, and turns a stop request into pycolmap's own
cancellation while it runs.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass

from voxnerf.errors import VoxNeRFError

WATCH_PERIOD_S = 0.5
"""How often a :class:`CountWatch` asks whether to stop while its call runs."""


class ImportCancelled(VoxNeRFError):
    """The import was asked to stop (its job was cancelled); nothing was written."""


def _ignore(_step: str, _fraction: float) -> None:
    return None


def _never() -> bool:
    return False


@dataclass(frozen=True)
class ImportMonitor:
    """Progress out (``report(step, fraction)``) and stop requests in (``should_stop()``) of one import."""

    report: Callable[[str, float], None] = _ignore
    should_stop: Callable[[], bool] = _never
    start: float = 0.0
    end: float = 1.0

    def step(self, text: str, fraction: float) -> None:
        """Report ``text`` at ``fraction`` (0..1) of this monitor's span."""
        fraction = min(max(float(fraction), 0.0), 1.0)
        self.report(text, self.start + (self.end - self.start) * fraction)

    def within(self, start: float, end: float) -> ImportMonitor:
        """This monitor for a part of its work spanning ``start..end`` (fractions of this monitor's span)."""
        width = self.end - self.start
        return ImportMonitor(self.report, self.should_stop, self.start + width * start, self.start + width * end)

    def check(self) -> None:
        """Raise ImportCancelled when the caller asked the import to stop."""
        if self.should_stop():
            raise ImportCancelled("the import was cancelled")


class CountWatch:
    """Around one blocking pycolmap call: reports ``"<text>: <before> of <total> <unit>"`` as it starts and
    ``count()`` (what the call has written, read once it returned) when it returns; while it runs, every
    WATCH_PERIOD_S, cancels ``token`` (a ``pycolmap.CancellationToken``) once the monitor says stop.

    Nothing is read from the call's database while it runs: pycolmap's writing threads meet "database is locked"
    when another connection reads it at the wrong moment, and their error aborts the whole process. Work that
    needs progress within it is split into several calls (:func:`voxnerf.data.importers.sfm.run_sfm`'s feature
    extraction)."""

    def __init__(self, monitor: ImportMonitor, count: Callable[[], int | None], total: int, text: str, unit: str,
                 token, before: int = 0) -> None:
        self.monitor, self.count, self.token = monitor, count, token
        self.total, self.text, self.unit, self.before = max(int(total), 1), text, unit, min(int(before), int(total))
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._watch, name=f"watch {text}", daemon=True)

    def _report(self, done: int | None) -> None:
        if done is not None:
            done = min(done, self.total)
            self.monitor.step(f"{self.text}: {done} of {self.total} {self.unit}", done / self.total)

    def _watch(self) -> None:
        while not self._done.wait(WATCH_PERIOD_S):
            if self.monitor.should_stop():
                self.token.cancel()
                return

    def __enter__(self) -> CountWatch:
        self._report(self.before)
        self._thread.start()
        return self

    def __exit__(self, exc_type, *exc) -> None:
        self._done.set()
        self._thread.join()
        if exc_type is None:
            self._report(self.count())
