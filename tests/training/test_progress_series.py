"""What the job page plots and links, below the browser: the training-loss series (voxnerf/training/records.py
LossSeries, kept by ProgressEvents and joined across attempts by app/core/jobstore.py), the front-loaded
progress-evaluation schedule and its stage record (voxnerf/training/callbacks.py), and the report and checkpoint
downloads (app/routes/jobs.py)."""

from __future__ import annotations

import json

import pytest
from fastapi.testclient import TestClient

from app.core import jobstore
from app.core.settings import Settings
from app.main import create_app
from voxnerf.config import TrainConfig
from voxnerf.files import CHECKPOINT, REPORT
from voxnerf.training.budget import Budget
from voxnerf.training.callbacks import (
    EARLY_EVAL_MAX_SHARE,
    PROGRESS_EVALS_STAGE,
    ProgressEvaluation,
    ProgressEvents,
    next_progress_eval,
    seconds_list,
)
from voxnerf.training.loop import LoopState
from voxnerf.training.records import LossSeries, ProgressEvent, TrainReport, merge_pairs, thin_series

SCENE = "a" * 32


class FakeClock:
    def __init__(self, now: float = 0.0) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now


# ------------------------------------------------------------------------------------------- loss series


def test_a_point_holds_the_mean_loss_of_its_steps_and_waits_for_the_gap():
    series = LossSeries(gap=1.0)
    assert not series.close(0.5)  # no step yet
    for loss in (1.0, 3.0, float("nan"), float("inf")):  # non-finite losses are left out
        series.add(loss)
    assert series.close(1.0) and series.points == [(1.0, 2.0)]
    series.add(5.0)
    assert not series.close(1.5)  # under the gap: the step waits for the next point
    series.add(7.0)
    assert series.close(2.0) and series.points[-1] == (2.0, 6.0)


def test_the_series_stays_bounded_evenly_spaced_and_keeps_its_start():
    series = LossSeries(max_points=300, gap=1.0)
    for second in range(1, 2001):
        series.add(float(second))
        series.close(float(second))
    points = series.points
    assert 150 <= len(points) <= 300
    assert points[0] == (1.0, 1.0) and points[-1][0] >= 1990.0
    gaps = {round(b[0] - a[0]) for a, b in zip(points[1:], points[2:], strict=False)}
    assert gaps <= {series.gap, series.gap / 2} and series.gap == 8.0


def test_merging_pairs_keeps_the_first_point_and_means_the_rest():
    points = [(1.0, 10.0), (2.0, 2.0), (3.0, 4.0), (4.0, 6.0), (5.0, 8.0), (6.0, 1.0)]
    assert merge_pairs(points) == [(1.0, 10.0), (3.0, 3.0), (5.0, 7.0), (6.0, 1.0)]
    assert len(thin_series(points * 100, max_points=50)) <= 50


def test_a_series_needs_room_for_three_points():
    with pytest.raises(ValueError, match="max_points"):
        LossSeries(max_points=2)


