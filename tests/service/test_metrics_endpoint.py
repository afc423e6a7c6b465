"""``GET /metrics`` and JSON logs (issue #44, item 5), through real HTTP: uvicorn, real Celery workers on the
embedded broker, ``VOXNERF_LOG_FORMAT=json``.

After a short training job, a render, a refused render and an export queued where no outputs worker runs, the
exposition (parsed by prometheus-client's own parser) counts the job as succeeded with its duration and stages,
the renders in the latency histogram by status, the upload's bytes, the export waiting in the ``outputs`` queue,
the live workers; it is refused without the token. The CPU workers report no device memory; a worker whose
``nvidia-smi`` (a script standing in for the GPU driver's tool: the only mock) reports one is exposed with it.
Every line the API and the workers logged parses as a JSON object, the job's lines name its ``job_id``.
"""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys

import httpx
import pytest
from prometheus_client.parser import text_string_to_metric_families
from service_fixtures import (
    REPO,
    first_pose,
    free_port,
    start_service,
    stop_process,
    wait_for,
    wait_until_succeeded,
    zip_scene,
)

pytestmark = pytest.mark.slow

TOKEN = "metrics-token"
FAKE_SMI = """#!/bin/sh
# stands in for the GPU driver's nvidia-smi: memory.used, memory.total in MiB
echo "1536, 81920"
"""


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    svc = start_service(tmp_path_factory.mktemp("metrics"), token=TOKEN, settings={"VOXNERF_LOG_FORMAT": "json"})
    try:
        yield svc
    finally:
        svc.stop()


@pytest.fixture(scope="module")
def worked(service, small_room):
    """The service after an upload, a short job, a render, a refused render and a queued export: what was sent."""
    archive = zip_scene(small_room)
    with service.client() as client:
        scene = client.post("/scenes", files={"file": ("room.zip", archive, "application/zip")}).json()
        job = client.post(f"/scenes/{scene['id']}/jobs", json={"max_iters": 6, "compile": False}).json()
        wait_until_succeeded(service, client, job["id"], 300)
        render = client.post("/render", json={"job_id": job["id"], "transform_matrix": first_pose(small_room),
                                              "width": 32, "height": 24})
        assert render.status_code == 200, render.text
        refused = client.post("/render", json={"job_id": "0" * 32, "transform_matrix": first_pose(small_room)})
        assert refused.status_code == 404
        export = client.post(f"/jobs/{job['id']}/exports", json={"kind": "pointcloud", "max_views": 2})
        assert export.status_code == 202, export.text
    return {"archive_bytes": len(archive), "job": job, "export": export.json()}


def _scrape(service) -> dict[tuple[str, tuple], float]:
    """``{(sample name, sorted labels): value}`` of ``GET /metrics``, parsed by prometheus-client."""
    with service.client() as client:
        response = client.get("/metrics")
    assert response.status_code == 200, response.text
    assert response.headers["content-type"].startswith("text/plain")
    samples = {}
    for family in text_string_to_metric_families(response.text):
        assert family.name.startswith("voxnerf_"), family.name
        for sample in family.samples:
            samples[(sample.name, tuple(sorted(sample.labels.items())))] = sample.value
    return samples


def _labels(**labels: str) -> tuple:
    return tuple(sorted(labels.items()))


def test_metrics_need_the_token(service):
    with service.client(auth=False) as client:
        response = client.get("/metrics")
    assert response.status_code == 401 and "bearer token" in response.json()["detail"]


def test_metrics_count_the_job_the_renders_the_upload_the_queue_and_the_workers(service, worked):
    samples = _scrape(service)
    assert samples[("voxnerf_jobs", _labels(kind="train", state="succeeded"))] == 1
    assert samples[("voxnerf_jobs", _labels(kind="train", state="failed"))] == 0
    assert samples[("voxnerf_jobs", _labels(kind="pointcloud", state="queued"))] == 1
    assert samples[("voxnerf_job_duration_seconds_count", _labels(kind="train", state="succeeded"))] == 1
    assert samples[("voxnerf_job_duration_seconds_sum", _labels(kind="train", state="succeeded"))] > 0
    stage_counts = {labels: v for (name, labels), v in samples.items()
                    if name == "voxnerf_stage_duration_seconds_count"}
    assert stage_counts and all(v == 1 for v in stage_counts.values()), stage_counts  # one finished job's stages

    assert samples[("voxnerf_render_seconds_count", _labels(status="200"))] == 1
    assert samples[("voxnerf_render_seconds_count", _labels(status="404"))] == 1
    assert samples[("voxnerf_render_seconds_bucket", _labels(status="200", le="+Inf"))] == 1
    assert 0 < samples[("voxnerf_render_seconds_sum", _labels(status="200"))] < 120
    assert samples[("voxnerf_upload_bytes_total", ())] >= worked["archive_bytes"]

    assert samples[("voxnerf_queue_messages", _labels(queue="outputs"))] == 1  # no outputs worker runs
    assert samples[("voxnerf_queue_messages", _labels(queue="train"))] == 0
    assert samples[("voxnerf_workers", _labels(queue="train"))] == 1
    assert samples[("voxnerf_workers", _labels(queue="render"))] == 1
    assert samples[("voxnerf_workers", _labels(queue="outputs"))] == 0
    assert samples[("voxnerf_up", _labels(component="database"))] == 1
    assert samples[("voxnerf_up", _labels(component="broker"))] == 1
    # CPU workers: no device memory at all
    assert not [key for key in samples if key[0].startswith("voxnerf_device_memory")]


