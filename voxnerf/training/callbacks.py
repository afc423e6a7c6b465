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

DEFAULT_EVAL_SECONDS_PER_RAY = 6e-6  # a progress evaluation's cost per ray until the first one measures it
# The progress evaluations' share of max_seconds: each is sized from the measured cost per ray to its part of that
# share (:class:`ProgressEvaluation`). A run that no max_seconds bounds evaluates every pixel of the progress views.
PROGRESS_EVAL_SHARE = 0.02
# Fewer rays than this (or than the progress views hold, when fewer) make too noisy a point: the evaluation is
# skipped instead (about 0.1 dB of sampling noise on a split's PSNR at this size).
MIN_PROGRESS_EVAL_RAYS = 2048
# The first progress evaluation of a run with max_seconds, before any cost per ray is measured, scores at most this
# many rays: a scene where rendering is dear then spends little on learning what it costs.
FIRST_PROGRESS_EVAL_RAYS = 2048
# Progress evaluations before the first ``eval_every_s`` (those below it), so that a short run's error curve has
# points in its first minute.
EARLY_EVAL_S = (10.0, 20.0, 30.0, 45.0)
PROGRESS_EVALS_STAGE = "progress_evals"
# Due times that one step went past are counted; the stage's why lists this many of them.
PASSED_LISTED = 8
COMPILE_RAN_WHY = "torch.compile of the training step (time of the first step)"
COMPILE_DENSITY_WHY = ", the occupancy grid's density compiled before the first step included"
COMPILE_NO_STEP_WHY = "no training step ran"
ProgressCallback = Callable[[ProgressEvent], None]
# (iteration, loss, rays: a progress evaluation's size, None for a full one) -> (seconds, seconds per ray)
Evaluate = Callable[[int, float, int | None], tuple[float, float]]


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
            density = self.model.compiled_density() if self.compiled else self.model.grid_density
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
            fractions.append((budget.previous + budget.charged) / cfg.run.max_seconds)
        progress = min(1.0, max(fractions)) if fractions else 0.0
        eta = budget.charged * (1 - progress) / progress if 0 < progress < 1 and budget.charged > 0 else None
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
    return early[0] if early else _first_multiple_after(after, every) * every


def _first_multiple_after(after: float, every: float) -> int:
    """The smallest k >= 1 whose ``k * every`` (as computed) is above ``after``: the floor of the quotient alone
    can round to the multiple itself (1e-3 steps) and then repeat it."""
    k = max(math.floor(after / every) + 1, 1)
    while k * every <= after:
        k += 1
    while k > 1 and (k - 1) * every > after:
        k -= 1
    return k


def progress_eval_times(first: float, every: float, until: float, most: int) -> list[float]:
    """The first ``most`` (at least one) progress-evaluation times from ``first`` (a :func:`next_progress_eval`
    time) up to ``until`` (training seconds, excluded); ``first`` alone when it is not below ``until``."""
    times = [first]
    while len(times) < most and (t := next_progress_eval(times[-1], every)) < until:
        times.append(t)
    return times


def progress_eval_count(first: float, every: float, until: float) -> int:
    """How many times :func:`progress_eval_times` has from ``first`` up to ``until`` (at least one), counted
    without listing them: a tiny ``every`` puts millions of due times into a few seconds."""
    if not first < until:
        return 1
    early = sum(1 for t in EARLY_EVAL_S if first < t < min(every, until))
    below = _first_multiple_after(until, every) - 1  # the largest k with k * every <= until
    if below * every == until:
        below -= 1  # until itself is excluded
    multiples = below - _first_multiple_after(first, every) + 1  # k * every in (first, until)
    return 1 + early + max(multiples, 0)


def seconds_list(times: Sequence[float], most: int = 8) -> str:
    """``10, 20, 30`` (seconds, rounded); a long list shows its first ones, then ``…`` and the last."""
    shown = [f"{t:.0f}" for t in times]
    if len(shown) > most:
        shown = [*shown[: most - 2], "…", shown[-1]]
    return ", ".join(shown)


