"""Waiting for a file to arrive in a folder without looking into it again and again: Linux's inotify(7).

The embedded broker's idle workers (app/core/broker.py) and the API waiting for a render's outcome on the embedded
broker (app/core/render_results.py) sleep on a watch and wake when a file is renamed into the folder, or closed
after writing in it. :meth:`FolderWatch.open` gives None where inotify is not available (another system, a folder
that is gone, no inotify instance left): the caller then polls.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import errno
import functools
import os
import select
import sys
from pathlib import Path

# inotify(7): a file renamed into, or closed after writing in, the watched folder.
_IN_MOVED_TO, _IN_CLOSE_WRITE = 0x80, 0x8


@functools.cache
def _libc() -> ctypes.CDLL | None:
    """The C library with inotify's calls, loaded once per process (``find_library`` may run ``ldconfig``: not
    for every render request); None where it lacks them."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)
        libc.inotify_init1, libc.inotify_add_watch  # noqa: B018 (AttributeError where they are missing)
    except (OSError, AttributeError):
        return None
    return libc


class FolderWatch:
    """An inotify watch of one folder: :meth:`wait` returns once a file has arrived in it since the watch was made
    or the last wait returned (events queue from the watch's creation on, so one that comes between a look into
    the folder and the wait is not missed), or when ``timeout_s`` ends. Also a context manager that closes it."""

    def __init__(self, fd: int) -> None:
        self.fd = fd

    @classmethod
    def open(cls, folder: str | Path) -> FolderWatch | None:
        if not sys.platform.startswith("linux"):
            return None
        libc = _libc()
        if libc is None:
            return None
        fd = libc.inotify_init1(os.O_NONBLOCK | os.O_CLOEXEC)
        if fd < 0:
            return None
        if libc.inotify_add_watch(fd, os.fsencode(folder), _IN_MOVED_TO | _IN_CLOSE_WRITE) < 0:
            os.close(fd)
            return None
        return cls(fd)

    def wait(self, timeout_s: float) -> bool:
        """Sleep until a file arrives or ``timeout_s`` ends; whether one arrived."""
        readable, _, _ = select.select([self.fd], [], [], max(timeout_s, 0.0))
        if readable:
            self._drain()
        return bool(readable)

    def _drain(self) -> None:
        """Read every queued event (what they name does not matter: the caller looks into the folder)."""
        while True:
            try:
                if not os.read(self.fd, 65536):
                    return
            except OSError as exc:
                if exc.errno in (errno.EAGAIN, errno.EWOULDBLOCK):
                    return
                raise

    def close(self) -> None:
        with contextlib.suppress(OSError):
            os.close(self.fd)

    def __enter__(self) -> FolderWatch:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()
