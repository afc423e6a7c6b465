"""A job's event log (app/core/events.py) against a temporary SQLite database: each change of the lease lifecycle
appends its events in order (stages and evaluations before the job's snapshot), state events only when the state
moves, progress events thinned, a deleted job's events gone; webhook deliveries beside the state events of a job
with a callback URL."""

from __future__ import annotations

import pytest

from app.core import events, jobstore
from app.core.db import session_scope
from app.core.models import JobEventRow
from app.core.settings import Settings
from app.core.tokens import Principal
from voxnerf.training.records import EvalRecord, ProgressEvent, StageRecord, TrainReport

SCENE = "a" * 32


@pytest.fixture
def settings(tmp_path) -> Settings:
    s = Settings(data_dir=tmp_path / "data", stale_after_s=5.0)
    s.make_dirs()
    jobstore.add_scene(s, SCENE, "room", {"frames": 1}, 10)
    return s


def _log(settings: Settings, job_id: str) -> list[tuple[int, str, object]]:
    """``(seq, kind, state or stage name or iteration)`` of each event of the job."""
    described = []
    for event in events.events_after(settings, job_id, 0):
        detail = {"state": "state", "progress": "state", "stage": "name", "evaluation": "iteration"}[event.kind]
        described.append((event.seq, event.kind, event.data[detail]))
    return described


def test_a_jobs_lifecycle_is_logged_in_order(settings):
    job = jobstore.create_job(settings, SCENE, {"max_iters": 5})
    claimed = jobstore.JOBS.claim(settings, job.id, "w:1")
    stage = StageRecord(name="prior", ran=True, why="given", seconds=1.5)
    point = EvalRecord(elapsed_s=2.0, iteration=3, psnr={"test": 20.0})
    jobstore.JOBS.record_progress(settings, job.id, claimed.attempt,
                                  ProgressEvent(stage="train", iteration=3, stages=[stage], history=[point]))
    jobstore.JOBS.record_progress(settings, job.id, claimed.attempt,
                                  ProgressEvent(stage="train", iteration=4, stages=[stage], history=[point]))
    updated = stage.model_copy(update={"seconds": 2.5})  # the engine updates some stage records in place
    jobstore.JOBS.record_progress(settings, job.id, claimed.attempt,
                                  ProgressEvent(stage="train", iteration=4, stages=[updated], history=[point]))
    final = EvalRecord(elapsed_s=3.0, iteration=5, psnr={"test": 21.0}, final=True)
    report = TrainReport(status="succeeded", config={"max_iters": 5}, device="cpu", iteration=5, train_seconds=3.0,
                         history=[point, final], stages=[updated])
    assert jobstore.finish_with_report(settings, job.id, claimed.attempt, report, 1.0)
    assert _log(settings, job.id) == [
        (1, "state", "queued"), (2, "state", "running"),
        (3, "stage", "prior"), (4, "evaluation", 3), (5, "progress", "running"),
        (6, "progress", "running"),
        (7, "stage", "prior"), (8, "progress", "running"),
        (9, "evaluation", 5), (10, "state", "succeeded"),
    ]
    last = events.last_event(settings, job.id)
    assert last.data["stage"] == "done" and last.data["progress"] == 1.0
    assert events.job_from_columns(last.data).state == "succeeded"


def test_cancels_failures_and_requeues_are_state_events(settings):
    queued = jobstore.create_job(settings, SCENE, {"max_iters": 5})
    jobstore.JOBS.request_cancel(settings, queued.id)
    assert [kind_state[1:] for kind_state in _log(settings, queued.id)] == [("state", "queued"),
                                                                          ("state", "cancelled")]
    running = jobstore.create_job(settings, SCENE, {"max_iters": 5})
    jobstore.JOBS.claim(settings, running.id, "w:1")
    jobstore.JOBS.request_cancel(settings, running.id)
    jobstore.JOBS.request_cancel(settings, running.id)  # the flag is set already: nothing changes
    stale = jobstore.JOBS.get(settings, running.id)
    assert jobstore.JOBS.mark_requeued(settings, [stale]) == [running.id]
    jobstore.JOBS.fail(settings, running.id, "the broker refused it")
    assert [entry[1:] for entry in _log(settings, running.id)] == [
        ("state", "queued"), ("state", "running"), ("progress", "running"), ("state", "queued"), ("state", "failed"),
    ]


