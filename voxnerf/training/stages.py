"""The set-up stages of a run, in the order ``train()`` runs them.

Each stage is a function that times itself and returns a :class:`StageRecord` (whether it ran, why, seconds)
with what it produced. The model stage (scene box, model, optimiser, resume) has no record of its own.
"""

from __future__ import annotations

import os
import random
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from voxnerf import native
from voxnerf.cameras import lens
from voxnerf.cameras.pose_refinement import PoseRefinement
from voxnerf.cameras.rules import Intrinsics
from voxnerf.config import TrainConfig
from voxnerf.data.image_io import write_atomic
from voxnerf.data.scene import Scene, SceneTransform, load_scene, read_depth_map
from voxnerf.errors import SceneError
from voxnerf.files import FUSED_PRIOR, TRANSFORMS
from voxnerf.model import hash_kernel
from voxnerf.model.appearance import ImageAppearance
from voxnerf.model.losses import PAPER_BETA
from voxnerf.model.voxnerf_model import VoxNeRFModel
from voxnerf.prior.carving import empty_leaves, remove_empty
from voxnerf.prior.depth_fusion import DepthNoise, DepthView, FusedPrior, FusionError, fit_noise, fuse_depth_prior
from voxnerf.prior.loading import GeometryPrior, load_prior, prior_from_mesh
from voxnerf.prior.octree import SparseVoxelOctree, coverage_octree
from voxnerf.prior.pseudo_depth import PriorDepthRenderer
from voxnerf.training import setup_cache
from voxnerf.training.pixels import TrainingPixels, per_pixel, rays_in_chunks, sensor_ray_distance
from voxnerf.training.prior_rays import PriorRayBank, bank_size, prior_ray_bank, seen_by
from voxnerf.training.records import EvalRecord, StageRecord
from voxnerf.training.step import DEPTH_BETA_PER_SIGMA, LossFn

MIN_PRIOR_COVERAGE = 0.05  # below this fraction of training pixels seeing the prior, the report warns
COVERAGE_RAYS = 65_536  # training rays that choose the sampler octree's leaf (voxnerf.prior.octree.coverage_octree)


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
    scene = load_scene(scene_dir, downscale=cfg.run.downscale)
    check_sensor_depth(cfg, scene)  # before any set-up work, not after it
    why = f"{len(scene.frames)} frames, {len(scene.train_indices)} for training"
    return SceneStage(_record("load_scene", True, why, t0), scene)


@dataclass
class PriorStage:
    record: StageRecord
    prior: GeometryPrior | None
    warning: str | None = None  # the sampler or the depth loss needs a prior the scene lacks
    fused: FusedPrior | None = None  # the prior was fused from the training frames' depth maps


def prior_stage(scene: Scene, cfg: TrainConfig, run_dir: Path | None = None) -> PriorStage:
    """The scene's prior file; without one, the TSDF fusion of the training frames' depth maps (written to
    ``run_dir/prior_tsdf.ply`` when a run directory is given); without either, none."""
    t0 = time.perf_counter()
    needs_prior = cfg.sampling.sampler == "voxnerf" or cfg.loss.depth_loss
    why_needed = "sets the scene box" + (" and guides sampling / depth" if needs_prior else " only (not needed else)")
    if scene.prior_path is not None:
        prior = load_prior(scene.prior_path, scene.prior_sigma, seed=cfg.run.seed)
        why = why_needed
        if scene.prior_key == "ply_file_path":
            why += f"; from nerfstudio's ply_file_path ({scene.prior_path.name}), no prior_file_path given"
        return PriorStage(_record("prior", True, f"{prior.kind} prior, sigma {prior.sigma:.4g} "
                                  f"({'estimated' if prior.sigma_estimated else 'given'}); {why}", t0), prior)
    depth_frames = [i for i in scene.train_indices if scene.frames[i].depth_path is not None]
    if needs_prior and depth_frames:
        try:
            fused = fuse_depth_prior(training_depth_views(scene, depth_frames))
        except FusionError as err:
            return _no_prior(cfg, f"no prior file, and the depth maps make none: {err}", t0, needs_prior)
        prior = prior_from_mesh(fused.mesh, fused.sigma, FUSED_PRIOR, seed=cfg.run.seed)
        if run_dir is not None:
            write_atomic(Path(run_dir) / FUSED_PRIOR, fused.mesh.export(file_type="ply"))
        why = f"no prior file; {fused.describe()} ({fused.noise.describe()}); {why_needed}"
        return PriorStage(_record("prior", True, why, t0), prior, fused=fused)
    why = "the scene has no prior" + (" and no training frame has a depth map" if needs_prior else "")
    return _no_prior(cfg, why, t0, needs_prior)


