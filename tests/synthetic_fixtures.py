"""Helpers of the tests of ``voxnerf.synthetic`` (tests/test_synthetic_*.py): the tiny room and its checks."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import open3d as o3d
import trimesh

from voxnerf.synthetic import RoomSpec, make_room_scene

TINY = RoomSpec(width=64, height=48, n_frames=60, train_every=5, gap_len=15, prior_max_points=60_000)


def make_tiny_scene(tmp_path_factory) -> Path:
    """The ``TINY`` room, written into a fresh directory of the session's ``tmp_path_factory``."""
    return make_room_scene(tmp_path_factory.mktemp("synthetic") / "tiny", TINY)


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
