"""The import monitor (:mod:`voxnerf.data.importers.monitor`): progress spans nest, a stop request raises, and a
count watch reports a blocking call's progress and turns a stop request into the call's cancellation."""

from __future__ import annotations

import threading
import time

import pytest

from voxnerf.data.importers.monitor import WATCH_PERIOD_S, CountWatch, ImportCancelled, ImportMonitor
from voxnerf.data.importers.sfm import sequential_pairs


def test_spans_nest_and_clamp():
    seen = []
    monitor = ImportMonitor(report=lambda step, fraction: seen.append((step, fraction)))
    part = monitor.within(0.2, 1.0).within(0.5, 1.0)  # 0.6 .. 1.0 of the whole
    part.step("half", 0.5)
    part.step("beyond", 7.0)
    monitor.within(0.0, 0.2).step("before", -1.0)
    assert seen == [("half", pytest.approx(0.8)), ("beyond", 1.0), ("before", 0.0)]


def test_check_raises_once_asked_to_stop():
    asked = threading.Event()
    monitor = ImportMonitor(should_stop=asked.is_set).within(0.1, 0.9)
    monitor.check()
    asked.set()
    with pytest.raises(ImportCancelled, match="cancelled"):
        monitor.check()


def test_a_default_monitor_reports_nowhere_and_never_stops():
    ImportMonitor().step("anything", 0.5)
    ImportMonitor().check()


class _Token:
    def __init__(self) -> None:
        self.cancelled = threading.Event()

    def cancel(self) -> None:
        self.cancelled.set()


def test_a_watch_reports_the_count_as_work_goes_on_and_once_more_at_the_end():
    written: list[int | None] = [None]  # what the call has written so far (None: cannot tell yet)
    seen = []
    monitor = ImportMonitor(report=lambda step, fraction: seen.append((step, fraction)))
    with CountWatch(monitor, lambda: written[-1], 4, "matching", "pairs", _Token()):
        for count in (None, 1, 4):
            written.append(count)
            time.sleep(3 * WATCH_PERIOD_S)
    assert seen[0] == ("matching: 0 of 4 pairs", 0.0)
    assert not any("None" in step for step, _ in seen)
    assert seen[-1] == ("matching: 4 of 4 pairs", 1.0)  # counted again when the call returned
    assert [f for _, f in seen] == sorted(f for _, f in seen)
    assert ("matching: 1 of 4 pairs", 0.25) in seen


def test_a_count_past_the_total_is_reported_as_the_total():
    seen = []
    with CountWatch(ImportMonitor(report=lambda *step: seen.append(step)), lambda: 9, 4, "x", "images", _Token()):
        pass
    assert seen[-1] == ("x: 4 of 4 images", 1.0)


def test_a_watch_cancels_the_token_when_asked_to_stop_and_reports_nothing_more_after_an_error():
    token, asked, seen = _Token(), threading.Event(), []
    monitor = ImportMonitor(report=lambda *step: seen.append(step), should_stop=asked.is_set)
    with pytest.raises(InterruptedError), CountWatch(monitor, lambda: 1, 10, "matching", "pairs", token):
        asked.set()
        assert token.cancelled.wait(5.0)
        raise InterruptedError("cancelled")  # what pycolmap raises once cancelled
    assert seen == [("matching: 0 of 10 pairs", 0.0)]


@pytest.mark.parametrize(("n", "pairs"), [(0, 0), (1, 0), (2, 1), (3, 3), (5, 8), (25, 94)])
def test_sequential_pairs_counts_the_quadratic_gaps(n, pairs):
    # gaps 1, 2, 4, 8, 16...: 25 images give 24 + 23 + 21 + 17 + 9 pairs (what COLMAP 4.2 matched on them)
    assert sequential_pairs(n) == pairs


def test_sequential_pairs_without_quadratic_overlap_counts_the_next_ones():
    assert sequential_pairs(25, overlap=15, quadratic=False) == 15 * 10 + sum(range(1, 15))