def _no_prior(cfg: TrainConfig, why: str, t0: float, needs_prior: bool) -> PriorStage:
    record = _record("prior", False, why, t0)
    if not needs_prior:
        return PriorStage(record, None)
    return PriorStage(record, None, (
        f"sampler {cfg.sampling.sampler!r}{' and the depth loss' if cfg.loss.depth_loss else ''} need a prior; "
        "the scene has none, so sampling falls back to the occupancy grid and no depth loss is used"))


def training_depth_views(scene: Scene, indices: list[int]) -> list[DepthView]:
    """The depth maps of the given training frames at their own resolution, with their cameras and poses."""
    train = set(scene.train_indices)
    views = []
    for i in indices:
        if i not in train:  # held-out depth never makes the prior
            raise ValueError(f"frame {i} is not a training frame")
        depth, camera = read_depth_map(scene.frames[i], scene.depth_unit_scale, scene.depth_max)
        if camera.lens is not None:
            depth, camera = pinhole_depth(depth, camera)
        views.append(DepthView(depth, camera, scene.frames[i].c2w))
    return views


def pinhole_depth(depth: np.ndarray, camera: Intrinsics) -> tuple[np.ndarray, Intrinsics]:
    """A distorted camera's depth map [H, W] resampled (nearest) onto the pinhole camera with the same
    ``fl cx cy`` and size, for fusion (a z-depth does not change under the lens: only where it is seen)."""
    v, u = torch.meshgrid(torch.arange(camera.height, dtype=torch.float64),
                          torch.arange(camera.width, dtype=torch.float64), indexing="ij")
    xy = torch.stack([(u + 0.5 - camera.cx) / camera.fl_x, (v + 0.5 - camera.cy) / camera.fl_y], dim=-1)
    coeffs = torch.tensor(camera.lens.coefficients, dtype=torch.float64)
    uv = lens.distort(xy, coeffs, camera.lens.model)
    cols = torch.floor(uv[..., 0] * camera.fl_x + camera.cx).long()
    rows = torch.floor(uv[..., 1] * camera.fl_y + camera.cy).long()
    inside = (cols >= 0) & (cols < camera.width) & (rows >= 0) & (rows < camera.height)
    picked = torch.from_numpy(depth)[rows.clamp(0, camera.height - 1), cols.clamp(0, camera.width - 1)]
    out = torch.where(inside, picked, torch.full_like(picked, float("nan")))
    return out.numpy().astype(np.float32), replace(camera, lens=None)


def hash_kernel_stage(cfg: TrainConfig, device: torch.device) -> StageRecord:
    t0 = time.perf_counter()
    if device.type != "cpu":
        return _record("hash_kernel", False, f"on {device.type} the hash encoding stays in PyTorch", t0)
    if not cfg.run.hash_kernel:
        return _record("hash_kernel", False, "disabled (--no-hash-kernel): the hash encoding stays in PyTorch", t0)
    if hash_kernel.available():
        return _record("hash_kernel", True,
                       "the hash encoding runs in its C kernel (voxnerf/model/hashgrid.c; built once, cached)", t0)
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


def training_mean_colour(scene: Scene) -> tuple[float, float, float]:
    """The mean sRGB colour (in [0, 1]) of the scene's training images."""
    total = np.zeros(3)
    for i in scene.train_indices:
        total += scene.images[i].reshape(-1, 3).mean(0)
    mean = total / max(len(scene.train_indices), 1) / 255.0
    return (float(mean[0]), float(mean[1]), float(mean[2]))


APPEARANCE_LR_SCALE = 0.1  # the per-image corrections learn at a tenth of the field's rate


