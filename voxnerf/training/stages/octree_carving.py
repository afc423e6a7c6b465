"""Stage octree_carving: the sampler octree less the leaves the sensor depth shows empty."""

from __future__ import annotations

import time
from dataclasses import dataclass

import torch

from voxnerf.config import TrainConfig
from voxnerf.prior.carving import empty_leaves, remove_empty
from voxnerf.prior.octree import SparseVoxelOctree
from voxnerf.training import setup_cache
from voxnerf.training.pixels import TrainingPixels, rays_in_chunks
from voxnerf.training.records import StageRecord
from voxnerf.training.stages.common import FROM_CACHE, octree_key, stage_record, training_rays_key
from voxnerf.training.stages.depth_target import DepthTargetStage
from voxnerf.training.step import DEPTH_BETA_PER_SIGMA


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
        return CarvingStage(stage_record("octree_carving", False, why, t0), None)
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
    return CarvingStage(stage_record("octree_carving", True, why, t0), carving.octree)


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