def test_taking_over_a_stale_running_job_is_no_state_change(settings):
    job = jobstore.create_job(settings, SCENE, {"max_iters": 5})
    jobstore.JOBS.claim(settings, job.id, "w:1")
    with session_scope(settings) as session:
        session.get(jobstore.JobRow, job.id).heartbeat_at = 0.0
    assert jobstore.JOBS.claim(settings, job.id, "w:2").attempt == 2
    assert [entry[1:] for entry in _log(settings, job.id)] == [
        ("state", "queued"), ("state", "running"), ("progress", "running"),
    ]


def test_progress_events_are_thinned_and_a_deleted_jobs_events_go(settings, monkeypatch):
    monkeypatch.setattr(events, "PROGRESS_EVENTS_KEPT", 3)
    job = jobstore.create_job(settings, SCENE, {"max_iters": 50})
    claimed = jobstore.JOBS.claim(settings, job.id, "w:1")
    for iteration in range(1, 11):
        jobstore.JOBS.record_progress(settings, job.id, claimed.attempt,
                                      ProgressEvent(stage="train", iteration=iteration))
    kept = events.events_after(settings, job.id, 0)
    assert [(e.seq, e.kind) for e in kept] == [(1, "state"), (2, "state"), (10, "progress"), (11, "progress"),
                                               (12, "progress")]
    assert kept[-1].data["iteration"] == 10
    jobstore.JOBS.finish(settings, job.id, claimed.attempt, "cancelled", {})
    assert jobstore.delete_job(settings, job.id) == []
    with session_scope(settings) as session:
        assert session.query(JobEventRow).filter_by(job_id=job.id).count() == 0


def test_a_job_with_a_callback_url_gets_one_delivery_per_state_event(settings):
    job = jobstore.create_job(settings, SCENE, {"max_iters": 5}, Principal(name="ci", scope="write"),
                              callback_url="https://hooks.example/x")
    claimed = jobstore.JOBS.claim(settings, job.id, "w:1")
    jobstore.JOBS.record_progress(settings, job.id, claimed.attempt, ProgressEvent(stage="train", iteration=1))
    jobstore.JOBS.finish(settings, job.id, claimed.attempt, "failed", {"error": "boom"})
    deliveries = events.deliveries_of(settings, job.id)
    assert [(d.event_seq, d.state, d.outcome) for d in deliveries] == [
        (1, "queued", "pending"), (2, "running", "pending"), (4, "failed", "pending"),
    ]
    assert jobstore.JOBS.get(settings, job.id).created_by == "ci"
    taken = events.take_due_deliveries(settings, lease_s=30.0)
    assert [d.event_seq for d in taken] == [1, 2, 4]
    assert events.take_due_deliveries(settings, lease_s=30.0) == []  # taken: not due again until the lease ends
    events.record_attempt(settings, taken[0], 500, "HTTP 500", retry_after_s=0.0)
    events.record_attempt(settings, taken[1], 204, None, retry_after_s=None)
    events.record_attempt(settings, taken[2], None, "connection refused", retry_after_s=None)
    first, second, third = events.deliveries_of(settings, job.id)
    assert (first.outcome, first.attempts, first.log[0]["status"]) == ("pending", 1, 500)
    assert (second.outcome, third.outcome) == ("delivered", "abandoned")
    assert [d.id for d in events.take_due_deliveries(settings, lease_s=30.0)] == [first.id]


def test_a_job_that_ended_before_its_log_existed_gets_its_final_state_event(settings):
    job = jobstore.create_job(settings, SCENE, {"max_iters": 5})
    with session_scope(settings) as session:  # as a database of an earlier version holds it: no events
        session.query(JobEventRow).filter_by(job_id=job.id).delete()
        session.get(jobstore.JobRow, job.id).state = "failed"
    events.complete_log(settings, job.id)
    events.complete_log(settings, job.id)  # once only
    assert _log(settings, job.id) == [(1, "state", "failed")]
