"""Fault tolerance of the deployed service, against real processes: a redis-server with append-only
persistence, the uvicorn API and Celery worker processes (``python -m worker``), all on loopback.

First, without processes, the job store's rule for a stale job taken over by a worker. Then one service
for the module (two train workers, one render worker), the tests in this order: two workers share N jobs
and each job runs exactly once; a SIGKILLed worker's job is redelivered and resumes from its checkpoint;
Redis stopped and restarted (503 meanwhile, every accepted job finishes); the API restarted (jobs, scenes
and renders all still there); more concurrent renders than the limit (429).

The ground truth of "ran once" is the job store's ``attempt``: every worker that trains a job first claims it,
which increments ``attempt`` (a redelivered message for a finished job claims nothing). The worker logs'
"received" lines and each run's report.json (``resumed_from_iteration``) back it up.
"""

from __future__ import annotations

import json
import os
import re
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import imageio.v3 as iio
import pytest
import redis as redis_client
import torch
from service_fixtures import (
    RedisServer,
    Service,
    first_pose,
    start_redis,
    start_service,
    upload_scene,
    wait_for,
)

from app.core import jobstore
from app.core.db import session_scope
from app.core.models import JobRow
from app.core.settings import Settings

pytestmark = pytest.mark.slow

# A job of a few iterations on a 16x12 downscale of the 64x48 room: about 10-40 s on a loaded 2-core CPU,
# most of it set-up (prior, pseudo depth) and the final evaluation.
TINY = {"max_iters": 3, "compile": False, "downscale": 4}
JOB_TIMEOUT_S = 180
RENDER_LIMIT = 2
SERVICE_SETTINGS = {
    "VOXNERF_CHECKPOINT_EVERY_S": "0.5",  # a checkpoint every few iterations, so a killed job has one
    "VOXNERF_MAX_CONCURRENT_RENDERS": str(RENDER_LIMIT),
    "VOXNERF_RENDER_TIMEOUT_S": "20",
    "OMP_NUM_THREADS": "1",  # three torch processes share two cores
}
SHORT_RENDER_TIMEOUT_S = 8  # the render timeout of the 429 test's API
RECEIVED = re.compile(r"Task voxnerf\.train\[[0-9a-f-]+\] received")


@pytest.fixture(scope="module")
def redis(tmp_path_factory) -> RedisServer:
    server = start_redis(tmp_path_factory.mktemp("faults") / "redis", appendonly=True)
    yield server
    server.stop()


@pytest.fixture(scope="module")
def service(redis, tmp_path_factory) -> Service:
    svc = start_service(
        tmp_path_factory.mktemp("faults") / "service", broker_url=redis.url, settings=SERVICE_SETTINGS
    )
    try:
        svc.start_worker("train", name="train2")
        wait_for(lambda: len(_health(svc)["workers"]["train"]) == 2, 120, "two train workers in /healthz")
        yield svc
    finally:
        svc.stop()


@pytest.fixture(scope="module")
def client(service) -> httpx.Client:
    with service.client() as c:
        yield c


@pytest.fixture(scope="module")
def scene(client, small_room) -> dict:
    return upload_scene(client, small_room)


@pytest.fixture(scope="module")
def trained(service, client, scene) -> dict:
    """A succeeded tiny job (what the render requests use)."""
    job_id = _submit(client, scene)
    return _wait_job(service, client, job_id, lambda j: j["state"] == "succeeded")


def _health(service: Service) -> dict:
    try:
        return httpx.get(f"{service.base_url}/healthz", timeout=10, trust_env=False).json()
    except (httpx.HTTPError, ValueError):
        return {"workers": {"train": [], "render": []}}


def _submit(client: httpx.Client, scene: dict, options: dict = TINY) -> str:
    response = client.post(f"/scenes/{scene['id']}/jobs", json=options)
    assert response.status_code == 202, response.text
    return response.json()["id"]


def _job(client: httpx.Client, job_id: str) -> dict:
    response = client.get(f"/jobs/{job_id}")
    assert response.status_code == 200, response.text
    return response.json()


def _wait_job(service: Service, client: httpx.Client, job_id: str, until, timeout_s: float = JOB_TIMEOUT_S):
    """Poll the job until ``until(job)``; fails with the process logs on timeout or on ``failed``."""
    deadline = time.monotonic() + timeout_s
    while True:
        job = _job(client, job_id)
        if until(job):
            return job
        if job["state"] == "failed" or time.monotonic() > deadline:
            state = f"{job['state']} ({job['error']})"
            pytest.fail(f"job {job_id} is {state} after {timeout_s} s\n{service.logs()}")
        time.sleep(0.3)


def _store(service: Service) -> Settings:
    """Settings that read the service's own job store (for what the API does not show: the worker)."""
    return Settings(_env_file=None, data_dir=service.data_dir)


