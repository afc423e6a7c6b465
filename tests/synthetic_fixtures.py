"""Synthetic rooms for the tests: the tiny room of tests/test_synthetic_*.py and its checks, and the 24x18 room
(with a small model's config) that training tests run in seconds."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import open3d as o3d
import trimesh

from voxnerf.config import TrainConfig
from voxnerf.synthetic import RoomSpec, make_room_scene

TINY = RoomSpec(width=64, height=48, n_frames=60, train_every=5, gap_len=15, prior_max_points=60_000)


def make_tiny_scene(tmp_path_factory) -> Path:
    """The ``TINY`` room, written into a fresh directory of the session's ``tmp_path_factory``."""
    return make_room_scene(tmp_path_factory.mktemp("synthetic") / "tiny", TINY)


# 24x18 pixels, 10 training and 9 held-out frames, a 20k-point prior (sigma 2 cm).
MICRO = RoomSpec(width=24, height=18, n_frames=40, train_every=4, n_gaps=0, gap_len=0, prior_max_points=20_000)


def make_micro_scene(tmp_path_factory, name: str) -> Path:
    """The ``MICRO`` room, written into a fresh directory ``name`` of ``tmp_path_factory``."""
    return make_room_scene(tmp_path_factory.mktemp(name) / "tiny", MICRO)


def micro_config(**overrides) -> TrainConfig:
    """A 3-iteration run of a small model on the CPU (``overrides`` replace any field)."""
    values = dict(max_iters=3, compile=False, device="cpu", rays_per_batch=128, hash_levels=4, hash_log2_size=10,
                  hidden_dim=16, n_importance=4, n_rest=2, checkpoint_every_s=1e9)
    return TrainConfig(**{**values, **overrides})


def meta_of(scene: Path) -> dict:
    return json.loads((scene / "transforms.json").read_text())


def distance_to_gt(scene: Path, points: np.ndarray) -> np.ndarray:
    """Unsigned distance (m) from ``points`` [N, 3] to the clean ground-truth mesh written with the scene."""
    gt = trimesh.load(scene / "gt_mesh.ply", process=False)
    raycast = o3d.t.geometry.RaycastingScene()
    raycast.add_triangles(
        o3d.core.Tensor(np.asarray(gt.vertices, np.float32)), o3d.core.Tensor(np.asarray(gt.faces, np.uint32))
    )
    return raycast.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy()


def robust_sigma(distances: np.ndarray) -> float:
    """Std of a zero-mean Gaussian whose absolute values have this median (outlier-robust)."""
    return float(np.median(distances) / 0.6745)
