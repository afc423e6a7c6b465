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
    FIRST_PROGRESS_EVAL_RAYS,
    MIN_PROGRESS_EVAL_RAYS,
    PASSED_LISTED,
    PROGRESS_EVAL_SHARE,
    PROGRESS_EVALS_STAGE,
    ProgressEvaluation,
    ProgressEvents,
    next_progress_eval,
    progress_eval_count,
    progress_eval_times,
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
    budget.start_training()
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
    budget = Budget(None, clock=clock)
    budget.start_training()
    events = ProgressEvents(None, TrainConfig(max_iters=10), budget, report, clock=clock)
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


def _evaluation(report: TrainReport, per_ray: float, max_seconds: float | None = 1000.0, every: float = 60.0,
                view_rays: int = 100_000):
    """A progress evaluation on a fake clock whose evaluations take ``per_ray`` seconds per ray they score."""
    clock = FakeClock()
    budget = Budget(max_seconds, clock=clock)
    budget.start_training()
    cfg = TrainConfig(max_iters=10, eval_every_s=every, compile=False)
    events = ProgressEvents(None, cfg, budget, report, clock=clock)
    calls = []

    def evaluate(iteration, loss, rays):
        calls.append((budget.train_seconds, rays))
        spent = rays * per_ray
        clock.now += spent
        return spent, per_ray

    return ProgressEvaluation(evaluate, budget, cfg, view_rays, events), calls, budget, clock


def _train_until(evaluation, budget, clock, train_seconds: float | None = None) -> None:
    """Step the clock in 0.5 s steps until ``train_seconds`` of training time (paused time left out), or until the
    budget is spent."""
    while (budget.train_seconds < train_seconds) if train_seconds is not None else budget.remaining() > 0:
        evaluation.before_step(LoopState(1, last_loss=0.1))
        clock.now += 0.5


def test_cheap_progress_evaluations_score_every_pixel_and_the_stage_says_when_and_what_they_cost():
    report = TrainReport(config={}, device="cpu")
    evaluation, calls, budget, clock = _evaluation(report, per_ray=1e-7, view_rays=10_000)
    _train_until(evaluation, budget, clock, 130.0)
    assert [round(t) for t, _ in calls] == [10, 20, 30, 45, 60, 120]
    assert [rays for _, rays in calls] == [FIRST_PROGRESS_EVAL_RAYS] + [10_000] * 5
    (record,) = [s for s in report.stages if s.name == PROGRESS_EVALS_STAGE]
    assert record.ran and record.seconds == round(1e-7 * (2048 + 50_000), 3)
    assert record.why.startswith("6 progress evaluations at 10, 20, 30, 45, 60, 120 s of training, of 2048-10000 "
                                 "rays over up to 4 views per split (10000 pixels): sized to 2% of max_seconds")
    assert "skipped" not in record.why
    assert budget.parts["progress_evals"] == pytest.approx(1e-7 * (2048 + 50_000))


def test_dear_progress_evaluations_are_subsampled_to_keep_within_their_share_of_the_budget():
    """At 1e-4 s per ray every pixel of the progress views (10 s) would take five times the 2 s that 2 % of a
    100 s budget allows: each scores about 4000 rays instead, and all of them fit in the share."""
    report = TrainReport(config={}, device="cpu")
    evaluation, calls, budget, clock = _evaluation(report, per_ray=1e-4, max_seconds=100.0)
    _train_until(evaluation, budget, clock)
    assert [round(t) for t, _ in calls] == [10, 20, 30, 45, 60]
    assert all(MIN_PROGRESS_EVAL_RAYS <= rays < 100_000 for _, rays in calls)
    assert budget.parts["progress_evals"] <= PROGRESS_EVAL_SHARE * 100.0 + 1e-9
    assert budget.parts["progress_evals"] > 0.9 * PROGRESS_EVAL_SHARE * 100.0  # the share is used, not wasted
    assert budget.train_seconds >= (1 - PROGRESS_EVAL_SHARE) * 100.0 - 0.5  # the rest trained (0.5 s steps)


def test_progress_evaluations_too_dear_even_when_subsampled_are_skipped_and_the_stage_says_so():
    report = TrainReport(config={}, device="cpu")
    evaluation, calls, budget, clock = _evaluation(report, per_ray=1e-3, max_seconds=100.0)
    _train_until(evaluation, budget, clock)
    assert calls == [(10.0, FIRST_PROGRESS_EVAL_RAYS)]  # 2.05 s: nothing of the 2 s share is left for the next
    (record,) = [s for s in report.stages if s.name == PROGRESS_EVALS_STAGE]
    assert record.why.endswith("; at 20, 30, 45, 60 s skipped: fewer than 2048 rays were left within 2% of "
                               "max_seconds")
    assert budget.parts["progress_evals"] == pytest.approx(2.048)


def test_a_scene_whose_progress_views_are_smaller_than_the_minimum_still_evaluates_them():
    report = TrainReport(config={}, device="cpu")
    evaluation, calls, budget, clock = _evaluation(report, per_ray=1e-5, max_seconds=60.0, view_rays=500)
    _train_until(evaluation, budget, clock)
    assert [rays for _, rays in calls] == [500] * 4  # 10, 20, 30 and 45 s, each 5 ms of the 1.2 s share