def _corrections(cfg: TrainConfig, scene: Scene, model: VoxNeRFModel, device: torch.device) -> list[dict]:
    """Give ``model`` the per-image corrections ``cfg`` asks for; their optimiser parameter groups."""
    if "auto" in (cfg.corrections.appearance, cfg.corrections.pose_refinement):
        raise ValueError("model_stage: resolve 'auto' appearance and pose_refinement first (corrections_stage)")
    if cfg.corrections.appearance == "none" and cfg.corrections.pose_refinement == "none":
        return []
    cameras = torch.from_numpy(np.stack([model.transform.c2w_to_normalized(scene.frames[i].c2w)
                                         for i in scene.train_indices]))  # both blend from the training cameras
    groups = []
    if cfg.corrections.appearance == "affine":
        model.appearance = ImageAppearance(len(cameras), cameras).to(device)
        groups.append({"params": list(model.appearance.parameters()), "lr": cfg.schedule.lr * APPEARANCE_LR_SCALE})
    if cfg.corrections.pose_refinement == "so3xr3":
        model.pose_refinement = PoseRefinement(len(cameras), cameras).to(device)
        groups.append({"params": list(model.pose_refinement.parameters()), "lr": cfg.corrections.pose_lr})
    return groups


def model_stage(cfg: TrainConfig, scene: Scene, prior: GeometryPrior | None, device: torch.device,
                previous: dict | None) -> ModelStage:
    if cfg.schedule.field_weight_decay == "auto":
        raise ValueError("model_stage: resolve 'auto' field_weight_decay first (weight_decay_stage)")
    transform, aabb = scene_box(scene, prior)
    prior_n = prior.transformed(np.asarray(transform.center), transform.scale) if prior is not None else None
    if cfg.model.background == "training_mean":
        cfg = cfg.updated(background=training_mean_colour(scene))
    model = VoxNeRFModel.create(cfg, transform, torch.from_numpy(aabb).float(), None, device)
    if prior_n is not None and cfg.sampling.sampler != "uniform" and cfg.sampling.occgrid_seed:
        model.grid.seed_from_points(torch.from_numpy(prior_n.points).float().to(device))
    # fused: one pass over each parameter per step instead of one per Adam operation (benchmarks/optimizer_step.py;
    # docs/performance.md, 'Optimiser step').
    groups = [{"params": list(model.field.parameters()), "lr": cfg.schedule.lr,
               "weight_decay": cfg.schedule.field_weight_decay},
              *_corrections(cfg, scene, model, device)]
    optimizer = torch.optim.Adam(groups, lr=cfg.schedule.lr, eps=1e-15, fused=True)
    stage = ModelStage(transform, prior_n, model, optimizer)
    if previous is not None:
        model.field.load_state_dict(previous["model"]["field"])
        model.grid.load_state_dict(previous["model"]["grid"])
        if model.appearance is not None and previous["model"].get("appearance") is not None:
            model.appearance.load_state_dict(previous["model"]["appearance"])
        if model.pose_refinement is not None and previous["model"].get("pose_refinement") is not None:
            model.pose_refinement.load_state_dict(previous["model"]["pose_refinement"])
        optimizer.load_state_dict(previous["optimizer"])
        # the command's weight decay, not the checkpoint's
        optimizer.param_groups[0]["weight_decay"] = cfg.schedule.field_weight_decay
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
    if cfg.sampling.sampler == "voxnerf" and prior_n is not None:
        octree, why = sampler_octree(prior_n, pixels, model, cfg, device)
        return OctreeStage(_record("octree", True, why, t0), octree)
    why = "no prior" if prior_n is None else f"sampler {cfg.sampling.sampler!r} does not use it"
    return OctreeStage(_record("octree", False, why, t0), None)