def _received(service: Service) -> int:
    """Training messages the train workers have received, from their logs."""
    logs = service.root.glob("worker-train*.log")
    return sum(len(RECEIVED.findall(path.read_text(errors="replace"))) for path in logs)


def _report(service: Service, job_id: str) -> dict:
    return json.loads((service.data_dir / "runs" / job_id / "report.json").read_text())


def _render_body(trained: dict, small_room: Path) -> dict:
    return {"job_id": trained["id"], "transform_matrix": first_pose(small_room)}


def test_a_worker_taking_over_a_stale_job_counts_one_requeue(tmp_path):
    """The sweep publishes before it marks the row; a worker that claims in between takes the job over."""
    settings = Settings(_env_file=None, data_dir=tmp_path / "data", stale_after_s=5.0)
    settings.make_dirs()
    jobstore.add_scene(settings, "a" * 32, "room", {"frames": 1}, 10)
    job = jobstore.create_job(settings, "a" * 32, {"max_iters": 5})
    jobstore.JOBS.claim(settings, job.id, "gone:1")
    with session_scope(settings) as session:  # the first worker went silent 10 s ago
        session.get(JobRow, job.id).heartbeat_at = time.time() - 10
    stale = jobstore.JOBS.stale(settings)
    taken = jobstore.JOBS.claim(settings, job.id, "here:2")
    assert (taken.state, taken.attempt, taken.requeues, taken.worker) == ("running", 2, 1, "here:2")
    assert jobstore.JOBS.mark_requeued(settings, stale) == []  # the sweep's late mark must not undo the claim
    assert jobstore.JOBS.get(settings, job.id).requeues == 1


def test_two_workers_finish_n_jobs_each_exactly_once(service, client, scene):
    received_before = _received(service)
    n_jobs = 4
    ids = [_submit(client, scene) for _ in range(n_jobs)]
    done = [_wait_job(service, client, job_id, lambda j: j["state"] == "succeeded") for job_id in ids]

    for job in done:
        assert (job["attempt"], job["requeues"], job["iteration"]) == (1, 0, TINY["max_iters"]), job["id"]
        assert "resumed_from_iteration" not in _report(service, job["id"])
    rows = [jobstore.JOBS.get(_store(service), job_id) for job_id in ids]
    assert len({row.worker for row in rows}) == 2, "both train workers should have trained jobs"
    assert any(
        a.worker != b.worker and a.started_at < b.finished_at and b.started_at < a.finished_at
        for a in rows
        for b in rows
    ), "the two workers never trained at the same time"
    assert _received(service) - received_before == n_jobs, "a training message was delivered twice"


def test_sigkilled_worker_job_is_redelivered_and_resumes_from_its_checkpoint(service, client, scene):
    options = {"max_iters": 24, "compile": False, "downscale": 4}
    job_id = _submit(client, scene, options)
    checkpoint = service.data_dir / "runs" / job_id / "checkpoint.pt"
    _wait_job(service, client, job_id, lambda j: j["state"] == "running" and checkpoint.is_file())
    saved_iteration = torch.load(checkpoint, map_location="cpu", weights_only=False)["iteration"]
    assert 0 < saved_iteration < options["max_iters"], "kill came too late: the job had (nearly) finished"

    owner = jobstore.JOBS.get(_store(service), job_id).worker  # host:pid of the Celery pool process
    group = os.getpgid(int(owner.rpartition(":")[2]))
    name = next(n for n, proc in service.procs.items() if proc.pid == group)
    service.kill(name)  # SIGKILL to the worker's whole process group: a crash, nothing acknowledged

    # The API's sweep sees the dead process, requeues the job and publishes it again; the other worker
    # takes it (the job is never left in "running").
    _wait_job(service, client, job_id, lambda j: j["requeues"] == 1, 60)
    service.start_worker("train", name=name)
    done = _wait_job(service, client, job_id, lambda j: j["state"] == "succeeded")
    assert (done["attempt"], done["requeues"], done["iteration"]) == (2, 1, options["max_iters"])
    assert _report(service, job_id)["resumed_from_iteration"] >= saved_iteration > 0
    assert jobstore.JOBS.get(_store(service), job_id).worker != owner
    wait_for(lambda: len(_health(service)["workers"]["train"]) == 2, 120, "the restarted train worker")


