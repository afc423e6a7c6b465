"""The job store (app/core/jobstore.py) against a temporary SQLite database: scenes, claims and their fencing,
progress from the engine's ProgressEvent, final states from its TrainReport, stale jobs and requeueing."""

from __future__ import annotations

import sqlite3
import time

import pytest
from sqlalchemy import inspect

from app.core import db, jobstore, progress
from app.core.db import get_engine, session_scope
from app.core.models import JobRow
from app.core.settings import Settings
from voxnerf.training.records import EvalRecord, ProgressEvent, StageRecord, TrainReport

SCENE = "a" * 32


@pytest.fixture
def settings(tmp_path) -> Settings:
    s = Settings(data_dir=tmp_path / "data", stale_after_s=5.0)
    s.make_dirs()
    jobstore.add_scene(s, SCENE, "room", {"frames": 1}, 10)
    return s


def _running(settings: Settings, worker: str = "w:1") -> JobRow:
    job = jobstore.create_job(settings, SCENE, {"max_iters": 5})
    return jobstore.JOBS.claim(settings, job.id, worker)


def _age_lease(settings: Settings, job_id: str, seconds: float) -> None:
    with session_scope(settings) as session:
        session.get(JobRow, job_id).heartbeat_at = time.time() - seconds


def test_progress_columns_are_the_events_fields_but_max_iters():
    assert set(progress.PROGRESS_FIELDS) == set(ProgressEvent.model_fields) - {"max_iters"}
    columns = {c.name: c for c in JobRow.__table__.columns}
    for name in progress.PROGRESS_FIELDS:
        assert name in columns, name
        assert columns[name].nullable == progress.nullable(name), name
    assert columns["stage"].nullable and columns["eta_s"].nullable and not columns["iteration"].nullable


def test_tables_are_created_with_the_progress_columns(settings):
    names = {c["name"] for c in inspect(get_engine(settings)).get_columns("jobs")}
    assert set(progress.PROGRESS_FIELDS) <= names


def test_a_new_job_is_queued_with_initial_progress(settings):
    job = jobstore.JOBS.get(settings, jobstore.create_job(settings, SCENE, {"max_iters": 5}).id)
    assert job.state == "queued" and job.attempt == 0 and job.requeues == 0
    assert (job.progress, job.iteration, job.elapsed_s, job.history, job.stages) == (0.0, 0, 0.0, [], [])
    assert job.stage is None and job.eta_s is None and job.loss is None
    assert jobstore.create_job(settings, "b" * 32, {"max_iters": 5}) is None  # no such scene


def test_claims_are_fenced(settings):
    job = _running(settings, "w:1")
    assert (job.state, job.attempt, job.worker, job.stage) == ("running", 1, "w:1", "starting")
    assert jobstore.JOBS.claim(settings, job.id, "w:2") is None  # a fresh lease: not claimable
    _age_lease(settings, job.id, 10)
    taken = jobstore.JOBS.claim(settings, job.id, "w:2")
    assert (taken.attempt, taken.requeues, taken.worker) == (2, 1, "w:2")
    event = ProgressEvent(stage="train", iteration=3, progress=0.5)
    assert not jobstore.JOBS.record_progress(settings, job.id, 1, event)  # the first worker is fenced off
    assert not jobstore.JOBS.renew_lease(settings, job.id, 1).owned
    assert not jobstore.JOBS.finish(settings, job.id, 1, "failed", {"error": "late"})
    assert jobstore.JOBS.get(settings, job.id).state == "running"


def test_progress_is_written_from_the_events_fields(settings):
    job = _running(settings)
    history = [EvalRecord(elapsed_s=2.0, iteration=10, loss=0.1, psnr={"test": 20.5, "bad": float("nan")})]
    stages = [StageRecord(name="load_scene", ran=True, why="2 frames", seconds=0.5)]
    event = ProgressEvent(
        stage="train",
        iteration=10,
        max_iters=100,
        elapsed_s=float("nan"),  # a non-finite number never reaches the store; a non-null column keeps its default
        progress=0.1,
        eta_s=float("inf"),
        loss=0.25,
        history=history,
        stages=stages,
    )
    assert jobstore.JOBS.record_progress(settings, job.id, job.attempt, event)
    row = jobstore.JOBS.get(settings, job.id)
    assert (row.stage, row.iteration, row.progress, row.loss) == ("train", 10, 0.1, 0.25)
    assert row.elapsed_s == 0.0 and row.eta_s is None
    # history entries keep only the keys the engine set (as in report.json), NaN made null
    assert row.history == [{"elapsed_s": 2.0, "iteration": 10, "loss": 0.1, "psnr": {"test": 20.5, "bad": None}}]
    assert row.stages == [{"name": "load_scene", "ran": True, "why": "2 frames", "seconds": 0.5}]
    assert row.heartbeat_at > time.time() - 5