def sampler_octree(
    prior: GeometryPrior, pixels: TrainingPixels, model: VoxNeRFModel, cfg: TrainConfig, device: torch.device
) -> tuple[SparseVoxelOctree, str]:
    """The voxnerf sampler's octree over ``prior`` (normalised frame) and a sentence saying how its leaf was
    chosen (``cfg.sampling.octree_leaf``: the paper's sigma, or for point clouds the coverage rule on 65,536 training
    rays; mesh priors are sampled at sigma / 3, dense enough for sigma leaves)."""
    points = torch.from_numpy(prior.points).float().to(device)
    if cfg.sampling.octree_leaf == "sigma" or prior.kind == "mesh":
        octree = SparseVoxelOctree.from_points(points, prior.sigma)
        why = "octree_leaf: sigma" if cfg.sampling.octree_leaf == "sigma" else "mesh prior, sampled densely"
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
    if not (cfg.loss.depth_loss and cfg.loss.depth_source != "none" and prior_n is not None):
        why = ("depth loss disabled" if not cfg.loss.depth_loss
               else "depth_source 'none'" if cfg.loss.depth_source == "none"
               else "no prior to render depth from")
        return PseudoDepthStage(_record("pseudo_depth", False, why, t0), None)
    depth_svo = prior_depth_octree(prior_n, octree, device)
    inputs = [*pixel_rays_key(pixels, model), *prior_key(prior_n), octree_key(depth_svo)]

    def cast() -> tuple[torch.Tensor, torch.Tensor]:
        renderer = PriorDepthRenderer(prior_n, depth_svo)
        return per_pixel(pixels, model, lambda rays, _: renderer.ray_distance(rays.origins, rays.dirs, rays.near,
                                                                              rays.far))

    (pseudo_t, _), loaded = setup_cache.cached_per_pixel("pseudo_depth", inputs, pixels.shape, device, cast,
                                                         cfg.run.setup_cache)
    valid = float(torch.isfinite(pseudo_t).float().mean())
    warning = None
    if valid < MIN_PRIOR_COVERAGE:
        warning = (f"{scene.prior_path.name}: only {valid:.1%} of training pixels see the prior; check its units, "
                   "placement and prior_sigma")
    why = f"depth loss: prior ray-cast for every training pixel ({valid:.1%} valid){FROM_CACHE if loaded else ''}"
    return PseudoDepthStage(_record("pseudo_depth", True, why, t0), pseudo_t, warning)


FROM_CACHE = "; loaded from the set-up cache"


def pixel_rays_key(pixels: TrainingPixels, model: VoxNeRFModel) -> list:
    """What fixes the rays of every training pixel and their near / far bounds (:func:`per_pixel`), for
    :mod:`setup_cache` keys."""
    return [*training_rays_key(pixels), model.aabb]


def training_rays_key(pixels: TrainingPixels) -> list:
    """What fixes the rays of every training pixel (:meth:`TrainingPixels.rays`), for :mod:`setup_cache` keys."""
    lens = None if pixels.lens is None else (pixels.lens.coeffs, pixels.lens.codes)
    table = None if pixels.directions is None else (pixels.directions.dirs, pixels.directions.camera)
    return [pixels.shape, pixels.c2w, pixels.intr, lens, table]


def prior_key(prior_n: GeometryPrior) -> list:
    mesh = None if prior_n.mesh is None else (np.asarray(prior_n.mesh.vertices), np.asarray(prior_n.mesh.faces))
    return [prior_n.kind, prior_n.points, mesh, float(prior_n.sigma)]


def octree_key(octree: SparseVoxelOctree | None) -> dict | None:
    return None if octree is None else octree.state_dict()


def prior_depth_octree(prior_n: GeometryPrior, octree: SparseVoxelOctree | None,
                       device: torch.device) -> SparseVoxelOctree:
    """The octree the prior's depth is cast through: leaves of the prior's sigma (the paper's) give the most
    accurate point-cloud depths, whatever leaf the sampler's octree settled on."""
    if octree is not None and octree.leaf_size == prior_n.sigma:
        return octree
    return SparseVoxelOctree.from_points(torch.from_numpy(prior_n.points).float().to(device), prior_n.sigma)


def prior_depth_renderer(prior_n: GeometryPrior, octree: SparseVoxelOctree | None,
                         device: torch.device) -> PriorDepthRenderer:
    """The prior's depth along rays (normalised frame), through :func:`prior_depth_octree`."""
    return PriorDepthRenderer(prior_n, prior_depth_octree(prior_n, octree, device))


UNSEEN_TOLERANCE_LEAVES = 3  # a view sees a prior ray's surface point where its depth target is this close


@dataclass
class PriorRaysStage:
    record: StageRecord
    bank: PriorRayBank | None = None


