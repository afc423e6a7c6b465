"""``train()``: scene -> prior -> octree -> pseudo depth -> optimisation -> evaluation, inside one time budget.

It writes ``run_dir/checkpoint.pt`` (atomically: temp file + rename), ``run_dir/report.json`` (config, stages
that ran and why, timings, the error-against-run-time history, final metrics) and
``run_dir/eval/<split>/<frame>.png``. The set-up stages are ``stages.py``, the loop ``loop.py``, its periodic
duties ``callbacks.py``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import torch

from voxnerf.config import TrainConfig
from voxnerf.devices import resolve_device
from voxnerf.errors import TrainingDiverged
from voxnerf.files import CHECKPOINT, REPORT
from voxnerf.octree import SparseVoxelOctree
from voxnerf.prior import GeometryPrior
from voxnerf.scene import Scene
from voxnerf.training import stages
from voxnerf.training.budget import Budget
from voxnerf.training.callbacks import (
    Checkpointing,
    CompileTimer,
    LearningRateSchedule,
    OccupancyGridUpdate,
    ProgressBar,
    ProgressCallback,
    ProgressEvaluation,
    ProgressEvents,
    present,
)
from voxnerf.training.checkpoint import CheckpointWriter, load_previous, write_report
from voxnerf.training.evals import EvalViews, eval_views_of, final_eval, progress_eval, view_rays
from voxnerf.training.loop import Limits, LoopState, run_loop
from voxnerf.training.pixels import TrainingPixels, training_pixels
from voxnerf.training.records import StageRecord, TrainReport
from voxnerf.training.step import PAPER_BETA, TrainStep, make_loss_fn


@dataclass
class Run:
    """What every part of a run shares: config, run directory, budget, report and its progress events."""

    cfg: TrainConfig
    dir: Path
    device: torch.device
    budget: Budget
    report: TrainReport
    events: ProgressEvents


@dataclass
class Setup:
    """The set-up stages' products."""

    scene: Scene
    prior: GeometryPrior | None
    built: stages.ModelStage
    pixels: TrainingPixels
    octree: SparseVoxelOctree | None
    use_depth: bool
    depth_beta: float | None = None  # scene units, when the depth loss is used


def train(
    scene_dir: str | Path,
    run_dir: str | Path,
    config: TrainConfig,
    *,
    on_progress: ProgressCallback | None = None,
    should_stop: Callable[[], bool] | None = None,
    resume: bool = True,
    progress_bar: bool = True,
) -> TrainReport:
    """Train a model on ``scene_dir`` into ``run_dir`` and return the report (also written to report.json).

    Stops at ``max_iters``, when ``max_seconds`` of wall clock would be exceeded (set-up, octree, pseudo depth
    and the final evaluation included), or when ``should_stop()`` returns True (status "cancelled"; the
    checkpoint is saved). Raises TrainingDiverged if the loss or the weights become NaN/inf; the last good
    checkpoint is kept and the report says why.
    """
    cfg = config.resolved()
    run_path = Path(run_dir)
    run_path.mkdir(parents=True, exist_ok=True)
    previous = load_previous(run_path / CHECKPOINT, resume)
    budget = Budget(cfg.max_seconds, previous["train_seconds"] if previous else 0.0)
    device = resolve_device(cfg.device)
    stages.seed_everything(cfg.seed + (previous["iteration"] if previous else 0))
    report = TrainReport(config=cfg.model_dump(), device=str(device))
    run = Run(cfg, run_path, device, budget, report, ProgressEvents(on_progress, cfg, budget, report))
    setup = _set_up_scene(run, scene_dir, previous)
    return _optimise(run, setup, should_stop, progress_bar)


