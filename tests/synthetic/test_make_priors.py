"""benchmarks/make_priors.py on a tiny synthetic room: three SCENE_FORMAT scenes with imperfect priors."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
import trimesh

from voxnerf.data.image_io import read_depth
from voxnerf.data.scene import load_scene
from voxnerf.prior.loading import load_prior
from voxnerf.synthetic import RoomSpec, make_room_scene

_PATH = Path(__file__).resolve().parents[2] / "benchmarks" / "make_priors.py"
_spec = importlib.util.spec_from_file_location("make_priors", _PATH)
make_priors = importlib.util.module_from_spec(_spec)
sys.modules["make_priors"] = make_priors
_spec.loader.exec_module(make_priors)


@pytest.fixture(scope="module")
def room(tmp_path_factory) -> Path:
    spec = RoomSpec(
        width=64, height=48, n_frames=120, prior_sigma=0.05, prior_max_points=20_000, supersample=1
    )
    return make_room_scene(tmp_path_factory.mktemp("priors") / "room", spec)


@pytest.fixture(scope="module")
def written(room: Path) -> dict[str, Path]:
    return make_priors.make_priors(room, seed=3)


def _gt_distance(points: np.ndarray, room: Path) -> np.ndarray:
    mesh = trimesh.load(room / "gt_mesh.ply", process=False, force="mesh")
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
        o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)),
    )
    return scene.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy()


def test_writes_one_loadable_scene_per_source(room: Path, written: dict[str, Path]) -> None:
    assert set(written) == {"monosdf", "slam", "tsdf"}
    source_meta = json.loads((room / "transforms.json").read_text())
    for source, path in written.items():
        assert path == room.parent / f"room-{source}"
        scene = load_scene(path)
        meta = json.loads((path / "transforms.json").read_text())
        assert scene.prior_path == path / "prior.ply"
        assert scene.prior_sigma == pytest.approx(meta["prior_sigma"])
        assert meta["prior_sigma"] >= make_priors.SIGMA_FLOOR
        assert meta["frames"] == source_meta["frames"] and meta["eval_splits"] == source_meta["eval_splits"]
        assert len(scene.images) == len(source_meta["frames"])
        assert meta["voxnerf_prior"]["source"] == source and meta["voxnerf_prior"]["seed"] == 3
        prior = load_prior(scene.prior_path, scene.prior_sigma)
        assert prior.kind == ("points" if source == "slam" else "mesh")
        assert np.isfinite(prior.points).all() and len(prior.points) > 1000


def test_priors_lie_near_the_true_surface_at_their_stated_sigma(room: Path, written: dict[str, Path]) -> None:
    for source, path in written.items():
        meta = json.loads((path / "transforms.json").read_text())
        sigma = meta["prior_sigma"]
        geometry = trimesh.load(path / "prior.ply", process=False)
        if isinstance(geometry, trimesh.Trimesh):
            points, _ = trimesh.sample.sample_surface(geometry, 50_000, seed=1)
        else:
            points = np.asarray(geometry.vertices)
        d = _gt_distance(np.asarray(points), room)
        assert np.median(d) < 3 * sigma, source
        # the stated sigma is the measured robust noise (median / 0.6745), unless the floor applies
        assert sigma == pytest.approx(max(np.median(d) / 0.6745, make_priors.SIGMA_FLOOR), rel=0.2), source
        # imperfect: not the ground truth itself
        assert np.median(d) > 1e-3, source


def test_tsdf_mesh_is_a_nonempty_surface(written: dict[str, Path]) -> None:
    mesh = trimesh.load(written["tsdf"] / "prior.ply", process=False, force="mesh")
    assert len(mesh.faces) > 1000 and mesh.area > 1.0


def test_monosdf_mesh_has_holes(room: Path, written: dict[str, Path]) -> None:
    gt = trimesh.load(room / "gt_mesh.ply", process=False, force="mesh")
    mono = trimesh.load(written["monosdf"] / "prior.ply", process=False, force="mesh")
    holes = json.loads((written["monosdf"] / "transforms.json").read_text())["voxnerf_prior"]["holes"]
    assert len(holes) == make_priors.PriorSettings().monosdf_holes
    # a hole centre is at least ~its radius away from the prior surface, but on the true surface
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.asarray(mono.vertices, np.float32)),
        o3d.core.Tensor(np.asarray(mono.faces, np.uint32)),
    )
    centres = np.array([h["centre"] for h in holes], np.float32)
    to_prior = scene.compute_distance(o3d.core.Tensor(centres)).numpy()
    radii = np.array([h["radius"] for h in holes])
    assert (to_prior > 0.5 * radii).all()
    # elsewhere the prior covers the true surface: GT vertices far from every hole are near the prior
    far = (
        np.linalg.norm(np.asarray(gt.vertices)[:, None] - centres[None], axis=2).min(axis=1) > 2 * radii.max()
    )
    gt_to_prior = scene.compute_distance(o3d.core.Tensor(np.asarray(gt.vertices, np.float32)[far])).numpy()
    assert np.median(gt_to_prior) < 0.05


def test_slam_points_only_where_training_cameras_saw(room: Path, written: dict[str, Path]) -> None:
    points = np.asarray(trimesh.load(written["slam"] / "prior.ply", process=False).vertices)
    s0 = json.loads((written["slam"] / "transforms.json").read_text())["voxnerf_prior"]["s0"]
    scene = load_scene(room, load_images=False)
    seen = np.zeros(len(points), bool)
    for index in scene.train_indices:
        frame = scene.frames[index]
        intr = frame.intrinsics
        depth = read_depth(frame.depth_path, scene.depth_unit_scale)
        cam = (points - frame.c2w[:3, 3]) @ frame.c2w[:3, :3]  # world -> camera (OpenGL axes)
        z = -cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.floor(cam[:, 0] / z * intr.fl_x + intr.cx)
            v = np.floor(-cam[:, 1] / z * intr.fl_y + intr.cy)
        inside = (z > 0.05) & (u >= 0) & (u < intr.width) & (v >= 0) & (v < intr.height)
        ui, vi = u[inside].astype(int), v[inside].astype(int)
        d = depth[vi, ui]
        near = np.abs(z[inside] - d) < 0.05 + 5 * s0 * d**2
        seen[np.flatnonzero(inside)[near]] = True
    outliers = json.loads((written["slam"] / "transforms.json").read_text())["voxnerf_prior"]["n_outliers"]
    assert outliers > 0
    assert (~seen).sum() <= outliers + 0.002 * len(points)


def test_same_seed_same_files(room: Path, written: dict[str, Path], tmp_path: Path) -> None:
    again = make_priors.make_priors(room, tmp_path, sources=("slam",), seed=3)
    assert (again["slam"] / "prior.ply").read_bytes() == (written["slam"] / "prior.ply").read_bytes()
    other = make_priors.make_priors(room, tmp_path / "other", sources=("slam",), seed=4)
    assert (other["slam"] / "prior.ply").read_bytes() != (written["slam"] / "prior.ply").read_bytes()


def test_rejects_a_scene_without_ground_truth(room: Path, tmp_path: Path) -> None:
    bare = make_priors.write_prior_scene(
        room, tmp_path / "bare", np.zeros((40, 3)) + np.arange(40)[:, None], 0.05, {"source": "test"}
    )
    (bare / "gt_mesh.ply").unlink()
    with pytest.raises(make_priors.SceneError, match="gt_mesh.ply"):
        make_priors.load_ground_truth(bare)
    with pytest.raises(ValueError, match="unknown prior sources"):
        make_priors.make_priors(room, tmp_path, sources=("lidar",))