def prior_rays_stage(cfg: TrainConfig, prior_n: GeometryPrior | None, use_depth: bool,
                     octree: SparseVoxelOctree | None, pixels: TrainingPixels, model: VoxNeRFModel,
                     device: torch.device) -> PriorRaysStage:
    """The bank of prior rays (:mod:`voxnerf.training.prior_rays`) when ``cfg.loss.prior_rays`` asks for them and the
    run has a prior and a depth loss."""
    t0 = time.perf_counter()
    if not (cfg.loss.prior_rays and prior_n is not None and use_depth):
        why = ("prior_rays 0" if not cfg.loss.prior_rays else "no prior" if prior_n is None else "no depth loss")
        return PriorRaysStage(_record("prior_rays", False, why, t0))
    wanted = bank_size(cfg.loss.prior_rays)
    bank = prior_ray_bank(pixels.c2w[:, :3, 3], model, prior_depth_renderer(prior_n, octree, device), octree, wanted,
                          cfg.run.seed)
    if not len(bank):
        return PriorRaysStage(_record("prior_rays", False, "no ray from the training cameras hits the prior", t0))
    why = (f"{cfg.loss.prior_rays} rays per step from the training cameras' centres, supervised by the prior's depth: "
           f"{len(bank)} of {wanted} random rays hit the prior")
    if cfg.loss.prior_ray_colour > 0:
        depth = pixels.depth_t if pixels.depth_t is not None else pixels.pseudo_t
        points = bank.rays.origins + bank.target_t[:, None] * bank.rays.dirs
        tolerance = UNSEEN_TOLERANCE_LEAVES * (octree.leaf_size if octree is not None else prior_n.sigma)
        bank.unseen = ~seen_by(points, pixels.c2w, pixels.intr, depth, tolerance)
        why += f"; {float(bank.unseen.float().mean()):.1%} meet surfaces no training view sees (mean-colour term)"
    return PriorRaysStage(_record("prior_rays", True, why, t0), bank)


def check_sensor_depth(cfg: TrainConfig, scene: Scene) -> None:
    """SceneError when ``depth_source`` 'sensor' is asked for and no training frame has a depth map."""
    wants_sensor = cfg.loss.depth_loss and cfg.loss.depth_source == "sensor"
    if wants_sensor and all(scene.depths[i] is None for i in scene.train_indices):
        raise SceneError(scene.root / TRANSFORMS, "depth_source 'sensor' needs depth maps, and no training frame "
                         "has one", key="depth_file_path")


def depth_source(cfg: TrainConfig, scene: Scene, prior: GeometryPrior | None) -> tuple[str, str]:
    """What the depth loss compares with ('sensor', 'prior' or 'none') and why (``TrainConfig.depth_source``).

    Raises SceneError when 'sensor' is asked for and no training frame has a depth map.
    """
    check_sensor_depth(cfg, scene)
    has_sensor = any(scene.depths[i] is not None for i in scene.train_indices)
    if not cfg.loss.depth_loss or cfg.loss.depth_source == "none":
        return "none", "depth loss disabled" if not cfg.loss.depth_loss else "depth_source 'none'"
    if cfg.loss.depth_source == "auto":
        if has_sensor:
            return "sensor", "auto: the training frames have depth maps"
        return ("prior", "auto: no depth maps, the prior's depth") if prior is not None else (
            "none", "auto: no depth maps and no prior")
    if cfg.loss.depth_source == "prior" and prior is None:
        return "none", "depth_source 'prior' but there is no prior"
    return cfg.loss.depth_source, f"depth_source {cfg.loss.depth_source!r}"


@dataclass
class DepthTargetStage:
    """The depth loss's target per training pixel and its log-Huber beta.

    ``target_t`` [N, H, W] normalised ray distances (NaN where none); ``beta_scale`` [N, H, W] each pixel's beta
    over ``beta`` (None: ``beta`` everywhere); ``beta`` in scene units; ``summary`` for the report; ``sensor_t``
    [N, H, W] the sensor's ray distances alone (NaN where it measured nothing; None without sensor depth).
    """

    record: StageRecord
    target_t: torch.Tensor | None = None
    beta_scale: torch.Tensor | None = None
    beta: float | None = None
    summary: dict | None = None
    sensor_t: torch.Tensor | None = None


