"""Stopping stops everything (issue #22, item 7; issue #42, item 7): a real ``voxnerf serve`` with its three
embedded workers, sent SIGTERM (``kill``, a service manager) or SIGINT (Ctrl-C), exits within a bound and leaves no
process of its tree behind; sent SIGKILL, its workers notice and stop themselves. The tree (workers and their pool
processes) is read from /proc before the signal."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from service_fixtures import REPO, free_port, wait_for

from app.serve import STOP_GRACE_S

pytestmark = pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads the process tree from /proc")

QUEUES = ("train", "render", "outputs")


def _stat(pid: int) -> tuple[str, int] | None:
    """``(state, parent pid)`` of a process from /proc, or None once it is gone."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except (FileNotFoundError, ProcessLookupError):
        return None
    fields = text.rsplit(")", 1)[1].split()  # the command name in (...) may contain spaces
    return fields[0], int(fields[1])


def _descendants(root: int) -> set[int]:
    """Every living process below ``root`` (children, their children, ...)."""
    parents = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit() and (stat := _stat(int(entry.name))) is not None:
            parents[int(entry.name)] = stat[1]
    found, frontier = set(), {root}
    while frontier:
        frontier = {pid for pid, parent in parents.items() if parent in frontier} - found
        found |= frontier
    return found


def _running(pid: int) -> bool:
    stat = _stat(pid)
    return stat is not None and stat[0] not in ("Z", "X")  # a zombie has stopped; only its entry is left


def _all_workers_ready(base_url: str) -> bool:
    try:
        body = httpx.get(f"{base_url}/healthz", timeout=10, trust_env=False).json()
    except (httpx.HTTPError, ValueError):
        return False
    return all(body.get("workers", {}).get(queue) for queue in QUEUES)


@contextlib.contextmanager
def _serving(tmp_path: Path, preload: bool = True) -> Iterator[tuple[subprocess.Popen, set[int], Path]]:
    """A real ``voxnerf serve`` with its three workers ready: ``(process, its tree read from /proc, its log)``;
    every process of the tree is SIGKILLed on the way out (only what the test started). ``preload``: whether the
    workers load the engine as they start (the default, ``VOXNERF_WORKER_PRELOAD``)."""
    port = free_port()
    env = {k: v for k, v in os.environ.items() if not k.startswith("VOXNERF_")}
    env.update(
        VOXNERF_DATA_DIR=str(tmp_path / "data"), VOXNERF_DEVICE="cpu", VOXNERF_HEALTH_TIMEOUT_S="2",
        PYTHONPATH=str(REPO), PYTHONUNBUFFERED="1", NO_PROXY="127.0.0.1,localhost",
        VOXNERF_WORKER_PRELOAD="1" if preload else "0",
    )
    log_path = tmp_path / "serve.log"
    with open(log_path, "wb") as log:
        serve = subprocess.Popen(
            [sys.executable, "-m", "voxnerf", "serve", "--host", "127.0.0.1", "--port", str(port)],
            cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
        )
    tree: set[int] = set()
    try:
        try:
            wait_for(lambda: _all_workers_ready(f"http://127.0.0.1:{port}"), 180, "all three workers in /healthz", 1)
        except AssertionError as err:
            log_tail = log_path.read_text(errors="replace")[-3000:]
            raise AssertionError(f"{err}; voxnerf serve's log ends:\n{log_tail}") from err
        tree = _descendants(serve.pid)
        assert len(tree) >= len(QUEUES), f"expected the workers below voxnerf serve, found {sorted(tree)}"
        yield serve, tree, log_path
    finally:
        for pid in [serve.pid, *sorted(tree)]:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        with contextlib.suppress(subprocess.TimeoutExpired):
            serve.wait(10)


# SIGTERM with the engine loaded in every worker, as deployed; the other cases' workers skip loading it (faster)
@pytest.mark.parametrize(("sig", "preload"), [(signal.SIGTERM, True), (signal.SIGINT, False)],
                         ids=["SIGTERM", "SIGINT"])
def test_a_stop_signal_stops_serve_and_every_worker(tmp_path, sig, preload):
    with _serving(tmp_path, preload) as (serve, tree, log_path):
        serve.send_signal(sig)
        serve.wait(STOP_GRACE_S + 60)  # a bound: the workers' grace, then they are killed
        wait_for(lambda: not any(_running(pid) for pid in tree), 10, "the reparented pool processes to end")
        log_text = log_path.read_text(errors="replace")
        assert f"received {sig.name}: stopping the workers" in log_text, log_text[-3000:]


def test_a_sigkilled_serve_takes_every_worker_with_it(tmp_path):
    """SIGKILL leaves ``voxnerf serve`` no chance to stop its workers: each one, told by the kernel
    (``PR_SET_PDEATHSIG``) or its watchdog, stops itself: within the grace, with no process of the tree left."""
    with _serving(tmp_path, preload=False) as (serve, tree, log_path):
        serve.kill()
        serve.wait(10)
        try:
            wait_for(lambda: not any(_running(pid) for pid in tree), STOP_GRACE_S + 30, "the orphaned workers to end")
        except AssertionError as err:
            left = sorted(pid for pid in tree if _running(pid))
            raise AssertionError(f"{err}: {len(left)} of {len(tree)} processes still run: {left}") from err
        assert "parent process" in log_path.read_text(errors="replace"), "no worker said why it stopped"
