"""No poison job and no orphaned job (issue #22, items 4 and 5), against real processes: the uvicorn API, Celery
train workers (``python -m worker``) and, for the Redis loss, a real redis-server; all on loopback.

- A job whose worker dies on loading its scene (``VOXNERF_KILL_WORKER_ON_SCENE``, a setting only tests set:
  the worker SIGKILLs itself) is retried ``max_worker_deaths`` (3) times, then ends ``failed`` naming the last
  death (signal 9); the good job queued behind it succeeds.
- A job whose message was lost is re-sent by the API's sweep after ``resend_queued_after_s``: the API died
  between the row and the send (the row is written without a send), Redis lost its last second (the queue
  key is deleted after the send), a filesystem-queue consumer was killed after taking the message (the
  message file is moved where a consumer puts the message it takes, and left there).

"Ran exactly once" is the job store's ``attempt``: every worker that trains a job claims it first, which
increments ``attempt``; the re-sent copies of a message a worker did get are refused by the claim's fence
(the worker logs "nothing to do").
"""

from __future__ import annotations

import time

import httpx
import pytest
import redis as redis_client
from service_fixtures import Service, start_redis, start_service, upload_scene, wait_for, wait_until_final

from app.core import jobstore
from app.core.settings import Settings

pytestmark = pytest.mark.slow

TINY = {"max_iters": 2, "compile": False, "downscale": 4}
JOB_TIMEOUT_S = 240
RESEND_AFTER_S = 3
SETTINGS = {
    "VOXNERF_RESEND_QUEUED_AFTER_S": str(RESEND_AFTER_S),
    "VOXNERF_WORKER_LOST_WAIT_S": "1",  # a SIGKILLed worker is counted dead 1 s after, not 10
    "OMP_NUM_THREADS": "1",
}


def _store(service: Service) -> Settings:
    """Settings that read the service's own job store (the row written without a send)."""
    return Settings(_env_file=None, data_dir=service.data_dir)


def _submit(client: httpx.Client, scene_id: str) -> str:
    response = client.post(f"/scenes/{scene_id}/jobs", json=TINY)
    assert response.status_code == 202, response.text
    return response.json()["id"]


def _ran_once(service: Service, client: httpx.Client, job_id: str) -> None:
    job = wait_until_final(service, client, f"/jobs/{job_id}", JOB_TIMEOUT_S)
    assert job["state"] == "succeeded", f"{job['error']}\n{service.logs()}"
    assert job["attempt"] == 1 and job["requeues"] == 0  # one claim: every other copy was refused


def _start_train_worker(service: Service, kill_scene: str | None = None) -> None:
    if kill_scene is not None:
        service.env["VOXNERF_KILL_WORKER_ON_SCENE"] = kill_scene
    service.start_worker("train")
    wait_for(lambda: "ready" in (service.root / "worker-train.log").read_text(errors="replace"), 120,
             "the train worker to be ready")


# ------------------------------------------------------------------------------------------------ embedded


@pytest.fixture(scope="module")
def embedded(tmp_path_factory) -> Service:
    """API only (the train worker starts in the first test, once a message sits in the queue)."""
    svc = start_service(tmp_path_factory.mktemp("job-faults") / "embedded", settings=SETTINGS, workers=False)
    yield svc
    svc.stop()


@pytest.fixture(scope="module")
def client(embedded) -> httpx.Client:
    with embedded.client() as c:
        yield c


@pytest.fixture(scope="module")
def scenes(client, small_room) -> dict[str, str]:
    """Two uploads of the same room: ``poison`` kills the worker that loads it, ``good`` does not."""
    return {name: upload_scene(client, small_room)["id"] for name in ("poison", "good")}


def test_a_message_a_killed_filesystem_consumer_took_is_sent_again(embedded, client, scenes):
    job_id = _submit(client, scenes["good"])
    queue, claimed = embedded.data_dir / "broker" / "queue", embedded.data_dir / "broker" / "claimed"
    (message,) = list(queue.glob("*.train.msg"))
    message.rename(claimed / f"999999-{message.name}")  # where a consumer puts what it takes, then it died
    _start_train_worker(embedded, kill_scene=scenes["poison"])
    _ran_once(embedded, client, job_id)


def test_a_job_whose_message_was_never_sent_is_sent_by_the_sweep(embedded, client, scenes):
    job = jobstore.create_job(_store(embedded), scenes["good"], TINY)  # the API died before the send
    _ran_once(embedded, client, job.id)


def test_a_job_that_kills_its_worker_fails_after_three_deaths_and_the_queue_moves_on(embedded, client, scenes):
    poison = _submit(client, scenes["poison"])
    good = _submit(client, scenes["good"])
    failed = wait_until_final(embedded, client, f"/jobs/{poison}", JOB_TIMEOUT_S)
    assert failed["state"] == "failed", embedded.logs()
    assert failed["error"].startswith("the worker died 3 times while running this job (last: ")
    assert "signal 9" in failed["error"] and failed["attempt"] == 3
    _ran_once(embedded, client, good)


# ------------------------------------------------------------------------------------------------ Redis


@pytest.fixture(scope="module")
def redis(tmp_path_factory):
    server = start_redis(tmp_path_factory.mktemp("job-faults") / "redis")
    yield server
    server.stop()


@pytest.fixture(scope="module")
def with_redis(redis, tmp_path_factory) -> Service:
    svc = start_service(tmp_path_factory.mktemp("job-faults") / "redis-service", broker_url=redis.url,
                        settings=SETTINGS, workers=False)
    yield svc
    svc.stop()


def test_a_message_redis_lost_is_sent_again(with_redis, redis, small_room):
    with with_redis.client() as api:
        scene_id = upload_scene(api, small_room)["id"]
        job_id = _submit(api, scene_id)
        queue = redis_client.Redis.from_url(redis.url)
        assert queue.llen("train") == 1
        queue.delete("train")  # the last second before a crash, not yet on disk
        time.sleep(RESEND_AFTER_S)
        _start_train_worker(with_redis)
        _ran_once(with_redis, api, job_id)