BETA_SCALE_RANGE = (0.1, 10.0)  # a pixel's beta stays within these factors of the run's


def depth_target_stage(cfg: TrainConfig, scene: Scene, prior: GeometryPrior | None, fused: FusedPrior | None,
                       pixels: TrainingPixels, transform: SceneTransform) -> DepthTargetStage:
    """Sensor depth where it is valid and the prior's depth elsewhere ('sensor'), the prior's ('prior'), or none.

    For sensor depth, beta follows the depth noise: ``DEPTH_BETA_PER_SIGMA x sigma(z)``, sigma measured against
    the fused prior (fused) or the prior's depth along the same rays (a prior file), unless ``depth_beta`` is
    set.
    """
    t0 = time.perf_counter()
    source, why = depth_source(cfg, scene, prior)
    if source == "none":
        return DepthTargetStage(_record("depth_target", False, why, t0))
    base_sigma = prior.sigma if prior is not None else None
    if source == "prior":
        beta = cfg.loss.depth_beta or DEPTH_BETA_PER_SIGMA * base_sigma
        valid = float(torch.isfinite(pixels.pseudo_t).float().mean())
        summary = {"source": "prior", "why": why, "prior_fraction": valid, "beta": beta}
        return DepthTargetStage(_record("depth_target", True, f"{why}: the prior's depth on {valid:.1%} of "
                                        "training pixels", t0), pixels.pseudo_t, None, beta, summary)
    z = torch.from_numpy(np.stack([_depth_or_nan(scene, i, pixels.shape[1:]) for i in scene.train_indices]))
    z = z.to(pixels.images.device)
    sensor_t = sensor_ray_distance(pixels, z, transform.scale)
    noise = fused.noise if fused is not None else measure_noise_against(sensor_t, pixels.pseudo_t, z, transform,
                                                                         base_sigma)
    sensor_ok = torch.isfinite(sensor_t)
    target = sensor_t if pixels.pseudo_t is None else torch.where(sensor_ok, sensor_t, pixels.pseudo_t)
    summary = {"source": "sensor", "why": why, "sensor_fraction": float(sensor_ok.float().mean()),
               "prior_fraction": float((~sensor_ok & torch.isfinite(target)).float().mean())}
    text = (f"{why}: sensor depth on {summary['sensor_fraction']:.1%} of training pixels, the prior's on "
            f"{summary['prior_fraction']:.1%}; ")
    if cfg.loss.depth_beta or noise is None:
        beta = cfg.loss.depth_beta or (DEPTH_BETA_PER_SIGMA * base_sigma if base_sigma else PAPER_BETA)
        rule = "given (depth_beta)" if cfg.loss.depth_beta else "no surface to measure the depth noise against"
        summary |= {"beta": beta, "beta_rule": rule}
        return DepthTargetStage(_record("depth_target", True, text + f"beta {beta:.4g}: {rule}", t0), target,
                                None, beta, summary, sensor_t)
    base_sigma = base_sigma or noise.at_median
    beta = DEPTH_BETA_PER_SIGMA * base_sigma
    beta_scale = torch.where(sensor_ok, (noise.s0 + noise.s2 * z * z) / base_sigma, torch.ones_like(z))
    summary |= {"noise": noise.as_dict(), "beta": beta, "beta_rule": f"{DEPTH_BETA_PER_SIGMA:g} x sigma(z)"}
    text += f"beta {DEPTH_BETA_PER_SIGMA:g} x sigma(z), {noise.describe()}"
    return DepthTargetStage(_record("depth_target", True, text, t0), target,
                            beta_scale.clamp(*BETA_SCALE_RANGE), beta, summary, sensor_t)


@dataclass
class CarvingStage:
    record: StageRecord
    octree: SparseVoxelOctree | None  # the carved octree; None where the stage did not run


