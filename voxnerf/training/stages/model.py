"""The model: the scene box, the model with its per-image corrections, its optimiser, a resumed state."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from voxnerf.cameras.pose_refinement import PoseRefinement
from voxnerf.config import TrainConfig
from voxnerf.data.scene import Scene, SceneTransform
from voxnerf.model.appearance import ImageAppearance
from voxnerf.model.voxnerf_model import VoxNeRFModel
from voxnerf.prior.loading import GeometryPrior
from voxnerf.training.records import EvalRecord


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
    """The model in the scene box, its optimiser, and where a resumed run continues (iteration, history, and the
    field's averaged parameters when it averaged them: ``schedule.weight_average``)."""

    transform: SceneTransform
    prior_n: GeometryPrior | None  # the prior in normalised units
    model: VoxNeRFModel
    optimizer: torch.optim.Optimizer
    iteration: int = 0
    history: list[EvalRecord] = field(default_factory=list)
    resumed: bool = False
    averaged_field: dict | None = None


def training_mean_colour(scene: Scene) -> tuple[float, float, float]:
    """The mean sRGB colour (in [0, 1]) of the scene's training images."""
    total = np.zeros(3)
    for i in scene.train_indices:
        total += scene.images[i].reshape(-1, 3).mean(0)
    mean = total / max(len(scene.train_indices), 1) / 255.0
    return (float(mean[0]), float(mean[1]), float(mean[2]))


def training_pixel_cone(scene: Scene) -> float:
    """A training pixel's cone radius per unit of distance (radians): mip-NeRF's ``2 / sqrt(12)`` of a pixel's
    width at unit distance, ``1 / (sqrt(3) f)`` for a focal length ``f`` in pixels (the geometric mean of fl_x and
    fl_y), the median over the training frames at the loaded resolution."""
    cones = [1.0 / (math.sqrt(3.0) * math.sqrt(k.fl_x * k.fl_y)) for k in map(scene.intrinsics, scene.train_indices)]
    return float(np.median(cones))


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
    if cfg.model.cone_radius == "auto":
        cfg = cfg.updated(cone_radius=training_pixel_cone(scene))
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
        if previous.get("field_live") is not None:  # the run averaged its weights: "model" holds the average
            stage.averaged_field = previous["model"]["field"]
            model.field.load_state_dict(previous["field_live"])
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
