"""The set-up stages of a run (their order and wiring: :mod:`voxnerf.training.setup`), one module each.

Each stage function takes what it needs and returns its product with its :class:`StageRecord` (whether it ran and
why). Modules: ``load_scene``, ``prior``, ``hash_kernel``, ``model``, ``octree``, ``pseudo_depth``, ``prior_rays``,
``depth_target``, ``octree_carving``, ``first_hit_cache``, ``window_check``, ``colour_prior``, ``compile``,
``corrections``, ``weight_decay``, ``focal``; ``common`` holds what they share. The names are re-exported here
(``window_check``'s and ``colour_prior``'s are imported from their modules), so
``from voxnerf.training.stages import model_stage`` reads as before the split.
"""

from __future__ import annotations

from voxnerf.training.stages.common import (
    FROM_CACHE,
    octree_key,
    pixel_rays_key,
    prior_depth_octree,
    prior_depth_renderer,
    prior_key,
    seed_everything,
    training_rays_key,
)
from voxnerf.training.stages.compile import CompileStage, compile_stage, inductor_cache_dir
from voxnerf.training.stages.depth_target import (
    BETA_SCALE_RANGE,
    DepthTargetStage,
    depth_source,
    depth_target_stage,
    measure_noise_against,
)
from voxnerf.training.stages.first_hit_cache import FirstHitStage, first_hit_stage
from voxnerf.training.stages.hash_kernel import hash_kernel_stage
from voxnerf.training.stages.load_scene import SceneStage, check_sensor_depth, load_scene_stage
from voxnerf.training.stages.model import (
    APPEARANCE_LR_SCALE,
    ModelStage,
    model_stage,
    scene_box,
    training_mean_colour,
    training_pixel_cone,
)
from voxnerf.training.stages.octree import COVERAGE_RAYS, OctreeStage, octree_stage, sampler_octree
from voxnerf.training.stages.octree_carving import (
    CARVE_FREE_RAYS,
    CARVE_MARGIN_LEAVES,
    CARVE_MARGIN_SIGMAS,
    CARVE_SURFACE_RAYS,
    CarvingStage,
    carving_stage,
)
from voxnerf.training.stages.prior import PriorStage, pinhole_depth, prior_stage, training_depth_views
from voxnerf.training.stages.prior_rays import UNSEEN_TOLERANCE_LEAVES, PriorRaysStage, prior_rays_stage
from voxnerf.training.stages.pseudo_depth import MIN_PRIOR_COVERAGE, PseudoDepthStage, pseudo_depth_stage

__all__ = [
    "APPEARANCE_LR_SCALE", "BETA_SCALE_RANGE", "CARVE_FREE_RAYS", "CARVE_MARGIN_LEAVES", "CARVE_MARGIN_SIGMAS",
    "CARVE_SURFACE_RAYS", "COVERAGE_RAYS", "CarvingStage", "CompileStage", "DepthTargetStage", "FROM_CACHE",
    "FirstHitStage", "MIN_PRIOR_COVERAGE", "ModelStage", "OctreeStage", "PriorRaysStage", "PriorStage",
    "PseudoDepthStage", "SceneStage", "UNSEEN_TOLERANCE_LEAVES", "carving_stage", "check_sensor_depth",
    "compile_stage", "depth_source", "depth_target_stage", "first_hit_stage", "hash_kernel_stage",
    "inductor_cache_dir", "load_scene_stage", "measure_noise_against", "model_stage", "octree_key",
    "octree_stage", "pinhole_depth", "pixel_rays_key", "prior_depth_octree", "prior_depth_renderer",
    "prior_key", "prior_rays_stage", "prior_stage", "pseudo_depth_stage", "sampler_octree", "scene_box",
    "seed_everything", "training_depth_views", "training_mean_colour", "training_pixel_cone",
    "training_rays_key",
]