def carving_stage(cfg: TrainConfig, octree: SparseVoxelOctree | None, pixels: TrainingPixels,
                  target: DepthTargetStage, scale: float) -> CarvingStage:
    """The sampler octree less the leaves that the training frames' sensor depth shows empty
    (:mod:`voxnerf.prior.carving`): each measured ray crosses empty space up to ``CARVE_MARGIN_LEAVES`` leaves
    plus ``CARVE_MARGIN_SIGMAS`` times its depth noise (``beta / DEPTH_BETA_PER_SIGMA``, per pixel where the
    noise was measured) before its depth. ``scale``: the scene's normalisation (scene units -> normalised)."""
    t0 = time.perf_counter()
    measured = None if target.sensor_t is None else torch.isfinite(target.sensor_t).view(-1).nonzero().squeeze(1)
    if octree is None or measured is None or not len(measured) or not cfg.sampling.octree_carving:
        why = ("octree_carving false" if not cfg.sampling.octree_carving else "no octree" if octree is None
               else "no sensor depth in use (the depth target is not the sensor's)" if measured is None
               else "no training pixel has sensor depth")
        return CarvingStage(_record("octree_carving", False, why, t0), None)
    inputs = [*training_rays_key(pixels), octree_key(octree), target.sensor_t, target.beta, target.beta_scale,
              float(scale)]

    def carve() -> setup_cache.Entry:
        empty, surface_leaves, rays = _empty_by_sensor_depth(octree, pixels, target, measured, scale)
        return {"empty": empty, "votes": torch.tensor([surface_leaves, rays])}

    def fits(entry: setup_cache.Entry) -> bool:
        empty, votes = entry.get("empty"), entry.get("votes")
        return (empty is not None and votes is not None and empty.dtype == torch.bool
                and tuple(empty.shape) == tuple(octree.codes[-1].shape) and tuple(votes.shape) == (2,))

    entry, loaded = setup_cache.cached("octree_carving", inputs, octree.device, carve, fits, cfg.run.setup_cache)
    carving = remove_empty(octree, entry["empty"], *(int(v) for v in entry["votes"]))
    why = (f"{carving.describe()}; free space ends {CARVE_MARGIN_LEAVES:g} leaves + {CARVE_MARGIN_SIGMAS:g} "
           f"sigma(z) before each measured depth{FROM_CACHE if loaded else ''}")
    return CarvingStage(_record("octree_carving", True, why, t0), carving.octree)


def _empty_by_sensor_depth(octree: SparseVoxelOctree, pixels: TrainingPixels, target: DepthTargetStage,
                           measured: torch.Tensor, scale: float) -> tuple[torch.Tensor, int, int]:
    """:func:`empty_leaves` with the measured training pixels ``measured`` (flat indices, int64 [M]): the
    surface points of up to ``CARVE_SURFACE_RAYS`` of them, the free-space votes of up to ``CARVE_FREE_RAYS``
    -> (empty leaves bool [L], leaves holding a surface point, rays that voted)."""
    gen = torch.Generator(device=measured.device).manual_seed(0)
    surface = _subset(measured, CARVE_SURFACE_RAYS, gen)
    free = _subset(measured, CARVE_FREE_RAYS, gen)
    sigma = torch.full((len(free),), target.beta * scale / DEPTH_BETA_PER_SIGMA, device=free.device)
    if target.beta_scale is not None:
        sigma = sigma * target.beta_scale.view(-1)[free]
    sensor_t = target.sensor_t.view(-1)
    points = torch.cat([o + sensor_t[f, None] * d for f, _, o, d in rays_in_chunks(pixels, surface)])
    free_rays = list(rays_in_chunks(pixels, free))
    origins, dirs = torch.cat([o for _, _, o, _ in free_rays]), torch.cat([d for *_, d in free_rays])
    margin = CARVE_MARGIN_LEAVES * octree.leaf_size + CARVE_MARGIN_SIGMAS * sigma
    empty, surface_leaves = empty_leaves(octree, points, origins, dirs, sensor_t[free] - margin)
    return empty, surface_leaves, len(free)


CARVE_MARGIN_LEAVES = 2.0
CARVE_MARGIN_SIGMAS = 3.0
CARVE_SURFACE_RAYS = 1 << 22  # measured pixels whose surface points protect their leaves
CARVE_FREE_RAYS = 1 << 18  # measured pixels whose rays vote on empty space


