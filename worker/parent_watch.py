"""An embedded worker ends with the ``voxnerf serve`` that started it, even when that one is killed with SIGKILL.

``voxnerf serve`` stops its workers itself on SIGTERM and SIGINT (:mod:`app.serve`); SIGKILL (the OOM killer,
``kill -9``, a container runtime giving up) leaves it no chance, and its workers, reparented, would go on
consuming the queues with nobody serving the API. :func:`exit_with_parent` makes a worker notice: on Linux the
kernel sends it SIGTERM the moment its parent dies (``PR_SET_PDEATHSIG``); everywhere a watchdog thread polls
the parent's pid as the fallback. Either way the worker then stops as ``voxnerf serve`` stops it: a warm
shutdown (SIGTERM: Celery finishes or hands back its task), and after a grace period SIGKILL to its process
group (itself and its pool processes; ``voxnerf serve`` starts each worker in a group of its own).
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import os
import signal
import sys
import threading
import time

PR_SET_PDEATHSIG = 1  # <linux/prctl.h>
POLL_S = 0.5
log = logging.getLogger(__name__)


def set_parent_death_signal(sig: signal.Signals) -> bool:
    """Ask the kernel to send ``sig`` to this process when its parent dies (Linux ``prctl``); whether it
    could (False on other systems, or when the call fails)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def _stop_orphaned(parent_pid: int, grace_s: float, signalled: bool) -> None:
    """This process lost ``parent_pid``: a warm shutdown (SIGTERM, unless the kernel sent it already), then
    after ``grace_s`` SIGKILL to the process group it leads (to itself alone when it leads none)."""
    log.warning("parent process %d is gone: stopping (SIGKILL to the worker's processes in %.0f s)",
                parent_pid, grace_s)
    if not signalled:
        os.kill(os.getpid(), signal.SIGTERM)
    time.sleep(grace_s)
    log.warning("still running %.0f s after the parent process died: killing the worker's processes", grace_s)
    with contextlib.suppress(ProcessLookupError, PermissionError):
        if os.getpgrp() == os.getpid():
            os.killpg(os.getpid(), signal.SIGKILL)
        os.kill(os.getpid(), signal.SIGKILL)


def exit_with_parent(parent_pid: int, grace_s: float, use_death_signal: bool = True) -> threading.Thread:
    """From now on, stop this process (:func:`_stop_orphaned`) once ``parent_pid`` is no longer its parent.

    ``use_death_signal``: also ask the kernel for SIGTERM at the parent's death (Linux); without it (or where
    the system has no such call) the watchdog thread alone notices, within :data:`POLL_S`. A parent that died
    before this call is noticed at once. Returns the watchdog thread (a daemon)."""
    signalled = use_death_signal and set_parent_death_signal(signal.SIGTERM)
    died_before = os.getppid() != parent_pid  # then the kernel sends nothing: the watchdog sends SIGTERM

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(POLL_S)
        _stop_orphaned(parent_pid, grace_s, signalled=signalled and not died_before)

    thread = threading.Thread(target=watch, name="exit-with-parent", daemon=True)
    thread.start()
    return thread
