"""Stage prior_rays: a bank of rays from the training cameras' centres, supervised by the prior's depth."""

from __future__ import annotations

import time
from dataclasses import dataclass

import torch

from voxnerf.config import TrainConfig
from voxnerf.model.voxnerf_model import VoxNeRFModel
from voxnerf.prior.loading import GeometryPrior
from voxnerf.prior.octree import SparseVoxelOctree
from voxnerf.training.pixels import TrainingPixels
from voxnerf.training.prior_rays import PriorRayBank, bank_size, prior_ray_bank, seen_by
from voxnerf.training.records import StageRecord
from voxnerf.training.stages.common import prior_depth_renderer, stage_record

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
        return PriorRaysStage(stage_record("prior_rays", False, why, t0))
    wanted = bank_size(cfg.loss.prior_rays)
    bank = prior_ray_bank(pixels.c2w[:, :3, 3], model, prior_depth_renderer(prior_n, octree, device), octree, wanted,
                          cfg.run.seed)
    if not len(bank):
        return PriorRaysStage(stage_record("prior_rays", False, "no ray from the training cameras hits the prior", t0))
    why = (f"{cfg.loss.prior_rays} rays per step from the training cameras' centres, supervised by the prior's depth: "
           f"{len(bank)} of {wanted} random rays hit the prior")
    if cfg.loss.prior_ray_colour > 0:
        depth = pixels.depth_t if pixels.depth_t is not None else pixels.pseudo_t
        points = bank.rays.origins + bank.target_t[:, None] * bank.rays.dirs
        tolerance = UNSEEN_TOLERANCE_LEAVES * (octree.leaf_size if octree is not None else prior_n.sigma)
        bank.unseen = ~seen_by(points, pixels.c2w, pixels.intr, depth, tolerance, sizes=pixels.sizes)
        why += f"; {float(bank.unseen.float().mean()):.1%} meet surfaces no training view sees (mean-colour term)"
    return PriorRaysStage(stage_record("prior_rays", True, why, t0), bank)