def _report(status: str, **fields) -> TrainReport:
    return TrainReport(
        status=status,
        config={"max_iters": 5},
        device="cpu",
        iteration=5,
        train_seconds=12.5,
        history=[EvalRecord(elapsed_s=12.5, iteration=5, psnr={"test": 21.0}, final=True)],
        stages=[StageRecord(name="train", ran=True, why=f"{status} at iteration 5", seconds=12.5)],
        **fields,
    )


def test_a_succeeded_report_finishes_the_job(settings):
    job = _running(settings)
    jobstore.JOBS.record_progress(settings, job.id, job.attempt, ProgressEvent(stage="train", iteration=4, loss=0.3))
    report = _report("succeeded", metrics={"test": {"psnr": 21.0, "ssim": float("nan")}})
    assert jobstore.finish_with_report(settings, job.id, job.attempt, report, progress=0.8)
    row = jobstore.JOBS.get(settings, job.id)
    assert (row.state, row.stage, row.progress, row.eta_s, row.iteration, row.elapsed_s) == (
        "succeeded", "done", 1.0, None, 5, 12.5
    )
    assert row.metrics == {"test": {"psnr": 21.0, "ssim": None}}
    assert row.history[-1]["final"] is True and row.stages[-1]["name"] == "train"
    assert row.loss == 0.3  # the last loss stays
    assert row.finished_at is not None
    assert not jobstore.finish_with_report(settings, job.id, job.attempt, report, progress=1.0)  # already final


def test_a_cancelled_report_keeps_the_progress_reached(settings):
    job = _running(settings)
    assert jobstore.finish_with_report(settings, job.id, job.attempt, _report("cancelled"), progress=0.4)
    row = jobstore.JOBS.get(settings, job.id)
    assert (row.state, row.stage, row.progress, row.metrics) == ("cancelled", "cancelled", 0.4, None)


def test_stale_jobs_are_requeued_once(settings):
    fresh = _running(settings, "w:1")
    stale = _running(settings, "w:2")
    _age_lease(settings, stale.id, 10)
    found = jobstore.JOBS.stale(settings)
    assert [j.id for j in found] == [stale.id]
    assert jobstore.JOBS.mark_requeued(settings, found) == [stale.id]
    assert jobstore.JOBS.mark_requeued(settings, found) == []  # the row changed since it was read
    row = jobstore.JOBS.get(settings, stale.id)
    assert (row.state, row.requeues, row.stage, row.worker) == ("queued", 1, "requeued", None)
    assert jobstore.JOBS.get(settings, fresh.id).state == "running"


def test_cancel_and_fail(settings):
    queued = jobstore.create_job(settings, SCENE, {"max_iters": 5})
    assert jobstore.JOBS.request_cancel(settings, queued.id).state == "cancelled"
    running = _running(settings)
    assert jobstore.JOBS.request_cancel(settings, running.id).cancel_requested
    assert jobstore.JOBS.renew_lease(settings, running.id, running.attempt).cancel_requested
    lost = jobstore.create_job(settings, SCENE, {"max_iters": 5})
    jobstore.JOBS.fail(settings, lost.id, "the broker refused the job")
    row = jobstore.JOBS.get(settings, lost.id)
    assert (row.state, row.error) == ("failed", "the broker refused the job")
    with pytest.raises(jobstore.SceneBusy):
        jobstore.delete_scene(settings, SCENE)



def test_a_database_from_an_earlier_version_gains_the_new_columns(tmp_path):
    """A jobs table made before a progress column existed: opening it adds the column, and its old row reads."""
    settings = Settings(data_dir=tmp_path)
    jobstore.add_scene(settings, SCENE, "room", {"frames": 1}, 10)
    job = jobstore.create_job(settings, SCENE, {"max_iters": 5})
    with sqlite3.connect(tmp_path / "voxnerf.sqlite") as conn:
        conn.execute("ALTER TABLE jobs DROP COLUMN loss_series")
    db._engines.clear()  # a new process opens the old database
    engine = get_engine(settings)
    assert "loss_series" in {c["name"] for c in inspect(engine).get_columns("jobs")}
    assert jobstore.JOBS.get(settings, job.id).loss_series is None  # read by JobOut as []
    assert db.add_missing_columns(engine) == []  # added once
