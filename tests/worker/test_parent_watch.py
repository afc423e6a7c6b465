"""A worker ends with the process that started it (issue #42, item 7), by the kernel's parent-death signal or,
without it, by the watchdog alone: the end-to-end test is ``tests/service/test_serve_signals.py`` (a real
``voxnerf serve`` killed with SIGKILL); here the watchdog's own rules, with real processes.

Each test starts a stand-in parent that starts a stand-in worker in a session of its own (as ``voxnerf serve``
does); the worker ignores SIGTERM (a worker whose warm shutdown waits for a long task) and has a child of its own
(its pool process). The parent is then killed with SIGKILL.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from service_fixtures import REPO, wait_for

pytestmark = pytest.mark.skipif(os.name != "posix", reason="process groups and signals are POSIX")

GRACE_S = 1.0
WORKER = textwrap.dedent("""
    import os, signal, subprocess, sys, time
    from worker.parent_watch import exit_with_parent
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    pool = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(600)"])
    print(os.getpid(), pool.pid, flush=True)
    exit_with_parent(int(sys.argv[1]), float(sys.argv[2]), use_death_signal=sys.argv[3] == "1")
    print("watching", flush=True)
    time.sleep(600)
""")
PARENT = textwrap.dedent("""
    import os, subprocess, sys, time
    watched = os.getpid() if sys.argv[1] == "parent" else 1  # 1: a pid that is not the worker's parent
    subprocess.Popen([sys.executable, "-c", sys.argv[2], str(watched), sys.argv[3], sys.argv[4]],
                     start_new_session=True)
    time.sleep(600)
""")


def _alive(pid: int) -> bool:
    """Running (not a zombie waiting for its parent to collect it)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, ProcessLookupError):
        return False
    return state not in ("Z", "X")


def _start(watched: str, use_death_signal: bool) -> tuple[subprocess.Popen, int, int]:
    """The stand-in parent and the pids of its worker and of the worker's child, once it watches."""
    parent = subprocess.Popen(
        [sys.executable, "-c", PARENT, watched, WORKER, str(GRACE_S), "1" if use_death_signal else "0"],
        cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)}, stdout=subprocess.PIPE, text=True,
    )
    worker, pool = map(int, parent.stdout.readline().split())
    assert parent.stdout.readline().strip() == "watching"
    return parent, worker, pool


@contextlib.contextmanager
def _cleaned_up(parent: subprocess.Popen, *pids: int):
    try:
        yield
    finally:
        for pid in (parent.pid, *pids):  # only what this test started
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        parent.wait(10)
        parent.stdout.close()


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads process states from /proc")
@pytest.mark.parametrize("use_death_signal", [True, False], ids=["death-signal", "watchdog-only"])
def test_a_worker_and_its_pool_end_once_the_parent_is_sigkilled(use_death_signal):
    parent, worker, pool = _start("parent", use_death_signal)
    with _cleaned_up(parent, worker, pool):
        assert _alive(worker) and _alive(pool)
        parent.kill()
        parent.wait(10)
        wait_for(lambda: not _alive(worker) and not _alive(pool), GRACE_S + 15, "the orphaned worker and its pool")


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads process states from /proc")
def test_a_worker_whose_parent_died_before_it_watched_stops_at_once():
    """The parent named is not (or no longer) the worker's parent when the watch starts: it stops without
    waiting for a death that already happened."""
    parent, worker, pool = _start("someone-else", use_death_signal=True)
    with _cleaned_up(parent, worker, pool):
        wait_for(lambda: not _alive(worker) and not _alive(pool), GRACE_S + 15, "the worker and its pool")
        assert parent.poll() is None  # its real parent lives on


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_the_death_signal_is_set_on_linux():
    """PR_GET_PDEATHSIG (2) reads back what :func:`set_parent_death_signal` set."""
    script = textwrap.dedent("""
        import ctypes, signal
        from worker.parent_watch import set_parent_death_signal
        assert set_parent_death_signal(signal.SIGTERM)
        value = ctypes.c_int()
        assert ctypes.CDLL(None).prctl(2, ctypes.byref(value), 0, 0, 0) == 0
        print(value.value)
    """)
    result = subprocess.run([sys.executable, "-c", script], cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)},
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert int(result.stdout) == signal.SIGTERM