def _subset(indices: torch.Tensor, most: int, gen: torch.Generator) -> torch.Tensor:
    """``indices`` itself, or ``most`` of them drawn without replacement (sorted)."""
    if len(indices) <= most:
        return indices
    pick = torch.randperm(len(indices), generator=gen, device=indices.device)[:most]
    return indices[pick.sort().values]


def _depth_or_nan(scene: Scene, index: int, shape: tuple[int, int]) -> np.ndarray:
    depth = scene.depths[index]
    return np.full(shape, np.nan, np.float32) if depth is None else depth.astype(np.float32)


def measure_noise_against(sensor_t: torch.Tensor, prior_t: torch.Tensor | None, z: torch.Tensor,
                          transform: SceneTransform, prior_sigma: float | None) -> DepthNoise | None:
    """Depth noise of the sensor against the prior's depth along the same rays (scene units); None without a
    prior or when no pixel has both."""
    if prior_t is None or prior_sigma is None:
        return None
    both = torch.isfinite(sensor_t) & torch.isfinite(prior_t)
    cos = z[both] * transform.scale / sensor_t[both]  # z per unit of ray distance
    residual = ((sensor_t[both] - prior_t[both]) / transform.scale * cos).double().cpu().numpy()
    depth = z[both].double().cpu().numpy()
    keep = np.abs(residual) < DEPTH_BETA_PER_SIGMA * prior_sigma
    return fit_noise(depth[keep], residual[keep], prior_sigma) if keep.any() else None


@dataclass
class FirstHitStage:
    record: StageRecord
    hit_t: torch.Tensor | None = None  # [N, H, W] octree first-hit distance, NaN on a miss
    hit: torch.Tensor | None = None  # [N, H, W] bool


def first_hit_stage(octree: SparseVoxelOctree | None, pixels: TrainingPixels, model: VoxNeRFModel,
                    use_cache: bool = True) -> FirstHitStage:
    t0 = time.perf_counter()
    if octree is None:
        return FirstHitStage(_record("first_hit_cache", False, "no octree", t0))
    # The pseudo depth, where there is one, tells the search where to stop first (same result, less work).
    hint = pixels.pseudo_t.view(-1) if pixels.pseudo_t is not None else None

    def cast() -> tuple[torch.Tensor, torch.Tensor]:
        return per_pixel(pixels, model, lambda rays, index: octree.first_hit(
            rays.origins, rays.dirs, rays.near, rays.far, t_hint=None if hint is None else hint[index]))

    inputs = [*pixel_rays_key(pixels, model), octree_key(octree), hint]
    (hit_t, hit), loaded = setup_cache.cached_per_pixel("first_hit", inputs, pixels.shape, pixels.images.device,
                                                        cast, use_cache)
    why = (f"octree first hit of every training pixel ({float(hit.float().mean()):.1%} hit)"
           f"{FROM_CACHE if loaded else ''}")
    return FirstHitStage(_record("first_hit_cache", True, why, t0), hit_t, hit)


def inductor_cache_dir() -> Path:
    """``$VOXNERF_CACHE/inductor`` (beside the C kernels, :func:`voxnerf.native.cache_dir`): unlike inductor's
    default under the temporary directory, it outlives a reboot."""
    return native.cache_dir() / "inductor"


@dataclass
class CompileStage:
    """The step's loss function, compiled or not. A compiled one's record comes after the first step (its
    compile time is that step's): ``record`` is None until then, timed from ``started``."""

    loss_fn: LossFn
    started: float
    record: StageRecord | None = None


def compile_stage(cfg: TrainConfig, loss_fn: LossFn) -> CompileStage:
    """The step's loss function through ``torch.compile`` (unless disabled). Inductor's cache goes to
    :func:`inductor_cache_dir` unless ``TORCHINDUCTOR_CACHE_DIR`` says otherwise, so a later run of the same
    configuration loads the compiled step instead of compiling it again."""
    t0 = time.perf_counter()
    if cfg.run.compile:
        os.environ.setdefault("TORCHINDUCTOR_CACHE_DIR", str(inductor_cache_dir()))
        return CompileStage(torch.compile(loss_fn, dynamic=False), t0)
    return CompileStage(loss_fn, t0, _record("compile", False, "disabled (--no-compile)", t0))