def test_progress_events_carry_the_series_and_the_report_keeps_it():
    clock, sent = FakeClock(100.0), []
    budget = Budget(None, clock=clock)
    report = TrainReport(config={}, device="cpu")
    events = ProgressEvents(sent.append, TrainConfig(max_iters=100), budget, report, clock=clock)
    for step in range(1, 9):  # 4 s of 0.5 s steps, the loss halving every second
        clock.now += 0.5
        events.after_step(LoopState(step, last_loss=0.5 ** ((step - 1) // 2)))
    assert [p[0] for p in sent[-1].loss_series] == [0.5, 1.5, 2.5, 3.5]
    assert sent[-1].loss_series[1][1] == pytest.approx(0.75)  # the mean of the steps since the first point
    assert report.loss_series == sent[-1].loss_series and "loss_series" in report.to_json_dict()


def test_without_a_listener_the_report_still_gets_the_series():
    clock = FakeClock()
    report = TrainReport(config={}, device="cpu")
    events = ProgressEvents(None, TrainConfig(max_iters=10), Budget(None, clock=clock), report, clock=clock)
    clock.now = 2.0
    events.after_step(LoopState(1, last_loss=0.25))
    assert report.loss_series == [(2.0, 0.25)]


# ------------------------------------------------------------------------------------------- the schedule


@pytest.mark.parametrize(("after", "every", "expected"), [
    (0.0, 60.0, 10.0), (10.0, 60.0, 20.0), (30.0, 60.0, 45.0), (45.0, 60.0, 60.0), (60.0, 60.0, 120.0),
    (0.0, 25.0, 10.0), (20.0, 25.0, 25.0), (0.0, 8.0, 8.0), (16.5, 8.0, 24.0), (100.0, 60.0, 120.0),
])
def test_progress_evaluations_come_early_then_every_eval_every_s(after, every, expected):
    assert next_progress_eval(after, every) == pytest.approx(expected)


def test_long_lists_of_seconds_are_shortened():
    assert seconds_list([10, 20.4]) == "10, 20"
    assert seconds_list(list(range(0, 1000, 60)), most=5) == "0, 60, 120, …, 960"


def _evaluation(spent: float, report: TrainReport, every: float = 60.0):
    clock = FakeClock()
    budget = Budget(1000.0, clock=clock)
    cfg = TrainConfig(max_iters=10, eval_every_s=every, compile=False)
    events = ProgressEvents(None, cfg, budget, report, clock=clock)
    calls = []

    def evaluate(iteration, loss, full):  # takes `spent` seconds of the clock
        calls.append(budget.train_seconds)
        clock.now += spent
        return spent, 1e-4

    return ProgressEvaluation(evaluate, budget, cfg, 1000, events), calls, budget, clock


def _train_until(evaluation, budget, clock, train_seconds: float) -> None:
    """Step the clock in 0.5 s steps until ``train_seconds`` of training time (paused time left out)."""
    while budget.train_seconds < train_seconds:
        evaluation.before_step(LoopState(1, last_loss=0.1))
        clock.now += 0.5


def test_cheap_early_evaluations_all_run_and_the_stage_says_when_and_what_they_cost():
    report = TrainReport(config={}, device="cpu")
    evaluation, calls, budget, clock = _evaluation(0.5, report)
    _train_until(evaluation, budget, clock, 130.0)
    assert [round(t) for t in calls] == [10, 20, 30, 45, 60, 120]
    (record,) = [s for s in report.stages if s.name == PROGRESS_EVALS_STAGE]
    assert record.ran and record.seconds == pytest.approx(3.0)
    assert record.why.startswith("6 progress evaluations of up to 4 views per split at 10, 20, 30, 45, 60, 120 s")
    assert "skipped" not in record.why
    assert budget.paused == pytest.approx(3.0)


def test_dear_early_evaluations_are_skipped_and_the_stage_says_so():
    report = TrainReport(config={}, device="cpu")
    evaluation, calls, budget, clock = _evaluation(2.0, report)  # 2 s each: at 20 s, 4 s > 15% of 20 s
    _train_until(evaluation, budget, clock, 70.0)
    assert EARLY_EVAL_MAX_SHARE == 0.15
    assert [round(t) for t in calls] == [10, 30, 45, 60]  # at 30 s: 4 s <= 4.5 s; at 45 s: 6 s <= 6.75 s
    (record,) = [s for s in report.stages if s.name == PROGRESS_EVALS_STAGE]
    assert "early one(s) at 20 s skipped" in record.why and record.seconds == pytest.approx(8.0)


def test_no_progress_evaluation_no_stage():
    report = TrainReport(config={}, device="cpu")
    evaluation, calls, budget, clock = _evaluation(0.5, report)
    _train_until(evaluation, budget, clock, 9.0)
    assert calls == [] and report.stages == []


# ------------------------------------------------------------------------------------------- the job store


@pytest.fixture
def settings(tmp_path) -> Settings:
    s = Settings(data_dir=tmp_path / "data")
    s.make_dirs()
    jobstore.add_scene(s, SCENE, "room", {"frames": 1}, 10)
    return s


def test_joined_series_keeps_an_earlier_attempts_points_before_the_resumed_ones():
    earlier = [[1.0, 0.9], [2.0, 0.8], [3.0, 0.7], [4.0, 0.6]]  # the attempt died at 4 s, its checkpoint at 2.5 s
    resumed = [(2.8, 0.75), (3.8, 0.65)]
    assert jobstore.joined_series(earlier, resumed) == [(1.0, 0.9), (2.0, 0.8), *resumed]
    assert jobstore.joined_series(earlier, []) == earlier
    assert jobstore.joined_series(None, resumed) == resumed
    assert len(jobstore.joined_series([[float(s), 1.0] for s in range(400)], [(400.0, 1.0)])) <= 300


def test_the_job_row_keeps_the_series_across_a_requeue(settings):
    job = jobstore.JOBS.claim(settings, jobstore.create_job(settings, SCENE, {"max_iters": 5}).id, "w:1")
    first = ProgressEvent(stage="train", loss_series=[(1.0, 0.5), (2.0, 0.4), (3.0, 0.3)])
    assert jobstore.JOBS.record_progress(settings, job.id, job.attempt, first)
    jobstore.JOBS.mark_requeued(settings, [jobstore.JOBS.get(settings, job.id)])
    again = jobstore.JOBS.claim(settings, job.id, "w:2")
    resumed = ProgressEvent(stage="train", loss_series=[(2.5, 0.35)])
    assert jobstore.JOBS.record_progress(settings, job.id, again.attempt, resumed)
    assert jobstore.JOBS.get(settings, job.id).loss_series == [[1.0, 0.5], [2.0, 0.4], [2.5, 0.35]]
    report = TrainReport(config={}, device="cpu", status="succeeded", iteration=5, train_seconds=4.0,
                         loss_series=[(2.5, 0.35), (3.5, 0.2)])
    assert jobstore.finish_with_report(settings, job.id, again.attempt, report, 1.0)
    assert jobstore.JOBS.get(settings, job.id).loss_series == [[1.0, 0.5], [2.0, 0.4], [2.5, 0.35], [3.5, 0.2]]


# ------------------------------------------------------------------------------------------- downloads


def _finished_job(settings: Settings, state: str) -> str:
    job = jobstore.JOBS.claim(settings, jobstore.create_job(settings, SCENE, {"max_iters": 5}).id, "w:1")
    if state != "running":
        jobstore.JOBS.finish(settings, job.id, job.attempt, state, {})
    return job.id


def test_report_and_checkpoint_downloads(settings):
    done, running = _finished_job(settings, "succeeded"), _finished_job(settings, "running")
    for job_id in (done, running):
        run = settings.runs_dir / job_id
        run.mkdir(parents=True)
        (run / REPORT).write_text(json.dumps({"status": "succeeded", "config": {"max_iters": 5}}))
        (run / CHECKPOINT).write_bytes(b"weights")
    with TestClient(create_app(settings)) as client:
        report = client.get(f"/jobs/{done}/report")
        assert report.status_code == 200 and report.json()["config"] == {"max_iters": 5}
        assert "report-" in report.headers["content-disposition"]
        checkpoint = client.get(f"/jobs/{done}/checkpoint")
        assert checkpoint.status_code == 200 and checkpoint.content == b"weights"
        busy = client.get(f"/jobs/{running}/checkpoint")
        assert busy.status_code == 409 and "running" in busy.json()["detail"]


def test_missing_report_and_checkpoint_are_404_and_unknown_jobs_too(settings):
    failed = _finished_job(settings, "failed")
    with TestClient(create_app(settings)) as client:
        report = client.get(f"/jobs/{failed}/report")
        assert report.status_code == 404 and "no report.json" in report.json()["detail"]
        checkpoint = client.get(f"/jobs/{failed}/checkpoint")
        assert checkpoint.status_code == 404 and "no checkpoint" in checkpoint.json()["detail"]
        assert client.get(f"/jobs/{'f' * 32}/report").status_code == 404
        assert client.get(f"/jobs/{'f' * 32}/checkpoint").status_code == 404
        assert client.get("/jobs/not-an-id/report").status_code == 422