def test_redis_restart_answers_503_meanwhile_and_loses_no_accepted_job(
    service, client, scene, redis, trained, small_room
):
    ids = [_submit(client, scene) for _ in range(3)]  # two workers: two run, one waits in Redis

    def running_and_queued() -> bool:
        states = [_job(client, job_id)["state"] for job_id in ids]
        return "running" in states and "queued" in states

    wait_for(running_and_queued, JOB_TIMEOUT_S, "one job running and one waiting in the queue")
    redis.stop()
    try:
        known = {j["id"] for j in client.get("/jobs", params={"limit": 1000}).json()}  # the store needs no broker
        refused = client.post(f"/scenes/{scene['id']}/jobs", json=TINY)
        assert refused.status_code == 503, refused.text
        assert "job queue is unavailable" in refused.json()["detail"]
        (row,) = [j for j in client.get("/jobs", params={"limit": 1000}).json() if j["id"] not in known]
        assert row["state"] == "failed" and "the broker refused it" in row["error"], row  # it says why, not queued
        render = client.post("/render", json=_render_body(trained, small_room))
        assert render.status_code == 503, render.text
        assert "render queue is unavailable" in render.json()["detail"]
        assert render.headers["retry-after"] == "1"
        health = client.get("/healthz")
        assert health.status_code == 503 and not health.json()["broker"]["ok"]
        assert all(_job(client, job_id)["state"] in ("queued", "running", "succeeded") for job_id in ids)
    finally:
        redis.start()  # same port, same directory: the append-only file brings the queue back

    for job_id in ids:
        done = _wait_job(service, client, job_id, lambda j: j["state"] == "succeeded")
        assert (done["attempt"], done["requeues"]) == (1, 0), "a job accepted before the outage ran twice"
    service.wait_healthy()
    assert client.post("/render", json=_render_body(trained, small_room)).status_code == 200


def test_api_restart_keeps_jobs_scenes_and_renders(service, client, trained, small_room):
    scenes = client.get("/scenes").json()
    jobs = client.get("/jobs", params={"limit": 1000}).json()
    renders = client.get(f"/jobs/{trained['id']}/renders").json()
    assert renders, "the job has no evaluation renders"
    images = {r["url"]: client.get(r["url"]).content for r in renders}

    service.restart_api()

    with service.client() as fresh:
        assert fresh.get("/scenes").json() == scenes
        assert fresh.get("/jobs", params={"limit": 1000}).json() == jobs
        for scene in scenes:
            assert fresh.get(f"/scenes/{scene['id']}").json() == scene
        for job in jobs:
            assert fresh.get(f"/jobs/{job['id']}").json() == job
        assert fresh.get(f"/jobs/{trained['id']}/renders").json() == renders
        assert all(fresh.get(url).content == data for url, data in images.items())
        response = fresh.post("/render", json=_render_body(trained, small_room))
        assert response.status_code == 200, response.text
        evaluation = iio.imread(next(iter(images.values())))  # the job's views, at its downscale
        assert iio.imread(response.content).shape == evaluation.shape


def test_renders_above_the_limit_are_refused_with_429(service, redis, trained, small_room):
    # The module's last test: the API restarts with a shorter render timeout, the wait for the renders it lets
    # time out (the module's 20 s are for the first render of a cold worker), still several seconds for the refusals.
    service.env["VOXNERF_RENDER_TIMEOUT_S"] = str(SHORT_RENDER_TIMEOUT_S)
    service.restart_api()
    service.kill("render")  # renders now wait in the queue: they stay in progress until they time out
    body = _render_body(trained, small_room)
    queue = redis_client.Redis(port=redis.port)

    def post(payload: dict) -> httpx.Response:
        with service.client(timeout_s=60) as c:
            return c.post("/render", json=payload)

    with ThreadPoolExecutor(RENDER_LIMIT) as pool:
        waiting = [pool.submit(post, body) for _ in range(RENDER_LIMIT)]
        wait_for(lambda: queue.llen("render") == RENDER_LIMIT, 30, f"{RENDER_LIMIT} renders in the queue")
        started = time.perf_counter()
        refused = post(body)
        assert time.perf_counter() - started < 5, "a render above the limit must be refused at once"
        assert refused.status_code == 429, refused.text
        assert refused.headers["retry-after"] == "1"
        assert f"{RENDER_LIMIT} renders are already in progress" in refused.json()["detail"]
        assert post({**body, "job_id": "f" * 32}).status_code == 429  # refused before any other work
        timed_out = [future.result() for future in waiting]
    assert [r.status_code for r in timed_out] == [504] * RENDER_LIMIT
    assert all("no render worker answered" in r.json()["detail"] for r in timed_out)

    assert post({**body, "job_id": "f" * 32}).status_code == 404, "slots are released after each render"
    # The restarted worker's first render loads the model cold, which can take longer than the short timeout on
    # a loaded machine: the API goes back to the module's timeout before it is asked for one.
    service.env["VOXNERF_RENDER_TIMEOUT_S"] = SERVICE_SETTINGS["VOXNERF_RENDER_TIMEOUT_S"]
    service.restart_api()
    service.start_worker("render")
    wait_for(lambda: _health(service)["workers"]["render"], 120, "the restarted render worker")
    rendered = post(body)
    assert rendered.status_code == 200, f"{rendered.text}\n{service.logs()}"
