"""``train()``: scene -> prior -> octree -> pseudo depth -> optimisation -> evaluation, inside one time budget.

It writes ``run_dir/checkpoint.pt`` (atomically: temp file + rename), ``run_dir/report.json`` (config, stages
that ran and why, timings, the error-against-run-time history, final metrics) and
``run_dir/eval/<split>/<frame>.png``. The set-up stages run in the order of ``setup.py`` (their work is in
``stages/``, one module per stage), the loop is ``loop.py``, its periodic
duties ``callbacks.py``.

``should_stop()`` is asked between set-up stages, at every step and between the final evaluation's views: a
cancelled run stops in whichever stage it is. ``may_write()`` (a service worker's lease) is asked before every
file the run writes: when it says no, another attempt owns the run directory, and this one raises
:class:`LeaseLost` having written nothing more (the final evaluation renders into a private directory that
replaces ``eval/`` only after that check).
"""

from __future__ import annotations

import json
import shutil
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np
import torch

from voxnerf.cameras.pose_refinement import refined_frames
from voxnerf.config import TrainConfig
from voxnerf.data.image_io import write_atomic
from voxnerf.devices import compute_environment, resolve_device
from voxnerf.errors import RunError, TrainingDiverged
from voxnerf.files import CHECKPOINT, REFINED_POSES, REPORT
from voxnerf.model.losses import PAPER_BETA
from voxnerf.model.samplers import VoxNeRFSampler
from voxnerf.training import stages
from voxnerf.training.budget import Budget, TrainingProgress
from voxnerf.training.callbacks import (
    Checkpointing,
    CoarseToFine,
    CompileTimer,
    DepthWeightSchedule,
    Evaluate,
    LearningRateSchedule,
    OccupancyGridUpdate,
    ProgressBar,
    ProgressCallback,
    ProgressEvaluation,
    ProgressEvents,
    present,
)
from voxnerf.training.checkpoint import CheckpointWriter, load_previous, write_report
from voxnerf.training.eval_passes import (
    EvalViews,
    eval_views_of,
    final_eval,
    progress_eval,
    progress_views,
    view_rays,
)
from voxnerf.training.loop import Callback, Limits, LoopState, run_loop
from voxnerf.training.records import StageRecord, TrainReport
from voxnerf.training.setup import SetupContext, run_setup
from voxnerf.training.step import TrainStep, make_loss_fn
from voxnerf.training.weight_average import WeightAverage


class LeaseLost(RunError):
    """``may_write()`` said no: another attempt owns the run directory, so this one stops writing."""


class StoppedInSetUp(Exception):
    """``should_stop()`` said yes between two set-up stages."""


def always() -> bool:
    return True


def never() -> bool:
    return False


@dataclass
class Run:
    """What every part of a run shares: config, run directory, budget, report and its progress events, and
    the caller's ``should_stop`` (cancel) and ``may_write`` (still the run's owner) questions."""

    cfg: TrainConfig
    dir: Path
    device: torch.device
    budget: Budget
    report: TrainReport
    events: ProgressEvents
    should_stop: Callable[[], bool] = never
    may_write: Callable[[], bool] = always

    def stop_point(self) -> None:
        """Between set-up stages: raise StoppedInSetUp when the caller asks to stop."""
        if self.should_stop():
            raise StoppedInSetUp()

    def fence(self) -> None:
        """Before writing into the run directory: raise LeaseLost unless the caller still owns it."""
        if not self.may_write():
            raise LeaseLost(f"{self.dir}: another attempt owns this run now; this one stopped without writing")


def train(
    scene_dir: str | Path,
    run_dir: str | Path,
    config: TrainConfig,
    *,
    on_progress: ProgressCallback | None = None,
    should_stop: Callable[[], bool] | None = None,
    resume: bool = True,
    progress_bar: bool = True,
    may_write: Callable[[], bool] | None = None,
) -> TrainReport:
    """Train a model on ``scene_dir`` into ``run_dir`` and return the report (also written to report.json).

    Stops at ``max_iters``, when ``max_seconds`` of training are spent (the loop's steps and the progress
    evaluations and checkpoints between them; the set-up, the step's compilation and the final evaluation come on
    top and are reported by part: :mod:`voxnerf.training.budget`), or when ``should_stop()`` returns True (status
    "cancelled": asked between set-up stages, at every step and between final-evaluation views; the checkpoint is
    saved once training started). Raises TrainingDiverged if the loss or the weights become NaN/inf; the last good
    checkpoint is kept and the report says why. Raises LeaseLost, having written nothing more, as soon as
    ``may_write()`` (asked before each file) returns False.
    """
    cfg = config.resolved()
    run_path = Path(run_dir)
    run_path.mkdir(parents=True, exist_ok=True)
    previous = load_previous(run_path / CHECKPOINT, resume)
    budget = Budget(cfg.run.max_seconds, previous["train_seconds"] if previous else 0.0)
    device = resolve_device(cfg.run.device)
    stages.seed_everything(cfg.run.seed + (previous["iteration"] if previous else 0))
    report = TrainReport(config=cfg.flat(), device=str(device))
    run = Run(cfg, run_path, device, budget, report, ProgressEvents(on_progress, cfg, budget, report),
              should_stop or never, may_write or always)
    run.events.checkpoint_iteration = previous["iteration"] if previous else None
    try:
        setup = _set_up(run, scene_dir, previous)
    except StoppedInSetUp:
        return _stopped_in_set_up(run, previous)
    return _optimise(run, setup, progress_bar)


