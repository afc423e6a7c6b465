"""Stage prior: the scene's prior file, or one fused from the training frames' depth maps, or none."""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from voxnerf.cameras import lens
from voxnerf.cameras.rules import Intrinsics
from voxnerf.config import TrainConfig
from voxnerf.data.image_io import write_atomic
from voxnerf.data.scene import Scene, read_depth_map
from voxnerf.files import FUSED_PRIOR
from voxnerf.prior.depth_fusion import DepthView, FusedPrior, FusionError, fuse_depth_prior
from voxnerf.prior.loading import GeometryPrior, load_prior, prior_from_mesh
from voxnerf.training.records import StageRecord
from voxnerf.training.stages.common import stage_record


@dataclass
class PriorStage:
    record: StageRecord
    prior: GeometryPrior | None
    warning: str | None = None  # the sampler or the depth loss needs a prior the scene lacks
    fused: FusedPrior | None = None  # the prior was fused from the training frames' depth maps


def prior_stage(scene: Scene, cfg: TrainConfig, run_dir: Path | None = None) -> PriorStage:
    """The scene's prior file (unless ``prior_file`` is off); without one, the TSDF fusion of the training frames'
    depth maps (written to ``run_dir/prior_tsdf.ply`` when a run directory is given); without either, none."""
    t0 = time.perf_counter()
    needs_prior = cfg.sampling.may_use_window or cfg.loss.depth_loss
    why_needed = "sets the scene box" + (" and guides sampling / depth" if needs_prior else " only (not needed else)")
    if scene.prior_path is not None and not cfg.sampling.prior_file:
        why_needed += f"; the scene's {scene.prior_path.name} left out (prior_file: false)"
    elif scene.prior_path is not None:
        prior = load_prior(scene.prior_path, scene.prior_sigma, seed=cfg.run.seed)
        why = why_needed
        if scene.prior_key == "ply_file_path":
            why += f"; from nerfstudio's ply_file_path ({scene.prior_path.name}), no prior_file_path given"
        return PriorStage(stage_record("prior", True, f"{prior.kind} prior, sigma {prior.sigma:.4g} "
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
        return PriorStage(stage_record("prior", True, why, t0), prior, fused=fused)
    why = "the scene has no prior" + (" and no training frame has a depth map" if needs_prior else "")
    return _no_prior(cfg, why, t0, needs_prior)


def _no_prior(cfg: TrainConfig, why: str, t0: float, needs_prior: bool) -> PriorStage:
    record = stage_record("prior", False, why, t0)
    if cfg.sampling.sampler == "auto":  # without a prior, auto's choice is the grid: only the depth loss misses it
        if not cfg.loss.depth_loss:
            return PriorStage(record, None)
        return PriorStage(record, None, "the depth loss needs a prior; the scene has none, so no depth loss is used "
                                        "(sampler 'auto' takes the occupancy grid)")
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
