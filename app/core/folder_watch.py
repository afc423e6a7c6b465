"""Waiting for a file to arrive in a folder without looking into it again and again: Linux's inotify(7).

The embedded broker's idle workers (app/core/broker.py) and the API waiting for a render's outcome on the embedded
broker (app/core/render_results.py) sleep on a watch and wake when a file is renamed into the folder, or closed
after writing in it, or when :func:`wake_all` is called (a worker that is stopping: Celery checks its stop flag only
between waits). :meth:`FolderWatch.open` gives None where inotify is not available (another system, a folder that is
gone, no inotify instance left): the caller then polls.
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
import weakref
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


_OPEN: weakref.WeakSet[FolderWatch] = weakref.WeakSet()  # this process's open watches, for wake_all


def wake_all() -> None:
    """End the wait of every watch this process opened (a forked child's inherited ones are its parent's): each
    returns with ``woken`` set, and so does the next wait of one not waiting now. Safe in a signal handler (one
    write to an eventfd each)."""
    pid = os.getpid()
    for watch in list(_OPEN):
        if watch.pid == pid:
            watch.wake()


class FolderWatch:
    """An inotify watch of one folder: :meth:`wait` returns once a file has arrived in it since the watch was made
    or the last wait returned (events queue from the watch's creation on, so one that comes between a look into
    the folder and the wait is not missed), when :meth:`wake` is called, or when ``timeout_s`` ends. Also a context
    manager that closes it."""

    def __init__(self, fd: int) -> None:
        self.fd = fd
        self.pid = os.getpid()
        self.woken = False  # whether the last wait ended by wake() (a stop request), not by a file or its timeout
        self._wake_fd = os.eventfd(0, os.EFD_NONBLOCK | os.EFD_CLOEXEC)
        _OPEN.add(self)

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
        try:
            if libc.inotify_add_watch(fd, os.fsencode(folder), _IN_MOVED_TO | _IN_CLOSE_WRITE) < 0:
                raise OSError(ctypes.get_errno(), "inotify_add_watch")
            return cls(fd)
        except OSError:  # the folder is gone, or no descriptor is left for the wake eventfd
            os.close(fd)
            return None

    def wait(self, timeout_s: float) -> bool:
        """Sleep until a file arrives, :meth:`wake` is called or ``timeout_s`` ends; whether a file arrived
        (``woken`` says whether the wait was woken)."""
        readable, _, _ = select.select([self.fd, self._wake_fd], [], [], max(timeout_s, 0.0))
        self.woken = self._wake_fd in readable
        if self.woken:
            self._drain(self._wake_fd)
        if self.fd in readable:
            self._drain(self.fd)
            return True
        return False

    def wake(self) -> None:
        """End the current wait, or the next one at once (nothing once the watch is closed)."""
        if self._wake_fd < 0:
            return  # closed: its number may belong to another file by now
        with contextlib.suppress(OSError):  # its counter full: a wake is pending anyway
            os.eventfd_write(self._wake_fd, 1)

    @staticmethod
    def _drain(fd: int) -> None:
        """Read everything queued on ``fd`` (which files the events name does not matter: the caller looks into
        the folder)."""
        while True:
            try:
                if not os.read(fd, 65536):
                    return
            except OSError as exc:
                if exc.errno in (errno.EAGAIN, errno.EWOULDBLOCK):
                    return
                raise

    def close(self) -> None:
        _OPEN.discard(self)
        wake_fd, self._wake_fd = self._wake_fd, -1
        for fd in (self.fd, wake_fd):
            if fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)

    def __enter__(self) -> FolderWatch:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()
