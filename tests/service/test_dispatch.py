"""Publishing (app/core/dispatch.py) on the embedded filesystem broker: train and render messages land in their
queues under their task names, a render expires, stale jobs are published again before they are marked, and the
sweep re-sends the message of a queued training or output job no worker took, but not one the broker (the
filesystem queue, a real redis-server) still holds."""

from __future__ import annotations

import base64
import json
import time

import pytest
from service_fixtures import start_redis

from app.core import jobstore, outputs
from app.core.celery_app import OUTPUTS_QUEUE, RENDER_QUEUE, RENDER_TASK, TRAIN_QUEUE, TRAIN_TASK, create_celery
from app.core.db import session_scope
from app.core.dispatch import requeue_stale, send, send_render, sweep_jobs
from app.core.models import JobRow, OutputRow
from app.core.settings import Settings


@pytest.fixture
def settings(tmp_path) -> Settings:
    s = Settings(data_dir=tmp_path / "data", stale_after_s=5.0)
    s.make_dirs()
    return s


def _messages(settings: Settings, queue: str) -> list[dict]:
    """The messages waiting in ``queue``: Celery's headers plus the decoded ``args``."""
    found = []
    for path in sorted((settings.broker_dir / "queue").glob(f"*.{queue}.msg")):
        message = json.loads(path.read_text())
        body = message["body"]
        if message["properties"].get("body_encoding") == "base64":
            body = base64.b64decode(body)
        args, _kwargs, _embed = json.loads(body)
        found.append({**message["headers"], "args": args})
    return found


def test_the_app_routes_by_task_name_on_the_configured_broker(settings):
    celery = create_celery(settings)
    assert celery.conf.broker_transport == "app.core.broker:Transport"
    assert celery.conf.task_routes[TRAIN_TASK] == {"queue": TRAIN_QUEUE}
    assert celery.conf.task_routes[RENDER_TASK] == {"queue": RENDER_QUEUE}
    redis = create_celery(settings.model_copy(update={"broker_url": "redis://127.0.0.1:1/0"}))
    assert redis.conf.broker_url == "redis://127.0.0.1:1/0"


def test_a_worker_counts_a_dead_task_lost_after_the_configured_wait(settings):
    assert create_celery(settings).conf.worker_lost_wait == 10.0  # Celery's own default
    assert create_celery(settings.model_copy(update={"worker_lost_wait_s": 1.5})).conf.worker_lost_wait == 1.5


def test_send_train_and_send_render_land_in_their_queues(settings):
    celery = create_celery(settings)
    send(celery, jobstore.JOBS, "j" * 32)
    send_render(celery, "r" * 32, "j" * 32, {"job_id": "j" * 32, "format": "png"}, expires_s=30)
    (train,) = _messages(settings, TRAIN_QUEUE)
    assert train["task"] == TRAIN_TASK and train["args"] == ["j" * 32]
    (render,) = _messages(settings, RENDER_QUEUE)
    assert render["task"] == RENDER_TASK
    assert render["args"] == ["r" * 32, "j" * 32, {"job_id": "j" * 32, "format": "png"}]
    assert render["expires"]  # a worker that gets it after the API gave up drops it


def _stale_job(settings: Settings) -> str:
    jobstore.add_scene(settings, "s" * 32, "room", {"frames": 1}, 10)
    job = jobstore.create_job(settings, "s" * 32, {"max_iters": 5})
    jobstore.JOBS.claim(settings, job.id, "gone:1")
    with session_scope(settings) as session:
        session.get(JobRow, job.id).heartbeat_at = time.time() - 60
    return job.id


def test_stale_jobs_are_published_then_marked(settings):
    celery = create_celery(settings)
    job_id = _stale_job(settings)
    assert requeue_stale(settings, celery, jobstore.JOBS) == [job_id]
    assert [m["args"] for m in _messages(settings, TRAIN_QUEUE)] == [[job_id]]
    assert jobstore.JOBS.get(settings, job_id).state == "queued"
    assert requeue_stale(settings, celery, jobstore.JOBS) == []  # nothing stale any more


def test_a_job_stays_stale_when_publishing_fails(settings, monkeypatch):
    celery = create_celery(settings)
    job_id = _stale_job(settings)

    def broker_down(*_args, **_kwargs):
        raise OSError("connection refused")

    monkeypatch.setattr(celery, "send_task", broker_down)
    with pytest.raises(OSError):
        requeue_stale(settings, celery, jobstore.JOBS)
    assert jobstore.JOBS.get(settings, job_id).state == "running"  # the next sweep tries again
    monkeypatch.undo()
    assert requeue_stale(settings, celery, jobstore.JOBS) == [job_id]


