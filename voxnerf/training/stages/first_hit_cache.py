"""Stage first_hit_cache: the voxnerf sampler's window centre (the octree's first hit, at the rule of
``sampling.window_centre``) per training pixel."""

from __future__ import annotations

import time
from dataclasses import dataclass

import torch

from voxnerf.model.samplers import window_centres
from voxnerf.model.voxnerf_model import VoxNeRFModel
from voxnerf.prior.octree import SparseVoxelOctree
from voxnerf.training import setup_cache
from voxnerf.training.pixels import TrainingPixels, per_pixel
from voxnerf.training.records import StageRecord
from voxnerf.training.stages.common import FROM_CACHE, octree_key, pixel_rays_key, stage_record


@dataclass
class FirstHitStage:
    record: StageRecord
    hit_t: torch.Tensor | None = None  # [N, H, W] window centre distance (samplers.window_centres)
    hit: torch.Tensor | None = None  # [N, H, W] bool


def first_hit_stage(octree: SparseVoxelOctree | None, pixels: TrainingPixels, model: VoxNeRFModel,
                    use_cache: bool = True) -> FirstHitStage:
    t0 = time.perf_counter()
    if octree is None:
        return FirstHitStage(stage_record("first_hit_cache", False, "no octree", t0))
    # The pseudo depth, where there is one, tells the search where to stop first (same result, less work).
    hint = pixels.pseudo_t.view(-1) if pixels.pseudo_t is not None else None

    centre = model.config.sampling.window_centre

    def cast() -> tuple[torch.Tensor, torch.Tensor]:
        return per_pixel(pixels, model, lambda rays, index: window_centres(
            octree, centre, rays.origins, rays.dirs, rays.near, rays.far, None if hint is None else hint[index]))

    inputs = [*pixel_rays_key(pixels, model), octree_key(octree), hint, centre]
    (hit_t, hit), loaded = setup_cache.cached_per_pixel("first_hit", inputs, pixels.shape, pixels.images.device,
                                                        cast, use_cache)
    why = (f"octree first hit of every training pixel ({float(hit.float().mean()):.1%} hit; window centre: "
           f"{centre})"
           f"{FROM_CACHE if loaded else ''}")
    return FirstHitStage(stage_record("first_hit_cache", True, why, t0), hit_t, hit)
