"""The set-up stages of a run, in the order ``train()`` runs them.

Each stage is a function that times itself and returns a :class:`StageRecord` (whether it ran, why, seconds)
with what it produced. The model stage (scene box, model, optimiser, resume) has no record of its own.
"""

from __future__ import annotations

import random
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from voxnerf import hash_kernel
from voxnerf.config import TrainConfig
from voxnerf.model import VoxNeRFModel
from voxnerf.octree import SparseVoxelOctree, coverage_octree
from voxnerf.prior import GeometryPrior, load_prior
from voxnerf.pseudo_depth import PriorDepthRenderer
from voxnerf.scene import Scene, SceneTransform, load_scene
from voxnerf.training.pixels import TrainingPixels, per_pixel
from voxnerf.training.records import EvalRecord, StageRecord
from voxnerf.training.step import LossFn

MIN_PRIOR_COVERAGE = 0.05  # below this fraction of training pixels seeing the prior, the report warns
COVERAGE_RAYS = 65_536  # training rays that choose the sampler octree's leaf (voxnerf.octree.coverage_octree)


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def _record(name: str, ran: bool, why: str, started: float) -> StageRecord:
    return StageRecord(name=name, ran=ran, why=why, seconds=time.perf_counter() - started)


@dataclass
class SceneStage:
    record: StageRecord
    scene: Scene


def load_scene_stage(scene_dir: str | Path, cfg: TrainConfig) -> SceneStage:
    t0 = time.perf_counter()
    scene = load_scene(scene_dir, downscale=cfg.downscale)
    why = f"{len(scene.frames)} frames, {len(scene.train_indices)} for training"
    return SceneStage(_record("load_scene", True, why, t0), scene)


@dataclass
class PriorStage:
    record: StageRecord
    prior: GeometryPrior | None
    warning: str | None = None  # the sampler or the depth loss needs a prior the scene lacks


def prior_stage(scene: Scene, cfg: TrainConfig) -> PriorStage:
    t0 = time.perf_counter()
    needs_prior = cfg.sampler == "voxnerf" or cfg.depth_loss
    if scene.prior_path is None:
        record = _record("prior", False, "the scene has no prior", t0)
        if not needs_prior:
            return PriorStage(record, None)
        return PriorStage(record, None, (
            f"sampler {cfg.sampler!r}{' and the depth loss' if cfg.depth_loss else ''} need a prior; "
            "the scene has none, so sampling falls back to the occupancy grid and no depth loss is used"))
    prior = load_prior(scene.prior_path, scene.prior_sigma, seed=cfg.seed)
    why = "sets the scene box" + (" and guides sampling / depth" if needs_prior else " only (not needed else)")
    if scene.prior_key == "ply_file_path":
        why += f"; from nerfstudio's ply_file_path ({scene.prior_path.name}), no prior_file_path given"
    return PriorStage(_record("prior", True, f"{prior.kind} prior, sigma {prior.sigma:.4g} "
                              f"({'estimated' if prior.sigma_estimated else 'given'}); {why}", t0), prior)


def hash_kernel_stage(cfg: TrainConfig, device: torch.device) -> StageRecord:
    t0 = time.perf_counter()
    if device.type != "cpu":
        return _record("hash_kernel", False, f"on {device.type} the hash encoding stays in PyTorch", t0)
    if not cfg.hash_kernel:
        return _record("hash_kernel", False, "disabled (--no-hash-kernel): the hash encoding stays in PyTorch", t0)
    if hash_kernel.available():
        return _record("hash_kernel", True,
                       "the hash encoding runs in its C kernel (voxnerf/hashgrid.c; built once, cached)", t0)
    return _record("hash_kernel", False, f"C kernel unavailable ({hash_kernel.unavailable_reason()}): the hash "
                   "encoding stays in PyTorch", t0)