def _set_up_scene(run: Run, scene_dir: str | Path, previous: dict | None) -> Setup:
    """Stages load_scene, prior, hash_kernel, then the model (and the resumed state)."""
    cfg, report, events = run.cfg, run.report, run.events
    loaded = stages.load_scene_stage(scene_dir, cfg)
    report.scene = loaded.scene.summary()
    events.stage(loaded.record, 0)
    found = stages.prior_stage(loaded.scene, cfg, run.dir)
    events.stage(found.record, 0)
    if found.prior is not None:
        report.prior = found.prior.summary() | ({"fused": found.fused.summary()} if found.fused else {})
    if found.warning:
        report.warnings.append(found.warning)
    events.stage(stages.hash_kernel_stage(cfg, run.device), 0)
    built = stages.model_stage(cfg, loaded.scene, found.prior, run.device, previous)
    if built.resumed:
        report.history.extend(built.history)
        report.resumed_from_iteration = built.iteration
    pixels = training_pixels(loaded.scene, built.transform, run.device)
    return _set_up_geometry(run, loaded.scene, found, built, pixels)


def _set_up_geometry(run: Run, scene: Scene, found: stages.PriorStage, built: stages.ModelStage,
                     pixels: TrainingPixels) -> Setup:
    """Stages octree, pseudo_depth, depth_target, first_hit_cache (the per-pixel caches land in ``pixels``)."""
    cfg, report, events, iteration = run.cfg, run.report, run.events, built.iteration
    tree = stages.octree_stage(cfg, built.prior_n, pixels, built.model, run.device)
    if tree.octree is not None:
        built.model.octree = tree.octree
        report.octree = tree.octree.summary()
    events.stage(tree.record, iteration)
    depth = stages.pseudo_depth_stage(cfg, scene, built.prior_n, tree.octree, pixels, built.model, run.device)
    pixels.pseudo_t = depth.pseudo_t
    if depth.warning:
        report.warnings.append(depth.warning)
    events.stage(depth.record, iteration)
    target = stages.depth_target_stage(cfg, scene, found.prior, found.fused, pixels, built.transform)
    pixels.depth_t, pixels.depth_beta_scale = target.target_t, target.beta_scale
    if target.summary is not None:
        report.depth = target.summary
    events.stage(target.record, iteration)
    hits = stages.first_hit_stage(tree.octree, pixels, built.model)
    pixels.hit_t, pixels.hit = hits.hit_t, hits.hit
    events.stage(hits.record, iteration)
    return Setup(scene, found.prior, built, pixels, tree.octree, target.target_t is not None, target.beta)


def _patches(cfg: TrainConfig, setup: Setup) -> tuple[bool, int, int]:
    """(whether batches carry smoothness patches, patch side, rays of all patches)."""
    use_patches = setup.use_depth and cfg.smooth_patches > 0 and cfg.lambda_smooth > 0
    patch = min(cfg.patch_size, setup.pixels.shape[1], setup.pixels.shape[2])
    return use_patches, patch, cfg.smooth_patches * patch * patch if use_patches else 0


def _make_step(run: Run, setup: Setup) -> tuple[TrainStep, stages.CompileStage]:
    """The loss (depth beta in the report), the compile stage, the sampler and the batch generator."""
    cfg, model, iteration = run.cfg, setup.built.model, setup.built.iteration
    use_patches, patch, n_patch_rays = _patches(cfg, setup)
    beta = setup.depth_beta or PAPER_BETA
    run.report.depth_beta = beta if setup.use_depth else None
    compiled = stages.compile_stage(cfg, make_loss_fn(model, cfg, beta, n_patch_rays, patch))
    if compiled.record is not None:
        run.events.stage(compiled.record, iteration)
    sampler = model.sampler()
    gen = torch.Generator(device=run.device)
    gen.manual_seed(cfg.seed + iteration)
    step = TrainStep(model, setup.built.optimizer, setup.pixels, cfg, compiled.loss_fn, use_patches, sampler, gen)
    return step, compiled


