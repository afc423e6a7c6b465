"""voxnerf.synthetic.priors: the point-cloud and mesh priors carry the noise, outliers and holes they state."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh
from synthetic_fixtures import TINY, distance_to_gt, make_tiny_scene, meta_of, robust_sigma

from voxnerf.synthetic import RoomSpec, build_room, make_room_scene


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory) -> Path:
    return make_tiny_scene(tmp_path_factory)


def test_point_prior_has_stated_noise(tiny_scene: Path):
    meta = meta_of(tiny_scene)
    cloud = trimesh.load(tiny_scene / meta["prior_file_path"])
    assert isinstance(cloud, trimesh.PointCloud)
    points = np.asarray(cloud.vertices)
    assert len(points) == meta["voxnerf_synthetic"]["prior"]["n_points"]
    assert 0.8 * TINY.prior_max_points < len(points) <= 1.03 * TINY.prior_max_points
    dist = distance_to_gt(tiny_scene, points)
    sigma = meta["prior_sigma"]
    assert sigma / 1.5 < robust_sigma(dist) < sigma * 1.5
    far = np.mean(dist > 5 * sigma)
    assert 0.005 < far < 0.05, f"about 2% outliers expected, got {far:.3%}"
    for hole in meta["voxnerf_synthetic"]["prior"]["holes"]:
        inside = np.linalg.norm(points - hole["centre"], axis=1) < hole["radius"] - 1e-3
        assert not inside.any()


def test_mesh_prior_into_empty_dir(tmp_path: Path):
    out = tmp_path / "mesh"
    out.mkdir()
    spec = RoomSpec(
        width=32, height=24, n_frames=40, train_every=4, gap_len=10, prior_kind="mesh", write_depth=False
    )
    make_room_scene(out, spec)
    meta = meta_of(out)
    assert "depth_unit_scale_factor" not in meta and all("depth_file_path" not in f for f in meta["frames"])
    mesh = trimesh.load(out / meta["prior_file_path"], process=False)
    assert isinstance(mesh, trimesh.Trimesh) and len(mesh.faces) > 10 * len(build_room(0).triangles)
    dist = distance_to_gt(out, np.asarray(mesh.vertices))
    assert spec.prior_sigma / 1.5 < robust_sigma(dist) < spec.prior_sigma * 1.5