def scene_box(scene: Scene, prior: GeometryPrior | None) -> tuple[SceneTransform, np.ndarray]:
    """The normalisation and the scene box [2, 3] (normalised units) from the prior and the cameras.

    Without a prior the box is the cameras' bounding box grown by its largest side in every direction (and at
    least one scene unit), since nothing else tells where the walls are.
    """
    centres = np.stack([f.c2w[:3, 3] for f in scene.frames])
    if prior is not None:
        pts = prior.points
        if len(pts) > 200_000:
            pts = pts[np.random.default_rng(0).choice(len(pts), 200_000, replace=False)]
        pts = np.concatenate([pts, centres])
    else:
        lo, hi = centres.min(0), centres.max(0)
        pad = max(float((hi - lo).max()), 1.0)
        pts = np.stack([lo - pad, hi + pad])
    transform = SceneTransform.fit(pts)
    norm = transform.points_to_normalized(pts)
    aabb = np.stack([norm.min(0), norm.max(0)])
    pad = 0.02 * float((aabb[1] - aabb[0]).max())
    aabb = np.clip(aabb + np.array([[-pad], [pad]]), -1.0, 1.0)
    return transform, aabb


@dataclass
class ModelStage:
    """The model in the scene box, its optimiser, and where a resumed run continues (iteration, history)."""

    transform: SceneTransform
    prior_n: GeometryPrior | None  # the prior in normalised units
    model: VoxNeRFModel
    optimizer: torch.optim.Optimizer
    iteration: int = 0
    history: list[EvalRecord] = field(default_factory=list)
    resumed: bool = False


def model_stage(cfg: TrainConfig, scene: Scene, prior: GeometryPrior | None, device: torch.device,
                previous: dict | None) -> ModelStage:
    transform, aabb = scene_box(scene, prior)
    prior_n = prior.transformed(np.asarray(transform.center), transform.scale) if prior is not None else None
    model = VoxNeRFModel.create(cfg, transform, torch.from_numpy(aabb).float(), None, device)
    if prior_n is not None and cfg.sampler != "uniform":
        model.grid.seed_from_points(torch.from_numpy(prior_n.points).float().to(device))
    # fused: one pass over each parameter per step instead of one per Adam operation (benchmarks/optimizer_step.py;
    # see docs/performance.md).
    optimizer = torch.optim.Adam(model.field.parameters(), lr=cfg.lr, eps=1e-15, fused=True)
    stage = ModelStage(transform, prior_n, model, optimizer)
    if previous is not None:
        model.field.load_state_dict(previous["model"]["field"])
        model.grid.load_state_dict(previous["model"]["grid"])
        optimizer.load_state_dict(previous["optimizer"])
        stage.iteration, stage.resumed = int(previous["iteration"]), True
        stage.history = [EvalRecord.model_validate(h) for h in previous["history"]]
    return stage


@dataclass
class OctreeStage:
    record: StageRecord
    octree: SparseVoxelOctree | None


def octree_stage(cfg: TrainConfig, prior_n: GeometryPrior | None, pixels: TrainingPixels, model: VoxNeRFModel,
                 device: torch.device) -> OctreeStage:
    t0 = time.perf_counter()
    if cfg.sampler == "voxnerf" and prior_n is not None:
        octree, why = sampler_octree(prior_n, pixels, model, cfg, device)
        return OctreeStage(_record("octree", True, why, t0), octree)
    why = "no prior" if prior_n is None else f"sampler {cfg.sampler!r} does not use it"
    return OctreeStage(_record("octree", False, why, t0), None)


