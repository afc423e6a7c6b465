"""What the set-up stages share: their records, the set-up cache's keys, the prior's depth renderers."""

from __future__ import annotations

import random
import time

import numpy as np
import torch

from voxnerf.model.voxnerf_model import VoxNeRFModel
from voxnerf.prior.loading import GeometryPrior
from voxnerf.prior.octree import SparseVoxelOctree
from voxnerf.prior.pseudo_depth import PriorDepthRenderer
from voxnerf.training.pixels import TrainingPixels
from voxnerf.training.records import StageRecord


def stage_record(name: str, ran: bool, why: str, started: float) -> StageRecord:
    return StageRecord(name=name, ran=ran, why=why, seconds=time.perf_counter() - started)


FROM_CACHE = "; loaded from the set-up cache"


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def pixel_rays_key(pixels: TrainingPixels, model: VoxNeRFModel) -> list:
    """What fixes the rays of every training pixel and their near / far bounds (:func:`per_pixel`), for
    :mod:`setup_cache` keys."""
    return [*training_rays_key(pixels), model.aabb]


def training_rays_key(pixels: TrainingPixels) -> list:
    """What fixes the rays of every training pixel (:meth:`TrainingPixels.rays`) and which pixels there are, for
    :mod:`setup_cache` keys (a scene of one image size keys as it always did)."""
    lens = None if pixels.lens is None else (pixels.lens.coeffs, pixels.lens.codes)
    table = None if pixels.directions is None else (pixels.directions.dirs, pixels.directions.camera)
    key = [pixels.shape, pixels.c2w, pixels.intr, lens, table]
    return key if pixels.sizes is None else [*key, pixels.sizes]


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