def _stopped_in_set_up(run: Run, previous: dict | None) -> TrainReport:
    """The report of a run cancelled before its first step (a resumed run keeps its checkpoint as it was)."""
    report, budget = run.report, run.budget
    iteration = previous["iteration"] if previous else 0
    report.stages.append(StageRecord(name="train", ran=False, why="cancelled during set-up", seconds=0.0))
    report.status, report.iteration = "cancelled", iteration
    report.train_seconds, report.wall_seconds = round(budget.train_seconds, 3), round(budget.wall, 3)
    _write_report(run)
    run.events.emit("done", iteration)
    return report


def _set_up(run: Run, scene_dir: str | Path, previous: dict | None) -> SetupContext:
    """The set-up stages (:data:`voxnerf.training.setup.SETUP_STAGES`); ``run.cfg`` then holds the resolved
    config."""
    ctx = SetupContext(run.cfg, Path(scene_dir), run.dir, run.device, run.report, previous, run.fence)
    run_setup(ctx, run.events.stage, run.stop_point)
    run.cfg = ctx.cfg
    return ctx


def _patches(cfg: TrainConfig, setup: SetupContext) -> tuple[bool, int, int]:
    """(whether batches carry smoothness patches, patch side, rays of all patches)."""
    use_patches = setup.use_depth and cfg.loss.smooth_patches > 0 and cfg.loss.lambda_smooth > 0
    patch = min(cfg.loss.patch_size, *setup.pixels.smallest_side)
    return use_patches, patch, cfg.loss.smooth_patches * patch * patch if use_patches else 0


def _make_step(run: Run, setup: SetupContext) -> tuple[TrainStep, stages.CompileStage]:
    """The loss (depth beta in the report), the compile stage, the sampler and the batch generator."""
    cfg, model, iteration = run.cfg, setup.built.model, setup.built.iteration
    use_patches, patch, n_patch_rays = _patches(cfg, setup)
    beta = setup.depth_beta or PAPER_BETA
    run.report.depth_beta = beta if setup.use_depth else None
    n_prior = cfg.loss.prior_rays if setup.prior_rays is not None else 0
    compiled = stages.compile_stage(cfg, make_loss_fn(model, cfg, beta, n_patch_rays, patch, n_prior))
    if compiled.record is not None:
        run.events.stage(compiled.record, iteration)
    sampler = model.sampler()
    gen = torch.Generator(device=run.device)
    gen.manual_seed(cfg.run.seed + iteration)
    step = TrainStep(model, setup.built.optimizer, setup.pixels, cfg, compiled.loss_fn, use_patches, sampler, gen,
                     setup.prior_rays)
    return step, compiled


def _progress_evaluator(evaluate: Callable[..., tuple[float, float]]) -> Evaluate:
    """``evaluate`` (:func:`progress_eval` less its last arguments) as the loop calls it, the process's first
    evaluation warmed up (``warm_up``)."""
    first = True

    def progress(iteration: int, loss: float, rays: int | None) -> tuple[float, float]:
        nonlocal first
        warm_up, first = first, False
        return evaluate(iteration, loss, rays, warm_up=warm_up)

    return progress