def test_a_render_worker_polls_the_embedded_queue_faster(settings):
    from app.core.celery_app import RENDER_QUEUE, TRAIN_QUEUE

    def interval(queues):
        return create_celery(settings, queues=queues).conf.broker_transport_options["polling_interval"]

    assert interval([TRAIN_QUEUE]) == settings.broker_polling_interval_s
    assert interval([TRAIN_QUEUE, RENDER_QUEUE]) == settings.render_polling_interval_s < interval([TRAIN_QUEUE])


def _queued_without_a_send(settings: Settings, kind: str) -> tuple[str, type, str]:
    """A queued row of ``kind`` whose message was never sent (the API died between the row and the send): its
    id, table and queue."""
    if kind == "train":
        jobstore.add_scene(settings, "s" * 32, "room", {"frames": 1}, 10)
        return jobstore.create_job(settings, "s" * 32, {"max_iters": 5}).id, JobRow, TRAIN_QUEUE
    row = outputs.create_output(settings, "j" * 32, "video", {"path": "orbit", "frames": 4}, 4, False)
    return row.id, OutputRow, OUTPUTS_QUEUE


@pytest.mark.parametrize("kind", ["train", "output"])
def test_a_queued_row_whose_message_was_lost_is_sent_again_by_the_sweep(settings, kind):
    """Training jobs and output jobs alike (issue #41: output jobs were never re-sent)."""
    celery = create_celery(settings)
    row_id, table, queue = _queued_without_a_send(settings, kind)
    sweep_jobs(settings, celery)
    assert _messages(settings, queue) == []  # just queued: its message may still be on its way
    with session_scope(settings) as session:  # resend_queued_after_s later, no worker has taken it
        session.get(table, row_id).heartbeat_at = time.time() - settings.resend_queued_after_s - 1
    sweep_jobs(settings, celery)
    assert [m["args"] for m in _messages(settings, queue)] == [[row_id]]
    sweep_jobs(settings, celery)  # noted as re-sent: not sent again before another resend_queued_after_s
    assert len(_messages(settings, queue)) == 1
    with session_scope(settings) as session:
        assert session.get(table, row_id).state == "queued"


def _lose_time(settings: Settings, table: type, row_id: str) -> None:
    """``resend_queued_after_s`` pass with the row still queued."""
    with session_scope(settings) as session:
        session.get(table, row_id).heartbeat_at = time.time() - settings.resend_queued_after_s - 1


@pytest.mark.parametrize("kind", ["train", "output"])
def test_a_queued_row_whose_message_waits_its_turn_gets_no_copy(settings, kind):
    """Issue #42: a row queued behind a long job gathered a copy of its message every resend_queued_after_s (one
    every 300 s behind a 24 h job), and the filesystem broker listed them all at every poll. Its one message
    waits in the queue: the sweep sees it there and sends nothing; once it is lost the sweep sends one."""
    celery = create_celery(settings)
    row_id, table, queue = _queued_without_a_send(settings, kind)
    send(celery, jobstore.JOBS if kind == "train" else outputs.OUTPUTS, row_id)
    for _ in range(3):
        _lose_time(settings, table, row_id)
        sweep_jobs(settings, celery)
        assert [m["args"] for m in _messages(settings, queue)] == [[row_id]]
    (message,) = (settings.broker_dir / "queue").glob(f"*.{queue}.msg")
    message.unlink()  # now it is lost
    _lose_time(settings, table, row_id)
    sweep_jobs(settings, celery)
    assert [m["args"] for m in _messages(settings, queue)] == [[row_id]]


@pytest.fixture
def redis_settings(tmp_path):
    server = start_redis(tmp_path / "redis")
    s = Settings(_env_file=None, data_dir=tmp_path / "data", broker_url=server.url)
    s.make_dirs()
    yield s
    server.stop()


def test_on_redis_a_waiting_message_gets_no_copy_and_a_lost_one_is_sent_again(redis_settings):
    import redis

    settings = redis_settings
    celery = create_celery(settings)
    row_id, table, queue = _queued_without_a_send(settings, "output")
    send(celery, outputs.OUTPUTS, row_id)
    server = redis.Redis.from_url(settings.broker_url)
    assert server.llen(queue) == 1
    for _ in range(3):
        _lose_time(settings, table, row_id)
        sweep_jobs(settings, celery)
        assert server.llen(queue) == 1
    server.delete(queue)  # Redis lost it (the last second before a crash)
    _lose_time(settings, table, row_id)
    sweep_jobs(settings, celery)
    (message,) = server.lrange(queue, 0, -1)
    assert json.loads(message)["headers"]["argsrepr"] == repr([row_id])