class ProgressEvaluation(Callback):
    """Progress evaluations at the :func:`next_progress_eval` times and full ones at the ``eval_at`` times,
    before a step. Their time is not training time (the budget's part ``progress_evals``, charged to
    ``max_seconds``, or ``eval_at``, not charged).

    The progress evaluations together take at most :data:`PROGRESS_EVAL_SHARE` of ``max_seconds``: each is
    sized to what that share has left over the evaluations still planned before the budget ends, at the cost
    per ray the last one measured (the first one, with none measured, scores at most
    :data:`FIRST_PROGRESS_EVAL_RAYS`). It scores that many rays spread over the progress views (``eval_views``
    per split; every pixel of them where the share allows, else the same random subset of each view's pixels
    every time), and is skipped when it can afford fewer than :data:`MIN_PROGRESS_EVAL_RAYS`; without
    ``max_seconds`` it scores every pixel of them. The progress evaluations that ran, and those skipped, are the
    stage ``progress_evals`` of the report (``events.report``), added at the first one and kept up to date.

    The full ones may take ``cfg.evaluation.eval_at_max_seconds`` in all: once that is spent the later ``eval_at``
    times are skipped and ``warnings`` (the report's) says so.
    """

    def __init__(self, evaluate: Evaluate, budget: Budget, cfg: TrainConfig, view_rays: int,
                 events: ProgressEvents | None = None, warnings: list[str] | None = None) -> None:
        self.evaluate, self.budget, self.events = evaluate, budget, events
        self.every = cfg.evaluation.eval_every_s
        self.views_per_split = cfg.evaluation.eval_views
        self.view_rays = view_rays  # the progress views' pixels: the most a progress evaluation scores
        self.share_of = (None if budget.max_seconds is None
                         else PROGRESS_EVAL_SHARE * max(budget.max_seconds - budget.previous, 0.0))
        self.next_at = next_progress_eval(budget.train_seconds, cfg.evaluation.eval_every_s)
        self.pending_full = sorted(t for t in cfg.evaluation.eval_at if t > budget.train_seconds)
        self.seconds_per_ray = DEFAULT_EVAL_SECONDS_PER_RAY
        self.full_cap, self.full_spent = cfg.evaluation.eval_at_max_seconds, 0.0
        self.warnings = warnings if warnings is not None else []
        self.progress_times: list[float] = []  # training seconds of the progress evaluations that ran
        self.progress_rays: list[int] = []  # and the rays each scored
        self.progress_spent = 0.0
        self.skipped: list[float] = []
        self.passed: list[float] = []  # due times a single step went past, with a later one: not evaluated
        self.passed_count = 0  # all of them; ``passed`` keeps the first PASSED_LISTED
        self.record: StageRecord | None = None

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

    def allowance(self) -> float:
        """Seconds the due progress evaluation may take: what the share has left, over the evaluations planned
        from now to the end of the budget (training seconds so far plus ``remaining()``); unbounded where no
        ``max_seconds`` bounds the run (the evaluations then take no training time from it)."""
        budget = self.budget
        if self.share_of is None:
            return math.inf
        end = budget.train_seconds + max(budget.remaining(), 0.0)
        planned = progress_eval_count(self.next_at, self.every, end)
        return (self.share_of - self.progress_spent) / planned

    def rays_now(self) -> int:
        """Rays the due progress evaluation scores (:meth:`allowance` at the cost per ray, at most the progress
        views' pixels); 0 when that is fewer than :data:`MIN_PROGRESS_EVAL_RAYS` (or than those pixels)."""
        rays = int(min(self.allowance() / max(self.seconds_per_ray, 1e-12), self.view_rays))
        if self.share_of is not None and not self.progress_times:
            rays = min(rays, FIRST_PROGRESS_EVAL_RAYS)
        return rays if rays >= min(MIN_PROGRESS_EVAL_RAYS, self.view_rays) and rays > 0 else 0

    def before_step(self, state: LoopState) -> None:
        budget = self.budget
        full = self._full_due()
        if not (full or budget.train_seconds >= self.next_at):
            return
        at = budget.train_seconds
        if full:
            self.pending_full.pop(0)
            spent, _ = self.evaluate(state.iteration, state.last_loss, None)  # its cost per ray has metrics in it
            budget.add("eval_at", spent)
            self.full_spent += spent
            self.next_at = next_progress_eval(at, self.every)  # a progress evaluation due now would repeat it
        else:
            self._note_passed(at)
            rays = self.rays_now()
            self.next_at = next_progress_eval(at, self.every)
            if not self.view_rays:  # no evaluation split: nothing to evaluate
                return
            if not rays:
                self.skipped.append(at)
                self._update_record()
                return
            spent, self.seconds_per_ray = self.evaluate(state.iteration, state.last_loss, rays)
            budget.add("progress_evals", spent)
            self.progress_times.append(at)
            self.progress_rays.append(rays)
            self.progress_spent += spent
            self._update_record()
        if self.events is not None:
            self.events.emit("train", state.iteration, state.last_loss)

    def _note_passed(self, at: float) -> None:
        """Counts the due times from ``next_at`` up to ``at`` but the latest (the evaluation now stands for it),
        and lists the first of them."""
        passed = progress_eval_count(self.next_at, self.every, at) - 1
        listed = min(passed, PASSED_LISTED - len(self.passed))
        if listed > 0:
            self.passed += progress_eval_times(self.next_at, self.every, at, listed)
        self.passed_count += passed

    def _update_record(self) -> None:
        """The stage ``progress_evals`` in the report: added at the first progress evaluation (or skip), then
        updated."""
        if self.events is None:
            return
        if self.record is None:
            self.record = StageRecord(name=PROGRESS_EVALS_STAGE, ran=False, why="")
            self.events.report.stages.append(self.record)
        n = len(self.progress_times)
        bounded = self.share_of is not None
        sizing = (f"sized to {PROGRESS_EVAL_SHARE:.0%} of max_seconds, to which they are charged (not training time)"
                  if bounded else "every pixel of them (no max_seconds to size them to; not training time)")
        parts = []
        if n:
            low, high = min(self.progress_rays), max(self.progress_rays)
            parts.append(f"{n} progress evaluation{'s' if n > 1 else ''} at {seconds_list(self.progress_times)} s "
                         f"of training, of {low if low == high else f'{low}-{high}'} rays over up to "
                         f"{self.views_per_split} views per split ({self.view_rays} pixels): {sizing}")
        if self.skipped:
            parts.append(f"at {seconds_list(self.skipped)} s skipped: fewer than "
                         f"{min(MIN_PROGRESS_EVAL_RAYS, self.view_rays)} rays were left within "
                         f"{PROGRESS_EVAL_SHARE:.0%} of max_seconds")
        if self.passed_count:
            times = (seconds_list(self.passed) if self.passed_count == len(self.passed)
                     else f"{seconds_list(self.passed)}, … ({self.passed_count} due times)")
            parts.append(f"at {times} s not run: one training step went past "
                         f"{'it' if self.passed_count == 1 else 'each'} and the next due time")
        why = "; ".join(parts)
        self.record.ran, self.record.why, self.record.seconds = n > 0, why, round(self.progress_spent, 3)


