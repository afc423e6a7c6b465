"""A run directory with an untrained model, written directly: renders in milliseconds, no training needed."""

from __future__ import annotations

from pathlib import Path

import torch

from voxnerf.cameras.rules import Intrinsics
from voxnerf.config import TrainConfig
from voxnerf.data.scene import SceneTransform
from voxnerf.inference.render import CHECKPOINT
from voxnerf.model.voxnerf_model import VoxNeRFModel

DEFAULT_INTRINSICS = Intrinsics(fl_x=20.0, fl_y=20.0, cx=8.0, cy=6.0, width=16, height=12)
DEPTH_UNIT_SCALE = 0.001


def write_tiny_run(run_dir: Path, seed: int = 0, iteration: int = 0) -> Path:
    """``run_dir/checkpoint.pt`` of a freshly initialised model (uniform sampler, eager) over the box
    ``[-2, 2]^3`` in scene units, with :data:`DEFAULT_INTRINSICS` as its default camera, saved as the checkpoint
    of ``iteration``."""
    torch.manual_seed(seed)
    config = TrainConfig(max_iters=1, device="cpu", sampler="uniform", compile=False, hash_kernel=False)
    transform = SceneTransform((0.0, 0.0, 0.0), 0.5)
    aabb = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    model = VoxNeRFModel.create(config, transform, aabb, None, torch.device("cpu"))
    run_dir.mkdir(parents=True, exist_ok=True)
    torch.save(
        {
            "model": model.state_dict(),
            "iteration": iteration,
            "default_intrinsics": DEFAULT_INTRINSICS.as_dict(),
            "depth_unit_scale": DEPTH_UNIT_SCALE,
            "scene_dir": None,
        },
        run_dir / CHECKPOINT,
    )
    return run_dir


def tiny_model(**overrides) -> VoxNeRFModel:
    """A freshly initialised small model (4 hash levels, 16 hidden) over the box ``[-1, 1]^3``, normalised units
    equal to scene units; ``overrides`` replace TrainConfig fields."""
    config = TrainConfig(**{**dict(max_iters=1, hash_levels=4, hash_log2_size=10, hash_max_resolution=32,
                                   hidden_dim=16), **overrides})
    aabb = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    return VoxNeRFModel.create(config, SceneTransform((0.0, 0.0, 0.0), 1.0), aabb, None, torch.device("cpu"))