def _optimise(run: Run, setup: SetupContext, progress_bar: bool) -> TrainReport:
    cfg, budget, built = run.cfg, run.budget, setup.built
    budget.start_training()  # the set-up ends here: building and compiling the step are the loop's
    step, compiled = _make_step(run, setup)
    misses = step.sampler.misses if isinstance(step.sampler, VoxNeRFSampler) else None
    run.report.runtime = compute_environment(run.device) | {"octree_misses": misses}
    views = eval_views_of(setup.scene, built.transform)
    average = WeightAverage.of(built.model.field, cfg.schedule.weight_average, built.averaged_field)
    evaluate = _progress_evaluator(_averaged(average, partial(progress_eval, built.model, views, cfg,
                                                              run.report.history, budget)))
    evaluation = ProgressEvaluation(evaluate, budget, cfg, view_rays(progress_views(views, cfg.evaluation.eval_views)),
                                    run.events, run.report.warnings)
    save = _fenced(run, CheckpointWriter(run.dir / CHECKPOINT, built.model, built.optimizer, budget,
                                         run.report.history, setup.scene, average))
    saving = Checkpointing(save, cfg.run.checkpoint_every_s, budget)
    grid = OccupancyGridUpdate.for_config(built.model, cfg, setup.octree is not None)
    timer = _compile_density_and_time(run, compiled, step, grid)
    bar = ProgressBar.create(cfg.run.max_iters, built.iteration, progress_bar)
    schedules = _schedules(cfg, built, step, TrainingProgress(budget, cfg.run.max_iters))
    callbacks = present([average, evaluation, *schedules, timer, bar, grid, saving, run.events])
    state = LoopState(built.iteration)
    if timer is not None:
        timer.loop_starts()
    try:
        status = run_loop(step, state, callbacks, Limits(cfg.run.max_iters, budget, run.should_stop))
    except TrainingDiverged as exc:
        bar.close()
        raise _diverged(run, exc, state.iteration) from None
    finally:
        built.model.field.encoding.set_active_levels(float(cfg.model.hash_levels))  # every level on, whatever happened
    bar.close()
    if timer is not None:
        timer.finish(state.iteration)
    return _finish(run, setup, views, save, status, state, average)


def _averaged(average: WeightAverage | None, evaluate: Callable[..., tuple[float, float]]
              ) -> Callable[..., tuple[float, float]]:
    """``evaluate`` run on the field's averaged parameters (the live ones back after it), or as it is."""
    if average is None:
        return evaluate

    def on_average(*args, **kwargs) -> tuple[float, float]:
        with average.applied():
            return evaluate(*args, **kwargs)

    return on_average


def _compile_density_and_time(run: Run, compiled: stages.CompileStage, step: TrainStep,
                              grid: OccupancyGridUpdate | None) -> CompileTimer | None:
    """When the step is compiled: compile the occupancy grid's density now, before the first step (its time then
    counts in the compile stage, not in the step of the first grid update), and return the compile stage's
    timer; None when the step is not compiled."""
    if compiled.record is not None:
        return None
    density = grid is not None and grid.compile_density()
    return CompileTimer(compiled.started, run.events.stage, run.budget, steps=step.graphs, density=density)


def _schedules(cfg: TrainConfig, built: stages.ModelStage, step: TrainStep,
               progress: TrainingProgress) -> list[Callback | None]:
    """What changes with the run's progress: the learning rate, the hash levels switched on (coarse_to_fine),
    lambda_d (depth_weight_final)."""
    levels = CoarseToFine(built.model.field.encoding, cfg.schedule.coarse_levels, cfg.schedule.coarse_to_fine, progress,
                          cfg.schedule.lr_decay_iters) if cfg.schedule.coarse_to_fine > 0 else None
    depth = DepthWeightSchedule(step.depth_weight, cfg.loss.lambda_depth, cfg.loss.depth_weight_final,
                                progress) if cfg.loss.depth_weight_final < 1 else None
    schedule = cfg.schedule
    return [LearningRateSchedule(built.optimizer, schedule.lr_decay_iters, schedule.lr_schedule, schedule.lr_final,
                                 progress),
            levels, depth]


def _fenced(run: Run, save: Callable[[int], None]) -> Callable[[int], None]:
    """``save`` behind the run's fence (:meth:`Run.fence`); once it saved, the run's progress events name
    ``iteration`` as the last complete checkpoint."""

    def fenced_save(iteration: int) -> None:
        run.fence()
        save(iteration)
        run.events.checkpoint_iteration = iteration

    return fenced_save


def _diverged(run: Run, exc: TrainingDiverged, iteration: int) -> TrainingDiverged:
    """Write the diverged report; the error to raise, saying whether a good checkpoint is kept."""
    run.budget.end_training()
    ckpt_path = run.dir / CHECKPOINT
    kept = ckpt_path.is_file()
    report = run.report
    report.status, report.error, report.iteration, report.checkpoint_kept = "diverged", str(exc), iteration, kept
    _write_report(run)
    where = f"last good checkpoint kept at {ckpt_path}" if kept else "no checkpoint yet"
    return TrainingDiverged(f"{exc}; {where}")


