"""A job trained through real service workers runs its loop as ``voxnerf train`` runs it: the same threads, OpenMP
settings, C kernels and compiled step (report.json's ``runtime`` and stages), on the embedded broker
(a Redis-fed worker runs the same worker process; benchmarks/service_speed.py measures both).

The same captured-like scene (a room whose transforms.json does not say ``synthetic``, so pose refinement and
per-image appearance train too) is trained by ``voxnerf train`` in a subprocess with the environment the
service's processes get, and by a job through the running service over HTTP. Nothing is timed: the check is on
what each process ran with. Render and outputs workers are the one intended difference (their OpenMP threads
sleep at once, :func:`worker.run.openmp_wait_policy`); their speed is measured side by side by
``benchmarks/service_speed.py``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from service_fixtures import REPO, start_redis, start_service, upload_scene, wait_until_succeeded

pytestmark = pytest.mark.slow

STEPS = 8
TRAIN_TIMEOUT_S = 600


def _service_env() -> dict[str, str]:
    """The environment :func:`service_fixtures.start_service` gives its processes, less its VOXNERF_ settings."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("VOXNERF_")}
    return env | {"PYTHONPATH": str(REPO), "PYTHONUNBUFFERED": "1"}


@pytest.fixture(scope="module")
def cli_report(captured_small_room, compiled_captured_step, tmp_path_factory) -> dict:
    """``voxnerf train``'s report.json (its step loads from the inductor cache ``compiled_captured_step`` filled)."""
    run = tmp_path_factory.mktemp("cli") / "run"
    cmd = [sys.executable, "-m", "voxnerf", "train", str(captured_small_room), "--out", str(run),
           "--max-iters", str(STEPS), "--device", "cpu"]
    done = subprocess.run(cmd, env=_service_env(), cwd=REPO, capture_output=True, text=True, timeout=TRAIN_TIMEOUT_S)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads((run / "report.json").read_text())


def _train_through_service(root: Path, scene_dir: Path, mode: str) -> dict:
    """Train a ``STEPS``-step job through a service on ``mode``'s broker; its report.json."""
    redis = start_redis(root / "redis") if mode == "redis" else None
    try:
        service = start_service(root / "service", broker_url=redis.url if redis else None)
        try:
            with service.client(timeout_s=120) as client:
                scene = upload_scene(client, scene_dir)
                response = client.post(f"/scenes/{scene['id']}/jobs", json={"max_iters": STEPS})
                assert response.status_code == 202, response.text
                job_id = response.json()["id"]
                wait_until_succeeded(service, client, job_id, TRAIN_TIMEOUT_S)
            reports = [p for p in service.data_dir.rglob("report.json") if job_id in p.as_posix()]
            assert len(reports) == 1, reports
            return json.loads(reports[0].read_text())
        finally:
            service.stop()
    finally:
        if redis is not None:
            redis.stop()


def _loop_configuration(report: dict) -> dict:
    """What decides how fast the loop runs: the process's compute environment, the C hash kernel and the compiled
    step (whether they ran, and the compile stage's account of its graphs)."""
    stages = {s["name"]: s for s in report["stages"]}
    return {
        "runtime": report["runtime"],
        "hash_kernel": stages["hash_kernel"]["ran"],
        "compile": (stages["compile"]["ran"], stages["compile"]["why"]),
        "corrections": stages["corrections"]["why"],
        "rays_per_step": report["throughput"]["rays_per_step"],
    }


@pytest.mark.parametrize("mode", ["embedded"])  # the train worker's process is the same behind Redis
def test_a_job_trained_by_a_worker_runs_its_loop_as_the_cli_does(mode, cli_report, captured_small_room, tmp_path):
    service_report = _train_through_service(tmp_path / mode, captured_small_room, mode)
    assert service_report["iteration"] == cli_report["iteration"] == STEPS
    expected = _loop_configuration(cli_report)
    assert expected["runtime"]["omp_wait_policy"] is None, "the CLI runs with OpenMP's default wait policy"
    assert expected["hash_kernel"] and expected["compile"][0], "the CLI's run uses the C kernel and compiles"
    assert _loop_configuration(service_report) == expected