def test_a_gpu_worker_reports_its_device_memory(service, worked, tmp_path):
    """A worker whose VOXNERF_DEVICE is cuda:0 and whose nvidia-smi answers (a script: this machine has no GPU)
    is exposed with that memory. It consumes the outputs queue; the export waiting there is cancelled first."""
    with service.client() as client:
        assert client.post(f"/outputs/{worked['export']['id']}/cancel").status_code == 202
    smi = tmp_path / "bin" / "nvidia-smi"
    smi.parent.mkdir()
    smi.write_text(FAKE_SMI)
    smi.chmod(smi.stat().st_mode | stat.S_IXUSR)
    service.start_worker("outputs", env={"VOXNERF_DEVICE": "cuda:0",
                                         "PATH": f"{smi.parent}{os.pathsep}{os.environ['PATH']}"})

    def reported():
        samples = _scrape(service)
        used = {labels: v for (name, labels), v in samples.items() if name == "voxnerf_device_memory_used_bytes"}
        return used and (used, samples)

    used, samples = wait_for(reported, 90, "the outputs worker's device memory in /metrics", 1.0)
    (labels, value), = used.items()
    assert dict(labels)["device"] == "cuda:0" and dict(labels)["worker"].startswith("outputs@")
    assert value == 1536 * 2**20
    assert samples[("voxnerf_device_memory_total_bytes", labels)] == 81920 * 2**20


def test_json_logs_are_one_object_per_line(service, worked):
    """Every line of the API's and the workers' logs is a JSON object with time, level, logger and message; the
    train worker's lines about the job name its id."""
    job_id = worked["job"]["id"]
    by_file = {}
    for name in ("api.log", "worker-train.log", "worker-render.log"):
        lines = [line for line in (service.root / name).read_text().splitlines() if line.strip()]
        assert lines, f"{name} is empty"
        entries = []
        for line in lines:
            try:
                entries.append(json.loads(line))
            except ValueError:
                pytest.fail(f"{name}: not a JSON line: {line[:300]}")
        for entry in entries:
            assert {"time", "level", "logger", "message"} <= set(entry), entry
        by_file[name] = entries
    train = by_file["worker-train.log"]
    assert any(entry.get("job_id") == job_id for entry in train), train[-5:]
    assert any("ready" in entry["message"] for entry in train)  # Celery's own lines go through it too


def test_the_api_served_by_app_serve_logs_json_uvicorn_included(tmp_path):
    """``python -m app.serve --api-only`` (the API image's entry) with JSON logs: uvicorn's own lines (its start,
    each request) are JSON objects like the app's, from start to a SIGTERM stop."""
    port = free_port()
    env = {k: v for k, v in os.environ.items() if not k.startswith("VOXNERF_")}
    env.update(VOXNERF_DATA_DIR=str(tmp_path / "data"), VOXNERF_DEVICE="cpu", VOXNERF_LOG_FORMAT="json",
               PYTHONPATH=str(REPO), PYTHONUNBUFFERED="1", NO_PROXY="127.0.0.1,localhost")
    log_path = tmp_path / "serve.log"
    with open(log_path, "wb") as log:
        serve = subprocess.Popen([sys.executable, "-m", "app.serve", "--api-only", "--port", str(port)], cwd=REPO,
                                 env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        wait_for(lambda: _answers(f"http://127.0.0.1:{port}/docs"), 60, "python -m app.serve to answer")
    finally:
        stop_process(serve)
    entries = [json.loads(line) for line in log_path.read_text().splitlines() if line.strip()]
    loggers = {entry["logger"] for entry in entries}
    assert {"uvicorn.error", "uvicorn.access"} <= loggers, loggers
    assert any("GET /docs" in entry["message"] for entry in entries if entry["logger"] == "uvicorn.access")


def _answers(url: str) -> bool:
    try:
        return httpx.get(url, timeout=5, trust_env=False).status_code == 200
    except httpx.HTTPError:
        return False
