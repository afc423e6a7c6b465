"""How a worker process starts (:mod:`worker.run`): the OpenMP wait policy each kind of worker loads torch with,
and whether it loads the engine before its first task (``worker_preload``)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from app.core.celery_app import QUEUES
from worker.run import openmp_wait_policy, set_openmp_wait_policy
from worker.tasks import WORK_MODULES

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize(
    ("queues", "expected"),
    [(["train"], None), (["train", "render", "outputs"], None), (["render"], "PASSIVE"), (["outputs"], "PASSIVE"),
     (["render", "outputs"], "PASSIVE")],
)
def test_a_training_worker_keeps_the_cli_s_policy_and_render_workers_sleep_at_once(queues, expected):
    assert openmp_wait_policy(queues) == expected


def test_the_environment_s_policy_wins():
    env = {"OMP_WAIT_POLICY": "ACTIVE"}
    assert set_openmp_wait_policy(["render"], env) == "ACTIVE" and env == {"OMP_WAIT_POLICY": "ACTIVE"}
    env = {}
    assert set_openmp_wait_policy(["render"], env) == "PASSIVE" and env == {"OMP_WAIT_POLICY": "PASSIVE"}
    env = {}
    assert set_openmp_wait_policy(["train"], env) is None and env == {}


def test_starting_a_worker_sets_the_policy_before_torch_loads():
    """``worker.run`` and the tasks load no torch (OpenMP reads the policy once, when torch loads it), and the
    policy it sets is the one torch's process has once the queues' work is loaded; a worker that trains sets none."""
    code = ("import sys, os; import worker.run as w, worker.tasks as t; assert 'torch' not in sys.modules; "
            "queues = sys.argv[1].split(','); w.set_openmp_wait_policy(queues); t.preload_work(queues); "
            "assert 'torch' in sys.modules; print(os.environ.get('OMP_WAIT_POLICY'))")
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    cases = (("render", "PASSIVE"), ("train,render", "None"))  # each queue's policy: the parametrized test above
    for queues, expected in cases:
        out = subprocess.run([sys.executable, "-c", code, queues], env=env, capture_output=True, text=True, check=True)
        assert out.stdout.strip() == expected, queues


def test_each_queue_preloads_the_work_of_its_own_tasks():
    assert set(WORK_MODULES) == set(QUEUES)
    assert WORK_MODULES["render"] == ("worker.rendering",) and WORK_MODULES["outputs"] == ("worker.outputs",)
    assert set(WORK_MODULES["train"]) == {"worker.training", "worker.imports"}  # imports are queued on train


def _ready_worker(tmp_path: Path, preload: str) -> subprocess.Popen:
    """A real render worker on the embedded broker, started with ``VOXNERF_WORKER_PRELOAD=preload``, once Celery
    logs it ready."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("VOXNERF_")}
    env |= {"VOXNERF_DATA_DIR": str(tmp_path / "data"), "VOXNERF_WORKER_PRELOAD": preload, "PYTHONPATH": str(REPO)}
    log = tmp_path / "worker.log"
    with log.open("wb") as out:
        proc = subprocess.Popen([sys.executable, "-m", "worker", "--queues", "render"], cwd=REPO, env=env,
                                stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
    deadline = time.monotonic() + 120
    while " ready." not in log.read_text(errors="replace"):
        assert proc.poll() is None and time.monotonic() < deadline, log.read_text(errors="replace")[-3000:]
        time.sleep(0.2)
    return proc


def _maps_torch(pid: int) -> bool:
    """Whether process ``pid`` or one of its children has torch's library mapped."""
    pids = [pid, *map(int, Path(f"/proc/{pid}/task/{pid}/children").read_text().split())]
    return any("libtorch" in Path(f"/proc/{p}/maps").read_text() for p in pids)


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="reads /proc")
@pytest.mark.parametrize(("preload", "loaded"), [("1", True), ("0", False)])
def test_a_ready_worker_holds_the_engine_only_when_it_preloads(tmp_path, preload, loaded):
    proc = _ready_worker(tmp_path, preload)
    try:
        assert _maps_torch(proc.pid) is loaded
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)


def test_torch_loaded_too_early_is_said(caplog, monkeypatch):
    monkeypatch.setitem(sys.modules, "torch", sys.modules.get("torch") or object())
    with caplog.at_level("WARNING", logger="worker.run"):
        set_openmp_wait_policy(["render"], {})
    assert "torch loaded before the worker set OMP_WAIT_POLICY=PASSIVE" in caplog.text
