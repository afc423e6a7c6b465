"""The loop's periodic duties as small callback objects (see :class:`voxnerf.training.loop.Callback`).

Callbacks that run every step keep to a comparison or two unless their period is due; none adds a host sync.
Clocks are injectable (``clock``) so that tests can drive them.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable, Sequence

import torch
from tqdm import tqdm

from voxnerf.config import TrainConfig
from voxnerf.model.voxnerf_model import VoxNeRFModel
from voxnerf.training.budget import Budget, Clock, TrainingProgress
from voxnerf.training.loop import Callback, LoopState
from voxnerf.training.records import LossSeries, ProgressEvent, StageRecord, TrainReport

DEFAULT_EVAL_SECONDS_PER_RAY = 6e-6  # the final-evaluation cost per ray (fast path and metrics) until one is measured
# Progress evaluations before the first ``eval_every_s`` (those below it), so that a short run's error curve has
# points in its first minute; each runs only while the progress evaluations, it included (costed as the last
# one), take at most EARLY_EVAL_MAX_SHARE of the training seconds so far. The first always runs.
EARLY_EVAL_S = (10.0, 20.0, 30.0, 45.0)
EARLY_EVAL_MAX_SHARE = 0.15
PROGRESS_EVALS_STAGE = "progress_evals"
COMPILE_RAN_WHY = "torch.compile of the training step (time of the first step)"
COMPILE_DENSITY_WHY = ", the occupancy grid's density compiled before the first step included"
COMPILE_NO_STEP_WHY = "no training step ran"
ProgressCallback = Callable[[ProgressEvent], None]
Evaluate = Callable[[int, float, bool], tuple[float, float]]  # (iteration, loss, full) -> (seconds, s per ray)


class LearningRateSchedule(Callback):
    """The learning rate of each parameter group (its initial lr times a factor), set before each step.

    ``schedule='iterations'``: factor ``0.1 ** (iteration / decay_iters)``. ``schedule='budget'``: factor
    ``final ** fraction`` of the run's :class:`TrainingProgress` (the iterations rule where no limit bounds it).
    """

    def __init__(self, optimizer: torch.optim.Optimizer, decay_iters: float, schedule: str = "iterations",
                 final: float = 0.1, progress: TrainingProgress | None = None) -> None:
        self.groups = optimizer.param_groups
        self.base = [group.setdefault("initial_lr", group["lr"]) for group in self.groups]
        self.decay_iters, self.schedule, self.final, self.progress = decay_iters, schedule, final, progress

    def factor(self, iteration: int) -> float:
        fraction = self.progress.fraction(iteration) if self.schedule == "budget" and self.progress else None
        return 0.1 ** (iteration / self.decay_iters) if fraction is None else self.final**fraction

    def before_step(self, state: LoopState) -> None:
        factor = self.factor(state.iteration)
        for group, base in zip(self.groups, self.base, strict=True):
            group["lr"] = base * factor
        state.lr = self.base[0] * factor


class CoarseToFine(Callback):
    """Switch the hash levels on from ``coarse`` to all over the first ``span`` of the run's progress (over
    ``span * fallback_iters`` steps where no limit bounds it); every level is on once it is done."""

    def __init__(self, encoding, coarse: int, span: float, progress: TrainingProgress, fallback_iters: int,
                 every: int = 8) -> None:
        self.encoding, self.coarse, self.span, self.progress = encoding, min(coarse, encoding.levels), span, progress
        self.fallback_iters, self.every, self.active = fallback_iters, every, -1.0

    def active_levels(self, iteration: int) -> float:
        fraction = self.progress.fraction(iteration)
        if fraction is None:
            fraction = iteration / self.fallback_iters
        ramp = min(fraction / self.span, 1.0)
        return self.coarse + ramp * (self.encoding.levels - self.coarse)

    def before_step(self, state: LoopState) -> None:
        if self.active >= self.encoding.levels or state.iteration % self.every and self.active >= 0:
            return
        self.active = self.active_levels(state.iteration)
        self.encoding.set_active_levels(self.active)

    def finish(self) -> None:
        """Every level on (the saved model renders with all of them)."""
        self.encoding.set_active_levels(float(self.encoding.levels))


class DepthWeightSchedule(Callback):
    """lambda_d now = ``lambda_d * final ** fraction`` of the run's progress, written into ``weight`` (the 0-d
    tensor the training step passes to its loss) every ``every`` steps."""

    def __init__(self, weight: torch.Tensor, lambda_depth: float, final: float, progress: TrainingProgress,
                 every: int = 8) -> None:
        self.weight, self.lam, self.final, self.progress, self.every = weight, lambda_depth, final, progress, every

    def before_step(self, state: LoopState) -> None:
        if state.iteration % self.every == 0:
            fraction = self.progress.fraction(state.iteration) or 0.0
            self.weight.fill_(self.lam * self.final**fraction)


class OccupancyGridUpdate(Callback):
    """Every ``every`` steps, re-estimate the occupancy grid from the field's density (the compiled density
    when training is compiled, see docs/engine.md, 'Samplers'); the first two updates are warm-up updates."""

    def __init__(self, model: VoxNeRFModel, every: int, compiled: bool) -> None:
        self.model, self.every, self.compiled = model, every, compiled

    @classmethod
    def for_config(cls, model: VoxNeRFModel, cfg: TrainConfig, has_octree: bool) -> OccupancyGridUpdate | None:
        """None for the uniform sampler. The grid drives the occgrid sampler; for voxnerf it only serves rays
        that miss the octree, so it is updated 4x less often there."""
        if cfg.sampling.sampler == "uniform":
            return None
        sampling = cfg.sampling
        return cls(model, sampling.occgrid_update_every * (1 if sampling.sampler == "occgrid" or not has_octree else 4),
                   cfg.run.compile)

    def compile_density(self) -> bool:
        """Compile the density the updates use now, before the first step, so that its compilation does not
        land in the step of the first update; False (nothing done) where the updates run eagerly."""
        if self.compiled:
            self.model.grid.prepare(self.model.compiled_density())
        return self.compiled

    def after_step(self, state: LoopState) -> None:
        iteration = state.iteration
        if iteration % self.every == 0:
            density = self.model.compiled_density() if self.compiled else self.model.field.density
            self.model.grid.update(density, warmup=iteration <= 2 * self.every)


class ProgressEvents(Callback):
    """``on_progress`` events: at every stage, after each progress evaluation and at the end (forced), and
    while training at most one per ``interval`` seconds. Also the run's stage log (:meth:`stage`) and its
    training-loss series (the report's ``loss_series``: at most a point per ``train`` event, :class:`LossSeries`).
    Every event carries ``checkpoint_iteration``, the iteration of the run's last complete checkpoint (set by the
    run after each save, and from the checkpoint a resumed run starts from)."""

    def __init__(self, on_progress: ProgressCallback | None, cfg: TrainConfig, budget: Budget,
                 report: TrainReport, clock: Clock = time.perf_counter, interval: float = 1.0) -> None:
        self.on_progress, self.cfg, self.budget, self.report = on_progress, cfg, budget, report
        self.clock, self.interval, self.last = clock, interval, 0.0
        self.series = LossSeries(gap=interval)
        self.checkpoint_iteration: int | None = None

    def stage(self, record: StageRecord, iteration: int) -> None:
        """Add a finished stage to the report and tell ``on_progress``."""
        self.report.stages.append(record)
        self.emit(record.name, iteration)

    def emit(self, stage: str, iteration: int = 0, loss: float | None = None, force: bool = True) -> None:
        now = self.clock()
        if not force and now - self.last < self.interval:
            return
        self.last = now
        if stage == "train" and self.series.close(self.budget.train_seconds):  # at a stage's event the
            self.report.loss_series = list(self.series.points)  # clock may hold a checkpoint's save
        if self.on_progress is not None:
            self.on_progress(self.event(stage, iteration, loss))

    def after_step(self, state: LoopState) -> None:
        self.series.add(state.last_loss)
        self.emit("train", state.iteration, state.last_loss, force=False)

    def event(self, stage: str, iteration: int, loss: float | None) -> ProgressEvent:
        cfg, budget = self.cfg, self.budget
        fractions = []
        if cfg.run.max_iters:
            fractions.append(iteration / cfg.run.max_iters)
        if cfg.run.max_seconds:
            fractions.append((budget.previous + budget.wall) / cfg.run.max_seconds)
        progress = min(1.0, max(fractions)) if fractions else 0.0
        eta = budget.wall * (1 - progress) / progress if 0 < progress < 1 else None
        return ProgressEvent(
            stage=stage, iteration=iteration, max_iters=cfg.run.max_iters, elapsed_s=budget.train_seconds,
            progress=1.0 if stage == "done" else progress, eta_s=eta,
            loss=loss if loss is not None and math.isfinite(loss) else None,
            history=list(self.report.history), stages=list(self.report.stages),
            loss_series=list(self.series.points), checkpoint_iteration=self.checkpoint_iteration,
        )


def next_progress_eval(after: float, every: float) -> float:
    """The first progress-evaluation time (training seconds) later than ``after``: the :data:`EARLY_EVAL_S`
    times below ``every``, then every multiple of ``every``."""
    early = [t for t in EARLY_EVAL_S if after < t < every]
    return early[0] if early else (math.floor(after / every) + 1) * every


def seconds_list(times: Sequence[float], most: int = 8) -> str:
    """``10, 20, 30`` (seconds, rounded); a long list shows its first ones, then ``…`` and the last."""
    shown = [f"{t:.0f}" for t in times]
    if len(shown) > most:
        shown = [*shown[: most - 2], "…", shown[-1]]
    return ", ".join(shown)


class ProgressEvaluation(Callback):
    """Progress evaluations at the :func:`next_progress_eval` times and full ones at the ``eval_at`` times,
    before a step. Their time is paused (not training time); a full one's is also not charged to the budget.

    They also measure the evaluation cost per ray, which sizes the final evaluation's reserve of the budget
    (:meth:`final_eval_reserve`). So that the reserve is measured before it can end a short run, a progress
    evaluation runs right after the first step (the step that compiles, when training is compiled) when the
    budget could otherwise run out on the assumed cost before the first due one.

    An early progress evaluation (:data:`EARLY_EVAL_S`) after the first is skipped when the progress
    evaluations, it included (costed as the last one), would take more than :data:`EARLY_EVAL_MAX_SHARE` of the
    training seconds so far. The progress evaluations that ran, and those skipped, are the stage
    ``progress_evals`` of the report (``events.report``), added at the first one and kept up to date.

    The full ones may take ``cfg.evaluation.eval_at_max_seconds`` in all: once that is spent the later ``eval_at`` times
    are skipped and ``warnings`` (the report's) says so.
    """

    def __init__(self, evaluate: Evaluate, budget: Budget, cfg: TrainConfig, final_eval_rays: int,
                 events: ProgressEvents | None = None, warnings: list[str] | None = None) -> None:
        self.evaluate, self.budget, self.events = evaluate, budget, events
        self.every, self.final_eval = cfg.evaluation.eval_every_s, cfg.evaluation.final_eval
        self.compiled = cfg.run.compile
        self.views_per_split = cfg.evaluation.eval_views
        self.final_eval_rays = final_eval_rays
        self.next_at = next_progress_eval(budget.train_seconds, cfg.evaluation.eval_every_s)
        self.pending_full = sorted(t for t in cfg.evaluation.eval_at if t > budget.train_seconds)
        self.seconds_per_ray = DEFAULT_EVAL_SECONDS_PER_RAY
        self.done = 0
        self.full_cap, self.full_spent = cfg.evaluation.eval_at_max_seconds, 0.0
        self.warnings = warnings if warnings is not None else []
        self.progress_times: list[float] = []  # training seconds of the progress evaluations that ran
        self.progress_spent, self.last_progress_cost = 0.0, 0.0
        self.skipped_early: list[float] = []
        self.record: StageRecord | None = None
        self.first_step_done = False

    def _full_due(self) -> bool:
        """Whether an ``eval_at`` time has come; drops the pending ones once their time cap is spent."""
        pending = self.pending_full
        if not (pending and self.budget.train_seconds >= pending[0]):
            return False
        if self.full_cap is not None and self.full_spent >= self.full_cap:
            self.warnings.append(f"eval_at: {len(pending)} full evaluation(s) from {pending[0]:g} s on skipped: "
                                 f"the {self.full_cap:g} s allowed for them were spent")
            pending.clear()
            return False
        return True

    def _measure_first(self) -> bool:
        """Whether to evaluate now although none is due: after the first step, with no cost per ray measured
        yet, when the budget could run out on the assumed reserve before the next due evaluation."""
        if self.done or not self.first_step_done or not self.final_eval:
            return False
        return self.budget.remaining() - self.final_eval_reserve() < self.next_at - self.budget.train_seconds

    def _too_dear(self) -> bool:
        """Whether the due progress evaluation is an early one that would take the progress evaluations over
        their share of the training seconds so far (never the first one)."""
        if self.next_at >= self.every or not self.progress_times:
            return False
        cost = self.progress_spent + self.last_progress_cost
        return cost > EARLY_EVAL_MAX_SHARE * self.budget.train_seconds

    def before_step(self, state: LoopState) -> None:
        budget, pending = self.budget, self.pending_full
        full = self._full_due()
        measure_now = self._measure_first()
        self.first_step_done = True
        if not (full or measure_now or budget.train_seconds >= self.next_at):
            return
        if not full and self._too_dear():
            self.skipped_early.append(self.next_at)
            self.next_at = next_progress_eval(budget.train_seconds, self.every)
            self._update_record()
            return
        if full:
            pending.pop(0)
        at = budget.train_seconds
        spent, per_ray = self.evaluate(state.iteration, state.last_loss, full)
        self.done += 1
        self.seconds_per_ray = per_ray
        budget.paused += spent
        if full:
            budget.excluded += spent
            self.full_spent += spent
        else:
            self.progress_times.append(at)
            self.progress_spent += spent
            self.last_progress_cost = spent
            self._update_record()
        self.next_at = next_progress_eval(at, self.every)
        if self.events is not None:
            self.events.emit("train", state.iteration, state.last_loss)

    def _update_record(self) -> None:
        """The stage ``progress_evals`` in the report: added at the first progress evaluation, then updated."""
        if self.events is None or not self.progress_times:
            return
        if self.record is None:
            self.record = StageRecord(name=PROGRESS_EVALS_STAGE, ran=True, why="")
            self.events.report.stages.append(self.record)
        n = len(self.progress_times)
        why = (f"{n} progress evaluation{'s' if n > 1 else ''} of up to {self.views_per_split} views per split at "
               f"{seconds_list(self.progress_times)} s of training: not training time, but charged to max_seconds")
        if self.skipped_early:
            why += (f"; early one(s) at {seconds_list(self.skipped_early)} s skipped: they would have taken the "
                    f"progress evaluations over {EARLY_EVAL_MAX_SHARE:.0%} of the training time")
        self.record.why, self.record.seconds = why, round(self.progress_spent, 3)

    def final_eval_reserve(self) -> float:
        """Seconds kept back for the final evaluation: 1.5x its estimated cost plus 2 s."""
        if not self.final_eval:
            return 0.0
        return 1.5 * self.seconds_per_ray * self.final_eval_rays + 2.0


class Checkpointing(Callback):
    """Calls ``save(iteration)`` after a step once ``every_s`` seconds have passed since the last save (or
    since the loop was set up)."""

    def __init__(self, save: Callable[[int], None], every_s: float, clock: Clock = time.perf_counter) -> None:
        self.save, self.every_s, self.clock = save, every_s, clock
        self.last = clock()

    def after_step(self, state: LoopState) -> None:
        if self.clock() - self.last >= self.every_s:
            self.save(state.iteration)
            self.last = self.clock()


class ProgressBar(Callback):
    """The tqdm bar (stderr): one tick per step, loss and learning rate every 50 steps."""

    def __init__(self, bar) -> None:
        self.bar = bar

    @classmethod
    def create(cls, total: int | None, initial: int, enabled: bool) -> ProgressBar:
        return cls(tqdm(total=total, initial=initial, disable=not enabled, file=sys.stderr, desc="train",
                        dynamic_ncols=True))

    def after_step(self, state: LoopState) -> None:
        self.bar.update(1)
        if state.iteration % 50 == 0:
            self.bar.set_postfix(loss=f"{state.last_loss:.4g}", lr=f"{state.lr:.2g}")

    def close(self) -> None:
        self.bar.close()


class CompileTimer(Callback):
    """Records the compile stage after the first ``steps`` steps, or at :meth:`finish` when fewer ran (what was
    compiled before the first step, ``density``, counts in: the first step's time runs from ``started``).
    ``torch.compile`` compiles a graph on its first call: the first step's time, from ``started``, is the step's
    compile time, and where the step alternates between graphs (pose refinement on every n-th step only) the
    first step of each other graph adds its own time (from its ``before_step``, so evaluations before it do not
    count)."""

    def __init__(self, started: float, record: Callable[[StageRecord, int], None],
                 clock: Clock = time.perf_counter, steps: int = 1, density: bool = False) -> None:
        self.started, self.record, self.clock, self.steps = started, record, clock, steps
        self.density = density  # the occupancy grid's density was compiled between ``started`` and the first step
        self.pending, self.timed, self.spent = True, 0, 0.0

    def before_step(self, state: LoopState) -> None:
        if self.pending and self.timed:
            self.started = self.clock()

    def after_step(self, state: LoopState) -> None:
        if self.pending:
            self.spent += self.clock() - self.started
            self.timed += 1
            if self.timed == self.steps:
                self._record(True, self._ran_why(), state.iteration)

    def finish(self, iteration: int) -> None:
        if self.pending:
            self._record(self.timed > 0, self._ran_why() if self.timed else COMPILE_NO_STEP_WHY, iteration)

    def _ran_why(self) -> str:
        why = (COMPILE_RAN_WHY if self.steps == 1 else
               f"torch.compile of the training step's {self.steps} graphs (time of the first step of each)")
        return why + COMPILE_DENSITY_WHY if self.density else why

    def _record(self, ran: bool, why: str, iteration: int) -> None:
        self.pending = False
        seconds = self.spent if self.timed else self.clock() - self.started
        self.record(StageRecord(name="compile", ran=ran, why=why, seconds=seconds), iteration)


def present(callbacks: Sequence[Callback | None]) -> list[Callback]:
    """The callbacks that apply to this run (a None stands for one that does not)."""
    return [c for c in callbacks if c is not None]