def _finish(run: Run, setup: SetupContext, views: EvalViews, save: Callable[[int], None], status: str,
            state: LoopState, average: WeightAverage | None = None) -> TrainReport:
    """The train stage, the last checkpoint, the final evaluation (of the averaged field, with ``average``) and
    the report."""
    report, budget, iteration = run.report, run.budget, state.iteration
    budget.end_training()
    train_seconds = budget.train_seconds
    report.stages.append(StageRecord(name="train", ran=iteration > 0, why=f"{status} at iteration {iteration}",
                                     seconds=train_seconds))
    save(iteration)
    if average is not None:
        average.apply()
    if setup.built.model.pose_refinement is not None:
        _write_refined_poses(run, setup)
    if setup.built.model.appearance is not None:
        report.appearance = setup.built.model.appearance.summary()
    status = _final_eval_stage(run, setup, views, status, train_seconds, state)
    use_patches, _, n_patch_rays = _patches(run.cfg, setup)
    report.status, report.iteration = status, iteration
    report.train_seconds, report.wall_seconds = round(train_seconds, 3), round(budget.wall, 3)
    report.throughput = throughput(run.cfg, iteration - setup.built.iteration, budget.this_command_training,
                                   use_patches, n_patch_rays)
    _write_report(run)
    run.events.emit("done", iteration, state.last_loss)
    return report


def _write_report(run: Run) -> None:
    """report.json, with the budget's accounting as it stands (:meth:`Budget.accounting`), behind the fence."""
    run.report.budget = run.budget.accounting()
    run.fence()
    write_report(run.report, run.dir / REPORT)


def _write_refined_poses(run: Run, setup: SetupContext) -> None:
    """``refined_poses.json`` (the training frames' learnt poses, scene units) and their summary in the report."""
    model, scene = setup.built.model, setup.scene
    frames = [scene.frames[i] for i in scene.train_indices]
    poses = refined_frames(model.pose_refinement, [f.file_path for f in frames], np.stack([f.c2w for f in frames]),
                           model.transform)
    run.fence()
    write_atomic(run.dir / REFINED_POSES, json.dumps(poses, indent=1).encode())
    run.report.pose_refinement = model.pose_refinement.summary(model.transform.scale) | {"file": REFINED_POSES}


def _final_eval_stage(run: Run, setup: SetupContext, views: EvalViews, status: str, train_seconds: float,
                      state: LoopState) -> str:
    """Evaluate every view (when the run succeeded and has views); the run's status: ``cancelled`` when
    ``should_stop()`` interrupted the evaluation (its renders are then dropped)."""
    cfg, iteration, t0 = run.cfg, state.iteration, time.perf_counter()
    if not (cfg.evaluation.final_eval and status == "succeeded" and views):
        why = ("disabled" if not cfg.evaluation.final_eval else "run cancelled" if status == "cancelled"
               else "the scene has no evaluation split")
        run.events.stage(StageRecord(name="final_eval", ran=False, why=why, seconds=time.perf_counter() - t0),
                         iteration)
        return status
    run.events.emit("final_eval", iteration, state.last_loss)
    private = run.dir / f".eval-{uuid.uuid4().hex}"
    try:
        done = final_eval(setup.built.model, views, cfg, private, run.budget, train_seconds, iteration,
                          state.last_loss, should_stop=run.should_stop)
        if done is not None:
            _replace_eval_dir(run, private)
    finally:
        shutil.rmtree(private, ignore_errors=True)
    seconds = time.perf_counter() - t0
    run.budget.add("final_eval", seconds)
    if done is None:
        run.events.stage(StageRecord(name="final_eval", ran=False, why="run cancelled during the evaluation",
                                     seconds=seconds), iteration)
        return "cancelled"
    metrics, record = done
    run.report.history.append(record)
    run.report.metrics = metrics
    run.events.stage(StageRecord(name="final_eval", ran=True, why=f"all views of splits {sorted(views)}",
                                 seconds=seconds), iteration)
    return status


def _replace_eval_dir(run: Run, rendered: Path) -> None:
    """Make the final evaluation's renders (written to the private ``rendered``) the run's ``eval/``, once the
    fence says this attempt still owns the run."""
    run.fence()
    target = run.dir / "eval"
    if target.exists():
        doomed = run.dir / f".eval-old-{uuid.uuid4().hex}"
        target.rename(doomed)
        shutil.rmtree(doomed, ignore_errors=True)
    if rendered.is_dir():
        rendered.rename(target)


def throughput(cfg: TrainConfig, steps: int, train_seconds: float, patches: bool, patch_rays: int) -> dict:
    """Rays per step, rays and samples per second of this command's ``steps`` over its ``train_seconds`` (the
    training loop's, set-up, compilation, evaluations and checkpoints left out: :class:`Budget`)."""
    rays_per_step = int(cfg.schedule.rays_per_batch) + (patch_rays if patches else 0)
    rays = rays_per_step * steps
    seconds = max(train_seconds, 1e-9)
    return {"rays_per_step": rays_per_step, "rays_per_s": rays / seconds,
            "samples_per_s": rays * cfg.sampling.samples_per_ray / seconds, "seconds_excluding_compile": seconds}
