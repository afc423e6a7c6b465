"""The training loop's callbacks (voxnerf/training/callbacks.py), each driven alone with stubs and a fake clock."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch

from voxnerf.config import TrainConfig
from voxnerf.model.field import HashEncoding
from voxnerf.training.budget import Budget, TrainingProgress
from voxnerf.training.callbacks import (
    COMPILE_DENSITY_WHY,
    COMPILE_NO_STEP_WHY,
    COMPILE_RAN_WHY,
    DEFAULT_EVAL_SECONDS_PER_RAY,
    FIRST_PROGRESS_EVAL_RAYS,
    Checkpointing,
    CoarseToFine,
    CompileTimer,
    DepthWeightSchedule,
    LearningRateSchedule,
    OccupancyGridUpdate,
    ProgressBar,
    ProgressEvaluation,
    ProgressEvents,
    present,
)
from voxnerf.training.loop import LoopState
from voxnerf.training.records import EvalRecord, ProgressEvent, StageRecord, TrainReport


class FakeClock:
    def __init__(self, now: float = 100.0) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now


def _report() -> TrainReport:
    return TrainReport(config={}, device="cpu")


# ------------------------------------------------------------------------------------------ learning rate


def test_learning_rate_decays_tenfold_every_decay_iters_on_every_group():
    optimizer = SimpleNamespace(param_groups=[{"lr": 1e-2}, {"lr": 1e-3}])
    schedule = LearningRateSchedule(optimizer, decay_iters=1000)
    state = LoopState(iteration=0)
    schedule.before_step(state)
    assert state.lr == pytest.approx(1e-2) and [g["lr"] for g in optimizer.param_groups] == [1e-2, 1e-3]
    state.iteration = 2000
    schedule.before_step(state)
    assert state.lr == pytest.approx(1e-4)
    assert [g["lr"] for g in optimizer.param_groups] == pytest.approx([1e-4, 1e-5])


def _progress(max_seconds: float | None, max_iters: int | None = None):
    clock = FakeClock(0.0)
    budget = Budget(max_seconds, clock=clock)
    clock.now = 10.0  # set-up before the loop: not charged
    budget.start_training()
    return clock, TrainingProgress(budget, max_iters)


def test_training_progress_is_training_time_over_what_the_budget_leaves_for_it():
    clock, progress = _progress(100.0)
    assert progress.fraction(0) == 0.0
    clock.now = 50.0
    progress.budget.add("progress_evals", 20.0)  # charged: 80 s of training in all, 20 done
    assert progress.fraction(5) == pytest.approx(0.25)
    progress.budget.add("compile", 20.0)  # not charged: nothing done, 80 s still to train
    assert progress.fraction(5) == 0.0
    clock.now = 110.0
    assert progress.fraction(9) == pytest.approx(60.0 / 80.0)
    clock.now = 130.0
    assert progress.fraction(9) == 1.0


def test_training_progress_takes_the_larger_of_the_iteration_and_time_fractions_or_none():
    clock, progress = _progress(100.0, max_iters=100)
    clock.now = 20.0
    assert progress.fraction(50) == pytest.approx(0.5)
    assert _progress(None, max_iters=100)[1].fraction(25) == pytest.approx(0.25)
    assert _progress(None)[1].fraction(25) is None


def test_budget_learning_rate_reaches_lr_final_at_the_end_of_the_budget():
    clock, progress = _progress(100.0)
    optimizer = SimpleNamespace(param_groups=[{"lr": 1e-2}])
    schedule = LearningRateSchedule(optimizer, decay_iters=1000, schedule="budget", final=0.01, progress=progress)
    state = LoopState(iteration=0)
    schedule.before_step(state)
    assert state.lr == pytest.approx(1e-2)
    clock.now = 60.0
    schedule.before_step(state)
    assert state.lr == pytest.approx(1e-3)
    clock.now = 110.0
    schedule.before_step(state)
    assert optimizer.param_groups[0]["lr"] == pytest.approx(1e-4)


def test_budget_learning_rate_falls_back_to_iterations_without_limits():
    optimizer = SimpleNamespace(param_groups=[{"lr": 1e-2}])
    schedule = LearningRateSchedule(optimizer, decay_iters=1000, schedule="budget", final=0.01,
                                    progress=_progress(None)[1])
    state = LoopState(iteration=1000)
    schedule.before_step(state)
    assert state.lr == pytest.approx(1e-3)


def test_coarse_to_fine_ramps_the_levels_over_its_span_then_keeps_all():
    encoding = HashEncoding(levels=8, features=2, log2_size=10, max_resolution=128)
    clock, progress = _progress(100.0)
    ramp = CoarseToFine(encoding, coarse=2, span=0.5, progress=progress, fallback_iters=1000, every=1)
    state = LoopState(iteration=0)
    ramp.before_step(state)
    weights = encoding.level_weight.view(8, 2)[:, 0]
    assert weights.tolist() == [1, 1, 0, 0, 0, 0, 0, 0]
    clock.now = 35.0  # a quarter of the 100 s of training: half the ramp, 2 + 3 = 5 levels
    ramp.before_step(state)
    assert encoding.level_weight.view(8, 2)[:, 0].tolist() == [1, 1, 1, 1, 1, 0, 0, 0]
    clock.now = 60.0
    ramp.before_step(state)
    assert bool((encoding.level_weight == 1).all())
    encoding.set_active_levels(3.5)
    ramp.finish()
    assert bool((encoding.level_weight == 1).all())


def test_depth_weight_schedule_writes_lambda_d_times_final_to_the_fraction():
    clock, progress = _progress(100.0)
    weight = torch.tensor(0.0)
    schedule = DepthWeightSchedule(weight, lambda_depth=0.4, final=0.25, progress=progress, every=1)
    schedule.before_step(LoopState(iteration=0))
    assert float(weight) == pytest.approx(0.4)
    clock.now = 60.0
    schedule.before_step(LoopState(iteration=1))
    assert float(weight) == pytest.approx(0.2)


# ----------------------------------------------------------------------------------------- occupancy grid


class StubModel:
    def __init__(self) -> None:
        self.updates: list[tuple[object, bool]] = []
        self.grid_density = "eager density"  # VoxNeRFModel.grid_density: the field's density as the grid reads it
        self.grid = SimpleNamespace(update=lambda density, warmup: self.updates.append((density, warmup)),
                                    prepare=lambda density: self.updates.append((density, "prepared")))

    def compiled_density(self) -> str:
        return "compiled density"


@pytest.mark.parametrize(("sampler", "has_octree", "every"),
                         [("uniform", False, None), ("occgrid", False, 32), ("occgrid", True, 32),
                          ("voxnerf", True, 128), ("voxnerf", False, 32)])
def test_grid_update_period_follows_the_sampler(sampler, has_octree, every):
    cfg = TrainConfig(sampler=sampler, occgrid_update_every=32, max_iters=10)
    update = OccupancyGridUpdate.for_config(StubModel(), cfg, has_octree)
    assert (update.every if update is not None else None) == every


@pytest.mark.parametrize(("compiled", "density"), [(False, "eager density"), (True, "compiled density")])
def test_grid_updates_every_n_steps_with_two_warmup_updates(compiled, density):
    model = StubModel()
    update = OccupancyGridUpdate(model, every=4, compiled=compiled)
    for iteration in range(1, 17):
        update.after_step(LoopState(iteration))
    assert model.updates == [(density, True), (density, True), (density, False), (density, False)]


@pytest.mark.parametrize("compiled", [False, True])
def test_the_compiled_density_is_compiled_before_the_first_step_and_the_eager_one_is_left_alone(compiled):
    model = StubModel()
    assert OccupancyGridUpdate(model, every=4, compiled=compiled).compile_density() is compiled
    assert model.updates == ([("compiled density", "prepared")] if compiled else [])


# --------------------------------------------------------------------------------------- progress events


def _events(clock: FakeClock, cfg: TrainConfig | None = None, sink: list | None = None):
    budget = Budget(None, clock=clock)
    budget.start_training()
    report = _report()
    cfg = cfg or TrainConfig(max_iters=100)
    return ProgressEvents(None if sink is None else sink.append, cfg, budget, report, clock=clock), budget, report


def test_progress_events_while_training_are_throttled_to_one_per_second():
    clock, sent = FakeClock(), []
    events, _, _ = _events(clock, sink=sent)
    for i in range(1, 13):  # 3 s of 0.25 s steps
        clock.now += 0.25
        events.after_step(LoopState(i, last_loss=0.5))
    assert [e.iteration for e in sent] == [1, 5, 9]
    assert all(isinstance(e, ProgressEvent) and e.stage == "train" and e.loss == 0.5 for e in sent)


def test_forced_events_are_never_throttled_and_reset_the_interval():
    clock, sent = FakeClock(), []
    events, _, _ = _events(clock, sink=sent)
    events.emit("octree", 0)
    events.emit("pseudo_depth", 0)
    clock.now += 0.5
    events.after_step(LoopState(1))  # 0.5 s after a forced event: throttled
    clock.now += 0.5
    events.after_step(LoopState(2))
    assert [e.stage for e in sent] == ["octree", "pseudo_depth", "train"]


def test_without_a_listener_nothing_is_built():
    events, _, report = _events(FakeClock())
    events.emit("x")
    events.after_step(LoopState(1))
    events.stage(StageRecord(name="octree", ran=False, why="no prior"), 0)
    assert [s.name for s in report.stages] == ["octree"]


def test_an_event_carries_progress_eta_and_copies_of_history_and_stages():
    clock, sent = FakeClock(), []
    events, budget, report = _events(clock, TrainConfig(max_iters=100, max_seconds=40.0), sent)
    clock.now += 10.0
    report.history.append(EvalRecord(elapsed_s=5.0, iteration=10, psnr={"test": 20.0}))
    events.stage(StageRecord(name="load_scene", ran=True, why="3 frames"), 0)
    events.emit("train", 50, math.nan)
    first, second = sent
    assert first.stage == "load_scene" and [s.name for s in first.stages] == ["load_scene"]
    assert second.progress == pytest.approx(0.5)  # iterations: 0.5; time: 10 / 40
    assert second.eta_s == pytest.approx(10.0) and second.loss is None
    assert second.elapsed_s == pytest.approx(budget.train_seconds) and second.history == report.history
    assert second.history is not report.history and second.stages is not report.stages
    events.emit("done", 60, 0.1)
    assert sent[-1].progress == 1.0 and sent[-1].loss == 0.1
    budget.previous = 100.0  # past max_seconds: progress is capped, no eta
    events.emit("train", 60, 0.1)
    assert sent[-1].progress == 1.0 and sent[-1].eta_s is None


def test_the_set_up_and_compilation_do_not_advance_an_events_time_progress():
    clock, sent = FakeClock(), []
    budget = Budget(None, clock=clock)
    events = ProgressEvents(sent.append, TrainConfig(max_seconds=40.0), budget, _report(), clock=clock)
    clock.now += 30.0  # the set-up
    events.emit("octree")
    budget.start_training()
    clock.now += 10.0
    budget.add("compile", 6.0)
    events.emit("train", 1, 0.5)
    assert [e.progress for e in sent] == [0.0, pytest.approx(4.0 / 40.0)]
    assert sent[-1].eta_s == pytest.approx(36.0)


# ------------------------------------------------------------------------------------- progress evaluation


class StubEvaluate:
    def __init__(self, spent: float, per_ray: float) -> None:
        self.calls: list[tuple[int, float, int | None]] = []
        self.spent, self.per_ray = spent, per_ray

    def __call__(self, iteration: int, loss: float, rays: int | None) -> tuple[float, float]:
        self.calls.append((iteration, loss, rays))
        return self.spent, self.per_ray


def _evaluation(eval_at=(5.0, 25.0), sink=None, max_seconds: float | None = 1000.0):
    clock = FakeClock(0.0)
    budget = Budget(max_seconds, clock=clock)
    budget.start_training()
    cfg = TrainConfig(max_iters=10, eval_every_s=10.0, eval_at=list(eval_at))
    events = ProgressEvents(sink.append, cfg, budget, _report(), clock=clock) if sink is not None else None
    evaluate = StubEvaluate(spent=2.0, per_ray=1e-6)
    return ProgressEvaluation(evaluate, budget, cfg, 10_000, events), evaluate, budget, clock


def test_progress_evaluations_run_every_eval_every_s_and_full_ones_at_eval_at():
    evaluation, evaluate, budget, clock = _evaluation(eval_at=(5.0,))
    state = LoopState(3, last_loss=0.25)
    evaluation.before_step(state)
    assert evaluate.calls == []
    clock.now = 5.0
    evaluation.before_step(state)  # the --eval-at time: a full evaluation, neither training time nor charged
    assert evaluate.calls == [(3, 0.25, None)]
    assert budget.parts["eval_at"] == 2.0 and budget.train_seconds == 3.0 and budget.remaining() == 997.0
    assert evaluation.next_at == pytest.approx(10.0)
    clock.now = 15.0  # 13 s of training time (2 s paused), past the progress evaluation due at 10 s
    evaluation.before_step(state)
    assert evaluate.calls[-1] == (3, 0.25, FIRST_PROGRESS_EVAL_RAYS)  # no cost per ray measured yet: a few rays
    assert budget.parts["progress_evals"] == 2.0 and budget.parts["eval_at"] == 2.0
    assert budget.remaining() == pytest.approx(1000.0 - 11.0 - 2.0)
    evaluation.before_step(state)
    assert len(evaluate.calls) == 2


def test_a_full_evaluation_due_with_a_progress_one_stands_for_both():
    evaluation, evaluate, _, clock = _evaluation(eval_at=(10.0,))
    clock.now = 10.0
    evaluation.before_step(LoopState(1))
    evaluation.before_step(LoopState(1))
    assert [rays for _, _, rays in evaluate.calls] == [None] and evaluation.next_at == 20.0


def test_eval_at_times_already_passed_by_a_resumed_run_are_skipped():
    clock = FakeClock(0.0)
    budget = Budget(None, previous_train_seconds=30.0, clock=clock)
    cfg = TrainConfig(max_iters=10, eval_every_s=10.0, eval_at=[5.0, 25.0, 35.0])
    evaluation = ProgressEvaluation(StubEvaluate(1.0, 1e-3), budget, cfg, 10)
    assert evaluation.pending_full == [35.0] and evaluation.next_at == 40.0


def test_each_progress_evaluation_measures_the_cost_per_ray_that_sizes_the_next():
    evaluation, evaluate, _, clock = _evaluation(eval_at=())
    assert evaluation.seconds_per_ray == DEFAULT_EVAL_SECONDS_PER_RAY
    evaluate.per_ray = 2e-5
    clock.now = 10.0
    evaluation.before_step(LoopState(1))
    assert evaluation.seconds_per_ray == 2e-5
    # 20 s (2 % of 1000) less the 2 s spent, over the 98 evaluations planned from 20 s to the budget's end (998 s of
    # training: 8 s so far and 990 s left), at 2e-5 s per ray
    assert evaluation.rays_now() == int(18.0 / 98 / 2e-5)


def test_without_max_seconds_every_pixel_of_the_progress_views_is_scored():
    evaluation, evaluate, _, clock = _evaluation(eval_at=(), max_seconds=None)
    evaluate.per_ray = 1.0  # however dear
    for now in (10.0, 22.0, 34.0):
        clock.now = now
        evaluation.before_step(LoopState(1))
    assert [rays for _, _, rays in evaluate.calls] == [10_000] * 3


def test_a_roomy_budget_keeps_to_the_schedule():
    evaluation, evaluate, _, clock = _evaluation(eval_at=())
    evaluation.before_step(LoopState(0))
    clock.now = 1.0
    evaluation.before_step(LoopState(1))
    assert evaluate.calls == []


def test_each_evaluation_sends_a_train_event():
    sent: list[ProgressEvent] = []
    evaluation, _, _, clock = _evaluation(eval_at=(), sink=sent)
    clock.now = 10.0
    evaluation.before_step(LoopState(7, last_loss=0.3))
    assert [(e.stage, e.iteration, e.loss) for e in sent] == [("train", 7, 0.3)]


# ------------------------------------------------------------------------------------------ checkpoints


def test_checkpoints_are_saved_every_checkpoint_every_s_and_charged_as_checkpoints():
    clock, saved = FakeClock(), []
    budget = Budget(1000.0, clock=clock)
    budget.start_training()

    def save(iteration: int) -> None:
        saved.append(iteration)
        clock.now += 2.0  # a save takes 2 s

    saving = Checkpointing(save, every_s=60.0, budget=budget, clock=clock)
    for iteration in range(1, 8):
        clock.now += 25.0
        saving.after_step(LoopState(iteration))
    assert saved == [3, 6]  # 75 s after set-up, then 75 s after that save
    assert budget.parts["checkpoints"] == 4.0 and budget.train_seconds == 175.0 and budget.remaining() == 821.0


# ----------------------------------------------------------------------------------------- progress bar


class StubBar:
    def __init__(self) -> None:
        self.n, self.postfix, self.closed = 0, [], False

    def update(self, n: int) -> None:
        self.n += n

    def set_postfix(self, **kwargs) -> None:
        self.postfix.append(kwargs)

    def close(self) -> None:
        self.closed = True


def test_progress_bar_ticks_every_step_and_shows_loss_and_lr_every_50():
    bar = ProgressBar(StubBar())
    for iteration in range(1, 101):
        bar.after_step(LoopState(iteration, last_loss=0.123456, lr=0.01))
    bar.close()
    assert bar.bar.n == 100 and bar.bar.closed
    assert bar.bar.postfix == [{"loss": "0.1235", "lr": "0.01"}] * 2


def test_a_disabled_progress_bar_is_created_silent(capsys):
    bar = ProgressBar.create(total=10, initial=3, enabled=False)
    bar.after_step(LoopState(4))
    bar.close()
    assert capsys.readouterr().err == ""


# --------------------------------------------------------------------------------------------- compile


def test_compile_stage_is_recorded_after_the_first_step_only():
    clock, recorded = FakeClock(), []
    budget = Budget(None, clock=clock)
    timer = CompileTimer(started=90.0, record=lambda rec, it: recorded.append((rec, it)), budget=budget,
                         clock=clock)
    timer.after_step(LoopState(1))
    clock.now += 5.0
    timer.after_step(LoopState(2))
    timer.finish(2)
    assert recorded == [(StageRecord(name="compile", ran=True, why=COMPILE_RAN_WHY, seconds=10.0), 1)]
    assert budget.parts["compile"] == 10.0  # neither training time nor charged


def test_a_step_of_two_graphs_counts_the_first_step_of_each_and_not_what_ran_between():
    clock, recorded = FakeClock(), []
    budget = Budget(None, clock=clock)
    timer = CompileTimer(started=90.0, record=lambda rec, it: recorded.append((rec, it)), budget=budget,
                         clock=clock, steps=2)
    timer.after_step(LoopState(1))  # 10 s from started
    clock.now += 30.0  # an evaluation before the second step
    timer.before_step(LoopState(1))
    clock.now += 4.0
    timer.after_step(LoopState(2))
    timer.before_step(LoopState(2))
    clock.now += 1.0
    timer.after_step(LoopState(3))
    timer.finish(3)
    why = "torch.compile of the training step's 2 graphs (time of the first step of each)"
    assert recorded == [(StageRecord(name="compile", ran=True, why=why, seconds=14.0), 2)]
    assert budget.parts["compile"] == 14.0


def test_a_density_compiled_before_the_first_step_is_counted_and_said_before_the_first_step():
    """The density compiles before the loop (issue #46: cold, 27 s that a progress evaluation before the first step
    took for training time): at loop_starts it is compile time already."""
    clock, recorded = FakeClock(), []
    budget = Budget(None, clock=clock)
    budget.start_training()
    clock.now += 2.0  # building the step
    timer = CompileTimer(started=clock.now, record=lambda rec, it: recorded.append((rec, it)), budget=budget,
                         clock=clock, density=True)
    clock.now += 27.0  # the density compiles
    timer.loop_starts()
    assert budget.parts["compile"] == 27.0 and budget.train_seconds == 2.0
    timer.before_step(LoopState(0))
    clock.now += 5.0  # the first step compiles
    timer.after_step(LoopState(1))
    assert recorded == [(StageRecord(name="compile", ran=True, why=COMPILE_RAN_WHY + COMPILE_DENSITY_WHY,
                                     seconds=32.0), 1)]
    assert budget.parts["compile"] == 32.0 and budget.train_seconds == 2.0


def test_a_run_that_stops_between_the_graphs_records_the_first_step():
    clock, recorded = FakeClock(), []
    budget = Budget(None, clock=clock)
    timer = CompileTimer(started=90.0, record=lambda rec, it: recorded.append((rec, it)), budget=budget,
                         clock=clock, steps=2)
    timer.after_step(LoopState(1))
    clock.now += 7.0
    timer.finish(1)
    assert recorded[0][0].ran and recorded[0][0].seconds == 10.0


def test_compile_stage_without_any_step_says_so():
    clock, recorded = FakeClock(), []
    budget = Budget(None, clock=clock)
    timer = CompileTimer(started=99.0, record=lambda rec, it: recorded.append((rec, it)), budget=budget,
                         clock=clock)
    timer.finish(0)
    assert recorded == [(StageRecord(name="compile", ran=False, why=COMPILE_NO_STEP_WHY, seconds=1.0), 0)]
    assert budget.parts["compile"] == 1.0  # what was built for the step: the stage's seconds, not training


def test_present_drops_callbacks_that_do_not_apply():
    bar = ProgressBar(StubBar())
    assert present([None, bar, None]) == [bar]