class Checkpointing(Callback):
    """Calls ``save(iteration)`` after a step once ``every_s`` seconds have passed since the last save (or
    since the loop was set up); the save's seconds are the budget's part ``checkpoints`` (not training time)."""

    def __init__(self, save: Callable[[int], None], every_s: float, budget: Budget,
                 clock: Clock = time.perf_counter) -> None:
        self.save, self.every_s, self.budget, self.clock = save, every_s, budget, clock
        self.last = clock()

    def after_step(self, state: LoopState) -> None:
        if self.clock() - self.last >= self.every_s:
            started = self.clock()
            self.save(state.iteration)
            self.last = self.clock()
            self.budget.add("checkpoints", self.last - started)


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
    count). Those seconds go to the budget's part ``compile`` (not training time, not charged to ``max_seconds``):
    what ran before the first step at :meth:`loop_starts`, each timed step's as it ends."""

    def __init__(self, started: float, record: Callable[[StageRecord, int], None], budget: Budget,
                 clock: Clock = time.perf_counter, steps: int = 1, density: bool = False) -> None:
        self.started, self.record, self.budget, self.clock, self.steps = started, record, budget, clock, steps
        self.density = density  # the occupancy grid's density was compiled between ``started`` and the first step
        self.pending, self.timed, self.spent = True, 0, 0.0

    def loop_starts(self) -> None:
        """Right before the loop: the seconds since ``started`` (what was compiled before the first step, the
        occupancy grid's density) are compile time from now on, so no callback of the first step counts them as
        training."""
        now = self.clock()
        self._spend(now - self.started)
        self.started = now

    def before_step(self, state: LoopState) -> None:
        if self.pending and self.timed:
            self.started = self.clock()

    def _spend(self, seconds: float) -> None:
        self.spent += seconds
        self.budget.add("compile", seconds)

    def after_step(self, state: LoopState) -> None:
        if self.pending:
            self._spend(self.clock() - self.started)
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
        if not self.timed:
            self._spend(self.clock() - self.started)
        seconds = self.spent
        self.record(StageRecord(name="compile", ran=ran, why=why, seconds=seconds), iteration)


def present(callbacks: Sequence[Callback | None]) -> list[Callback]:
    """The callbacks that apply to this run (a None stands for one that does not)."""
    return [c for c in callbacks if c is not None]
