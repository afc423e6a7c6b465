"""Stage octree: the sampler's Sparse Voxel Octree over the prior, its leaf from sigma and the rays' coverage."""

from __future__ import annotations

import time
from dataclasses import dataclass

import torch

from voxnerf.config import TrainConfig
from voxnerf.model.voxnerf_model import VoxNeRFModel
from voxnerf.prior.loading import GeometryPrior
from voxnerf.prior.octree import SparseVoxelOctree, coverage_octree
from voxnerf.training.pixels import TrainingPixels
from voxnerf.training.records import StageRecord
from voxnerf.training.stages.common import stage_record

COVERAGE_RAYS = 65_536  # training rays that choose the sampler octree's leaf (voxnerf.prior.octree.coverage_octree)


@dataclass
class OctreeStage:
    record: StageRecord
    octree: SparseVoxelOctree | None


def octree_stage(cfg: TrainConfig, prior_n: GeometryPrior | None, pixels: TrainingPixels, model: VoxNeRFModel,
                 device: torch.device) -> OctreeStage:
    t0 = time.perf_counter()
    if cfg.sampling.may_use_window and prior_n is not None:
        octree, why = sampler_octree(prior_n, pixels, model, cfg, device)
        return OctreeStage(stage_record("octree", True, why, t0), octree)
    why = "no prior" if prior_n is None else f"sampler {cfg.sampling.sampler!r} does not use it"
    return OctreeStage(stage_record("octree", False, why, t0), None)


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
    gen = torch.Generator(device=device).manual_seed(0)
    flat = pixels.random_pixels(min(COVERAGE_RAYS, pixels.pixel_count), gen)
    rays = model.ray_bundle(*pixels.rays(*pixels.index_of(flat)))
    octree, misses = coverage_octree(points, prior.sigma, rays.origins, rays.dirs, rays.near, rays.far)
    tried = ", ".join(f"{s} sigma: {m:.1%}" for s, m in misses.items())
    scale = octree.leaf_size_requested / prior.sigma
    return octree, (f"voxnerf sampler: {octree.levels} levels, leaf {scale:g} sigma = {octree.leaf_size:.4g} "
                    f"(normalised), the smallest that training rays do not slip through (rays missing every "
                    f"leaf: {tried})")