def sampler_octree(
    prior: GeometryPrior, pixels: TrainingPixels, model: VoxNeRFModel, cfg: TrainConfig, device: torch.device
) -> tuple[SparseVoxelOctree, str]:
    """The voxnerf sampler's octree over ``prior`` (normalised frame) and a sentence saying how its leaf was
    chosen (``cfg.octree_leaf``: the paper's sigma, or for point clouds the coverage rule on 65,536 training
    rays; mesh priors are sampled at sigma / 3, dense enough for sigma leaves)."""
    points = torch.from_numpy(prior.points).float().to(device)
    if cfg.octree_leaf == "sigma" or prior.kind == "mesh":
        octree = SparseVoxelOctree.from_points(points, prior.sigma)
        why = "octree_leaf: sigma" if cfg.octree_leaf == "sigma" else "mesh prior, sampled densely"
        return octree, (f"voxnerf sampler: {octree.levels} levels, leaf = sigma = {octree.leaf_size:.4g} "
                        f"(normalised; {why})")
    n, h, w = pixels.shape
    gen = torch.Generator(device=device).manual_seed(0)
    flat = torch.randint(0, n * h * w, (min(COVERAGE_RAYS, n * h * w),), generator=gen, device=device)
    rays = model.ray_bundle(*pixels.rays(flat // (h * w), flat % (h * w) // w, flat % w))
    octree, misses = coverage_octree(points, prior.sigma, rays.origins, rays.dirs, rays.near, rays.far)
    tried = ", ".join(f"{s} sigma: {m:.1%}" for s, m in misses.items())
    scale = octree.leaf_size_requested / prior.sigma
    return octree, (f"voxnerf sampler: {octree.levels} levels, leaf {scale:g} sigma = {octree.leaf_size:.4g} "
                    f"(normalised), the smallest that training rays do not slip through (rays missing every "
                    f"leaf: {tried})")


@dataclass
class PseudoDepthStage:
    record: StageRecord
    pseudo_t: torch.Tensor | None  # [N, H, W] normalised ray distances, NaN where the prior is not seen
    warning: str | None = None  # few training pixels see the prior


def pseudo_depth_stage(cfg: TrainConfig, scene: Scene, prior_n: GeometryPrior | None,
                       octree: SparseVoxelOctree | None, pixels: TrainingPixels, model: VoxNeRFModel,
                       device: torch.device) -> PseudoDepthStage:
    t0 = time.perf_counter()
    if not (cfg.depth_loss and prior_n is not None):
        why = "depth loss disabled" if not cfg.depth_loss else "no prior to render depth from"
        return PseudoDepthStage(_record("pseudo_depth", False, why, t0), None)
    # Leaves of the prior's sigma (the paper's) give the most accurate point-cloud depths, whatever leaf
    # the sampler's octree settled on.
    depth_svo = octree if octree is not None and octree.leaf_size == prior_n.sigma else (
        SparseVoxelOctree.from_points(torch.from_numpy(prior_n.points).float().to(device), prior_n.sigma))
    renderer = PriorDepthRenderer(prior_n, depth_svo)
    pseudo_t, _ = per_pixel(
        pixels, model, lambda rays, _: renderer.ray_distance(rays.origins, rays.dirs, rays.near, rays.far)
    )
    valid = float(torch.isfinite(pseudo_t).float().mean())
    warning = None
    if valid < MIN_PRIOR_COVERAGE:
        warning = (f"{scene.prior_path.name}: only {valid:.1%} of training pixels see the prior; check its units, "
                   "placement and prior_sigma")
    why = f"depth loss: prior ray-cast for every training pixel ({valid:.1%} valid)"
    return PseudoDepthStage(_record("pseudo_depth", True, why, t0), pseudo_t, warning)


@dataclass
class FirstHitStage:
    record: StageRecord
    hit_t: torch.Tensor | None = None  # [N, H, W] octree first-hit distance, NaN on a miss
    hit: torch.Tensor | None = None  # [N, H, W] bool


def first_hit_stage(octree: SparseVoxelOctree | None, pixels: TrainingPixels, model: VoxNeRFModel) -> FirstHitStage:
    t0 = time.perf_counter()
    if octree is None:
        return FirstHitStage(_record("first_hit_cache", False, "no octree", t0))
    # The pseudo depth, where there is one, tells the search where to stop first (same result, less work).
    hint = pixels.pseudo_t.view(-1) if pixels.pseudo_t is not None else None
    hit_t, hit = per_pixel(
        pixels, model, lambda rays, index: octree.first_hit(
            rays.origins, rays.dirs, rays.near, rays.far, t_hint=None if hint is None else hint[index]
        )
    )
    why = f"octree first hit of every training pixel ({float(hit.float().mean()):.1%} hit)"
    return FirstHitStage(_record("first_hit_cache", True, why, t0), hit_t, hit)


@dataclass
class CompileStage:
    """The step's loss function, compiled or not. A compiled one's record comes after the first step (its
    compile time is that step's): ``record`` is None until then, timed from ``started``."""

    loss_fn: LossFn
    started: float
    record: StageRecord | None = None


COMPILE_RAN_WHY = "torch.compile of the training step (time of the first step)"
COMPILE_NO_STEP_WHY = "no training step ran"


def compile_stage(cfg: TrainConfig, loss_fn: LossFn) -> CompileStage:
    t0 = time.perf_counter()
    if cfg.compile:
        return CompileStage(torch.compile(loss_fn, dynamic=False), t0)
    return CompileStage(loss_fn, t0, _record("compile", False, "disabled (--no-compile)", t0))
