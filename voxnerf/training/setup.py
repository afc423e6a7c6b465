"""The set-up of a run as a list of stages with one protocol, and the one loop that runs them.

A stage (:class:`SetupStage`) has a ``name`` and ``run(ctx)``: it reads what earlier stages made from the
:class:`SetupContext`, puts its own product there (and its part of the report), and returns its
:class:`StageRecord`, which says whether the stage applied to this run and why (``ran`` and ``why``), or None for
the steps that only build (the model). The work of each stage lives in its own module of
:mod:`voxnerf.training.stages`, named as report.json names the stage; a stage here only wires its inputs and
products.

:func:`run_setup` runs :data:`SETUP_STAGES` in order: after each it keeps the report's config in step with the
context's (stages resolve ``auto`` values), emits the stage's event and asks whether to stop (``StoppedInSetUp``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import torch

from voxnerf.config import TrainConfig
from voxnerf.data.scene import Scene
from voxnerf.prior.loading import GeometryPrior
from voxnerf.prior.octree import SparseVoxelOctree
from voxnerf.training import stages
from voxnerf.training.pixels import TrainingPixels, training_pixels
from voxnerf.training.prior_rays import PriorRayBank
from voxnerf.training.records import StageRecord, TrainReport
from voxnerf.training.stages.colour_prior import colour_prior_stage
from voxnerf.training.stages.corrections import corrections_stage
from voxnerf.training.stages.focal import focal_stage
from voxnerf.training.stages.weight_decay import weight_decay_stage
from voxnerf.training.stages.window_check import window_check_stage


@dataclass
class SetupContext:
    """What the set-up stages share: the run's inputs (config, directories, device, report, the checkpoint a
    resumed run continues from) and the products of the stages so far. ``cfg`` is the run's config as resolved
    so far; ``fence`` is asked before a stage writes into the run directory."""

    cfg: TrainConfig
    scene_dir: Path
    run_dir: Path
    device: torch.device
    report: TrainReport
    previous: dict | None
    fence: Callable[[], None]
    scene: Scene | None = None
    found: stages.PriorStage | None = None  # the prior found or fused
    built: stages.ModelStage | None = None  # the model, its optimiser, where a resumed run continues
    pixels: TrainingPixels | None = None
    octree: SparseVoxelOctree | None = None  # the sampler's octree (carved, where carving ran)
    target: stages.DepthTargetStage | None = None
    prior_rays: PriorRayBank | None = None

    @property
    def iteration(self) -> int:
        """The iteration the run starts from (a resumed run's), as the stage events report it."""
        return self.built.iteration if self.built is not None else 0

    @property
    def prior(self) -> GeometryPrior | None:
        return self.found.prior if self.found is not None else None

    @property
    def use_depth(self) -> bool:
        """Whether the run has a depth target (and so a depth loss)."""
        return self.target is not None and self.target.target_t is not None

    @property
    def depth_beta(self) -> float | None:
        """The depth loss's beta, scene units (None without a depth loss, or where the rule left it unset)."""
        return self.target.beta if self.target is not None else None


class SetupStage(Protocol):
    name: str

    def run(self, ctx: SetupContext) -> StageRecord | None:
        """Do the stage's work on ``ctx``, put its product there; its record (None: nothing to report)."""


@dataclass(frozen=True)
class Stage:
    """A :class:`SetupStage` made of a function of the context."""

    name: str
    run: Callable[[SetupContext], StageRecord | None]


def _load_scene(ctx: SetupContext) -> StageRecord:
    loaded = stages.load_scene_stage(ctx.scene_dir, ctx.cfg)
    ctx.scene = loaded.scene
    ctx.report.scene = loaded.scene.summary()
    return loaded.record


def _corrections(ctx: SetupContext) -> StageRecord:
    chosen = corrections_stage(ctx.cfg, ctx.scene, ctx.previous)
    ctx.cfg = chosen.cfg
    return chosen.record


def _weight_decay(ctx: SetupContext) -> StageRecord:
    decay = weight_decay_stage(ctx.cfg, ctx.scene)
    ctx.cfg = decay.cfg
    return decay.record


def _prior(ctx: SetupContext) -> StageRecord:
    ctx.fence()  # the prior stage may write the fused prior into the run directory
    found = ctx.found = stages.prior_stage(ctx.scene, ctx.cfg, ctx.run_dir)
    if found.prior is not None:
        ctx.report.prior = found.prior.summary() | ({"fused": found.fused.summary()} if found.fused else {})
    if found.warning:
        ctx.report.warnings.append(found.warning)
    return found.record


def _focal(ctx: SetupContext) -> StageRecord:
    focal = focal_stage(ctx.cfg, ctx.scene, ctx.prior)
    ctx.cfg, ctx.scene = focal.cfg, focal.scene  # renders of the scene's views use the measured scale too
    return focal.record


def _hash_kernel(ctx: SetupContext) -> StageRecord:
    return stages.hash_kernel_stage(ctx.cfg, ctx.device)


def _model(ctx: SetupContext) -> None:
    built = ctx.built = stages.model_stage(ctx.cfg, ctx.scene, ctx.prior, ctx.device, ctx.previous)
    if built.resumed:
        ctx.report.history.extend(built.history)
        ctx.report.resumed_from_iteration = built.iteration
    ctx.pixels = training_pixels(ctx.scene, built.transform, ctx.device)


def _octree(ctx: SetupContext) -> StageRecord:
    tree = stages.octree_stage(ctx.cfg, ctx.built.prior_n, ctx.pixels, ctx.built.model, ctx.device)
    if tree.octree is not None:
        ctx.octree = ctx.built.model.octree = tree.octree
        ctx.report.octree = tree.octree.summary()
    return tree.record


def _pseudo_depth(ctx: SetupContext) -> StageRecord:
    depth = stages.pseudo_depth_stage(ctx.cfg, ctx.scene, ctx.built.prior_n, ctx.octree, ctx.pixels,
                                      ctx.built.model, ctx.device)
    ctx.pixels.pseudo_t = depth.pseudo_t
    if depth.warning:
        ctx.report.warnings.append(depth.warning)
    return depth.record


def _depth_target(ctx: SetupContext) -> StageRecord:
    found = ctx.found
    target = ctx.target = stages.depth_target_stage(ctx.cfg, ctx.scene, found.prior, found.fused, ctx.pixels,
                                                    ctx.built.transform)
    ctx.pixels.depth_t, ctx.pixels.depth_beta_scale = target.target_t, target.beta_scale
    if target.summary is not None:
        ctx.report.depth = target.summary
    return target.record


def _carving(ctx: SetupContext) -> StageRecord:
    """The sampler octree less the leaves the sensor depth shows empty (the model's too)."""
    carved = stages.carving_stage(ctx.cfg, ctx.octree, ctx.pixels, ctx.target, ctx.built.transform.scale)
    if carved.octree is not None:
        ctx.octree = ctx.built.model.octree = carved.octree
        ctx.report.octree = carved.octree.summary()
    return carved.record


def _first_hit(ctx: SetupContext) -> StageRecord:
    hits = stages.first_hit_stage(ctx.octree, ctx.pixels, ctx.built.model, ctx.cfg.run.setup_cache)
    ctx.pixels.hit_t, ctx.pixels.hit = hits.hit_t, hits.hit
    return hits.record


def _window_check(ctx: SetupContext) -> StageRecord:
    sensor_t = ctx.target.sensor_t if ctx.target is not None else None
    checked = window_check_stage(ctx.cfg, ctx.built.model, ctx.pixels, sensor_t, ctx.built.prior_n,
                                 ctx.built.transform.scale)
    if checked.summary is not None:
        ctx.report.window_check = checked.summary
    if checked.sampler is not None:  # sampler 'auto' chose: the run and its model (checkpoints, renders) use it
        ctx.cfg = ctx.cfg.updated(sampler=checked.sampler)
        ctx.built.model.use_sampler(checked.sampler)
    return checked.record


def _colour_prior(ctx: SetupContext) -> StageRecord:
    pooled = colour_prior_stage(ctx.cfg, ctx.octree is not None, ctx.pixels)
    ctx.built.model.colour_prior = pooled.prior
    return pooled.record


def _prior_rays(ctx: SetupContext) -> StageRecord:
    extra = stages.prior_rays_stage(ctx.cfg, ctx.built.prior_n, ctx.use_depth, ctx.octree, ctx.pixels,
                                    ctx.built.model, ctx.device)
    ctx.prior_rays = extra.bank
    return extra.record


SETUP_STAGES: tuple[SetupStage, ...] = (
    Stage("load_scene", _load_scene),
    Stage("corrections", _corrections),  # resolves "auto" appearance and pose refinement
    Stage("weight_decay", _weight_decay),  # resolves "auto" field weight decay
    Stage("prior", _prior),
    Stage("focal", _focal),  # resolves "auto" focal scale
    Stage("hash_kernel", _hash_kernel),
    Stage("model", _model),
    Stage("octree", _octree),
    Stage("pseudo_depth", _pseudo_depth),
    Stage("depth_target", _depth_target),
    Stage("octree_carving", _carving),
    Stage("first_hit_cache", _first_hit),
    Stage("window_check", _window_check),  # the window against the depth maps; resolves "auto" sampler
    Stage("colour_prior", _colour_prior),  # after the sampler's choice: only the octree's hits look it up
    Stage("prior_rays", _prior_rays),
)


def run_setup(ctx: SetupContext, emit: Callable[[StageRecord, int], None], stop_point: Callable[[], None],
              setup_stages: tuple[SetupStage, ...] = SETUP_STAGES) -> SetupContext:
    """Run ``setup_stages`` in order on ``ctx``: after each, the report's config follows the context's (the
    "auto" values resolved so far), the stage's record goes to ``emit`` (with the iteration the run starts
    from) and ``stop_point`` may stop the set-up."""
    for stage in setup_stages:
        before = ctx.cfg
        record = stage.run(ctx)
        if ctx.cfg is not before:  # the stage resolved a setting
            ctx.report.config = ctx.cfg.flat()
        if record is not None:
            emit(record, ctx.iteration)
        stop_point()
    return ctx
