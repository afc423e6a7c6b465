"""Stage pseudo_depth: the prior's depth per training pixel (paper III-D)."""

from __future__ import annotations

import time
from dataclasses import dataclass

import torch

from voxnerf.config import TrainConfig
from voxnerf.data.scene import Scene
from voxnerf.model.voxnerf_model import VoxNeRFModel
from voxnerf.prior.loading import GeometryPrior
from voxnerf.prior.octree import SparseVoxelOctree
from voxnerf.prior.pseudo_depth import PriorDepthRenderer
from voxnerf.training import setup_cache
from voxnerf.training.pixels import TrainingPixels, per_pixel
from voxnerf.training.records import StageRecord
from voxnerf.training.stages.common import (
    FROM_CACHE,
    octree_key,
    pixel_rays_key,
    prior_depth_octree,
    prior_key,
    stage_record,
)

MIN_PRIOR_COVERAGE = 0.05  # below this fraction of training pixels seeing the prior, the report warns


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
        return PseudoDepthStage(stage_record("pseudo_depth", False, why, t0), None)
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
        used_file = scene.prior_path is not None and cfg.sampling.prior_file
        name = scene.prior_path.name if used_file else "the prior fused from the depth maps"
        warning = (f"{name}: only {valid:.1%} of training pixels see the prior; check its units, placement and "
                   "prior_sigma")
    why = f"depth loss: prior ray-cast for every training pixel ({valid:.1%} valid){FROM_CACHE if loaded else ''}"
    return PseudoDepthStage(stage_record("pseudo_depth", True, why, t0), pseudo_t, warning)