def _optimise(run: Run, setup: Setup, should_stop: Callable[[], bool] | None, progress_bar: bool) -> TrainReport:
    cfg, budget, built = run.cfg, run.budget, setup.built
    step, compiled = _make_step(run, setup)
    views = eval_views_of(setup.scene, built.transform)
    evaluate = partial(progress_eval, built.model, views, cfg, run.report.history, budget)
    evaluation = ProgressEvaluation(evaluate, budget, cfg, view_rays(views), run.events)
    save = CheckpointWriter(run.dir / CHECKPOINT, built.model, built.optimizer, budget, run.report.history,
                            setup.scene)
    saving = Checkpointing(save, cfg.checkpoint_every_s)
    timer = CompileTimer(compiled.started, run.events.stage) if compiled.record is None else None
    bar = ProgressBar.create(cfg.max_iters, built.iteration, progress_bar)
    callbacks = present([evaluation, LearningRateSchedule(built.optimizer, cfg.lr, cfg.lr_decay_iters), timer, bar,
                         OccupancyGridUpdate.for_config(built.model, cfg, setup.octree is not None), saving,
                         run.events])
    state = LoopState(built.iteration)
    try:
        status = run_loop(step, state, callbacks, Limits(cfg.max_iters, budget, evaluation.final_eval_reserve,
                                                         should_stop))
    except TrainingDiverged as exc:
        bar.close()
        raise _diverged(run, exc, state.iteration) from None
    bar.close()
    if timer is not None:
        timer.finish(state.iteration)
    return _finish(run, setup, views, save, status, state)


def _diverged(run: Run, exc: TrainingDiverged, iteration: int) -> TrainingDiverged:
    """Write the diverged report; the error to raise, saying whether a good checkpoint is kept."""
    ckpt_path = run.dir / CHECKPOINT
    kept = ckpt_path.is_file()
    report = run.report
    report.status, report.error, report.iteration, report.checkpoint_kept = "diverged", str(exc), iteration, kept
    write_report(report, run.dir / REPORT)
    where = f"last good checkpoint kept at {ckpt_path}" if kept else "no checkpoint yet"
    return TrainingDiverged(f"{exc}; {where}")


def _finish(run: Run, setup: Setup, views: EvalViews, save: CheckpointWriter, status: str,
            state: LoopState) -> TrainReport:
    """The train stage, the last checkpoint, the final evaluation and the report."""
    report, budget, iteration = run.report, run.budget, state.iteration
    train_seconds = budget.train_seconds
    report.stages.append(StageRecord(name="train", ran=iteration > 0, why=f"{status} at iteration {iteration}",
                                     seconds=train_seconds))
    save(iteration)
    _final_eval_stage(run, setup, views, status, train_seconds, state)
    use_patches, _, n_patch_rays = _patches(run.cfg, setup)
    report.status, report.iteration = status, iteration
    report.train_seconds, report.wall_seconds = round(train_seconds, 3), round(budget.wall, 3)
    report.throughput = throughput(run.cfg, iteration, report.stages, use_patches, n_patch_rays)
    write_report(report, run.dir / REPORT)
    run.events.emit("done", iteration, state.last_loss)
    return report


def _final_eval_stage(run: Run, setup: Setup, views: EvalViews, status: str, train_seconds: float,
                      state: LoopState) -> None:
    cfg, iteration, t0 = run.cfg, state.iteration, time.perf_counter()
    if not (cfg.final_eval and status == "succeeded" and views):
        why = ("disabled" if not cfg.final_eval else "run cancelled" if status == "cancelled"
               else "the scene has no evaluation split")
        run.events.stage(StageRecord(name="final_eval", ran=False, why=why, seconds=time.perf_counter() - t0),
                         iteration)
        return
    run.events.emit("final_eval", iteration, state.last_loss)
    metrics, record = final_eval(setup.built.model, views, cfg, run.dir / "eval", run.budget, train_seconds,
                                 iteration, state.last_loss)
    run.report.history.append(record)
    run.report.metrics = metrics
    run.events.stage(StageRecord(name="final_eval", ran=True, why=f"all views of splits {sorted(views)}",
                                 seconds=time.perf_counter() - t0), iteration)


def throughput(cfg: TrainConfig, iterations: int, records: list[StageRecord], patches: bool,
               patch_rays: int) -> dict:
    """Rays per step, rays and samples per second of training time less the compile stage's."""
    train_s = next((s.seconds for s in records if s.name == "train"), 0.0)
    compile_s = next((s.seconds for s in records if s.name == "compile" and s.ran), 0.0)
    rays_per_step = int(cfg.rays_per_batch) + (patch_rays if patches else 0)
    rays = rays_per_step * iterations
    seconds = max(train_s - compile_s, 1e-9)
    return {"rays_per_step": rays_per_step, "rays_per_s": rays / seconds,
            "samples_per_s": rays * cfg.samples_per_ray / seconds, "seconds_excluding_compile": seconds}