def test_without_max_seconds_every_pixel_is_scored_however_dear():
    report = TrainReport(config={}, device="cpu")
    evaluation, calls, budget, clock = _evaluation(report, per_ray=1e-4, max_seconds=None)
    _train_until(evaluation, budget, clock, 70.0)
    assert [rays for _, rays in calls] == [100_000] * 5
    (record,) = [s for s in report.stages if s.name == PROGRESS_EVALS_STAGE]
    assert "every pixel of them (no max_seconds to size them to" in record.why


def test_no_progress_evaluation_no_stage():
    report = TrainReport(config={}, device="cpu")
    evaluation, calls, budget, clock = _evaluation(report, per_ray=1e-7)
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


def test_due_times_one_step_went_past_are_said_and_the_latest_is_evaluated():
    """A step of 12 s (a loaded machine) goes past the 10 and 20 s due times: the evaluation before the next step
    stands for 20 s, and the stage says 10 s was not run."""
    report = TrainReport(config={}, device="cpu")
    evaluation, calls, budget, clock = _evaluation(report, per_ray=1e-7, view_rays=10_000)
    evaluation.before_step(LoopState(1, last_loss=0.1))
    clock.now += 21.0
    _train_until(evaluation, budget, clock, 31.0)
    assert [round(t) for t, _ in calls] == [21, 30]
    (record,) = [s for s in report.stages if s.name == PROGRESS_EVALS_STAGE]
    assert record.why.endswith("; at 10 s not run: one training step went past it and the next due time")



@pytest.mark.parametrize("every", [1e-3, 0.7, 7.0, 15.0, 25.0, 60.0, 100.0])
def test_the_due_times_are_counted_as_they_are_listed(every):
    for first_from in (0.0, 3.0, 10.0, 44.0, 61.0, 250.0):
        first = next_progress_eval(first_from, every)
        for until in (first - 1.0, first, first + 0.5, first + 30.0, first + 300.0):
            listed = progress_eval_times(first, every, until, 10**6)
            assert progress_eval_count(first, every, until) == len(listed), (first, until)
            assert progress_eval_times(first, every, until, 3) == listed[:3]


def test_a_tiny_eval_every_s_counts_the_due_times_a_step_went_past_without_listing_them():
    """eval_every_s 1 ms and a step of 30 s: about 30,000 due times went past. They are counted, the first
    ``PASSED_LISTED`` listed (listing them all took gigabytes at 1 us). The allowance is sized over the
    evaluations still due (about a million up to max_seconds), so the one due now is skipped."""
    report = TrainReport(config={}, device="cpu")
    evaluation, calls, budget, clock = _evaluation(report, per_ray=1e-7, every=1e-3, view_rays=10_000)
    evaluation.before_step(LoopState(1, last_loss=0.1))
    clock.now += 30.0
    evaluation.before_step(LoopState(2, last_loss=0.1))
    passed = progress_eval_count(1e-3, 1e-3, 30.0) - 1
    assert not calls and evaluation.skipped == [30.0] and evaluation.passed_count == passed and passed > 29_000
    assert len(evaluation.passed) == PASSED_LISTED and evaluation.passed[0] == pytest.approx(1e-3)
    (record,) = [s for s in report.stages if s.name == PROGRESS_EVALS_STAGE]
    assert record.why.endswith(f", … ({passed} due times) s not run: one training step went past each and the "
                               "next due time")


@pytest.mark.parametrize("every", [1e-3, 0.1, 0.7, 3.3])
def test_each_next_due_time_is_later_than_the_last(every):
    """From a computed multiple of ``every``, the next one is later: the quotient's floor can round onto the
    multiple itself (3 * 0.7 / 0.7 < 3), which repeated the time, and then sizing an evaluation under max_seconds
    listed the same time for ever (``--eval-every 0.7 --max-seconds 6`` hung)."""
    t = next_progress_eval(0.0, every)
    for _ in range(5000):
        later = next_progress_eval(t, every)
        assert later > t and later == pytest.approx(t + every, rel=1e-9, abs=1e-12), t
        t = later


def test_progress_evaluations_every_0_7_s_under_max_seconds_run_and_are_sized():
    report = TrainReport(config={}, device="cpu")
    evaluation, calls, budget, clock = _evaluation(report, per_ray=1e-7, max_seconds=60.0, every=0.7,
                                                   view_rays=10_000)
    _train_until(evaluation, budget, clock, 5.0)
    assert calls and all(rays for _, rays in calls)


@pytest.mark.parametrize("every", [0.0, 1e-7, 1e-300, 5e-324])
def test_an_eval_every_s_below_a_microsecond_is_refused(every):
    """Smaller intervals only repeat "before every step", and at 1e-300 the multiples no longer grow with k
    (k * every rounds to the same float), so finding the next one never ended."""
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match="eval_every_s"):
        TrainConfig(max_iters=1, eval_every_s=every)
    assert TrainConfig(max_iters=1, eval_every_s=1e-6).evaluation.eval_every_s == 1e-6
