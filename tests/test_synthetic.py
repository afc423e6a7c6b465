"""The synthetic room: SCENE_FORMAT.md compliance, camera conventions, prior noise, splits, determinism."""

from __future__ import annotations

import json
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import open3d as o3d
import pytest
import trimesh

from voxnerf.synthetic import (
    RoomSpec,
    build_room,
    camera_path,
    make_room_scene,
    render_view,
    split_frames,
)

TINY = RoomSpec(width=64, height=48, n_frames=60, train_every=5, gap_len=15, prior_max_points=60_000)


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory) -> Path:
    return make_room_scene(tmp_path_factory.mktemp("synthetic") / "tiny", TINY)


def _meta(scene: Path) -> dict:
    return json.loads((scene / "transforms.json").read_text())


def _distance_to_gt(scene: Path, points: np.ndarray) -> np.ndarray:
    """Unsigned distance (m) from ``points`` [N, 3] to the clean ground-truth mesh written with the scene."""
    gt = trimesh.load(scene / "gt_mesh.ply", process=False)
    raycast = o3d.t.geometry.RaycastingScene()
    raycast.add_triangles(
        o3d.core.Tensor(np.asarray(gt.vertices, np.float32)), o3d.core.Tensor(np.asarray(gt.faces, np.uint32))
    )
    return raycast.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy()


def _robust_sigma(distances: np.ndarray) -> float:
    """Std of a zero-mean Gaussian whose absolute values have this median (outlier-robust)."""
    return float(np.median(distances) / 0.6745)


def test_scene_follows_scene_format(tiny_scene: Path):
    meta = _meta(tiny_scene)
    for key in ("fl_x", "fl_y", "cx", "cy", "w", "h", "frames"):
        assert key in meta
    assert (meta["w"], meta["h"]) == (TINY.width, TINY.height)
    assert (meta["cx"], meta["cy"]) == (TINY.width / 2, TINY.height / 2)
    hfov = 2 * np.degrees(np.arctan(meta["w"] / 2 / meta["fl_x"]))
    assert 60 <= hfov <= 70
    assert meta["depth_unit_scale_factor"] == 0.001
    assert meta["prior_file_path"] == "prior.ply" and meta["prior_sigma"] == TINY.prior_sigma

    frame_paths = [f["file_path"] for f in meta["frames"]]
    assert len(frame_paths) == len(set(frame_paths))
    for frame in meta["frames"]:
        c2w = np.asarray(frame["transform_matrix"])
        assert c2w.shape == (4, 4)
        np.testing.assert_allclose(c2w[3], [0, 0, 0, 1])
        np.testing.assert_allclose(c2w[:3, :3] @ c2w[:3, :3].T, np.eye(3), atol=1e-6)
        assert np.linalg.det(c2w[:3, :3]) == pytest.approx(1.0, abs=1e-6)
        rgb = iio.imread(tiny_scene / frame["file_path"])
        assert rgb.shape == (TINY.height, TINY.width, 3) and rgb.dtype == np.uint8
        assert rgb.std() > 10, "images should carry texture"
        depth = iio.imread(tiny_scene / frame["depth_file_path"])
        assert depth.shape == (TINY.height, TINY.width) and depth.dtype == np.uint16
        assert depth.min() > 0, "the closed room leaves no pixel without depth"

    splits = {"train": meta["train_filenames"], "test": meta["test_filenames"], **meta["eval_splits"]}
    assert set(meta["eval_splits"]) == {"interpolation", "extrapolation"}
    assert meta["test_filenames"] == meta["eval_splits"]["interpolation"]
    for name, files in splits.items():
        assert files, name
        assert set(files) <= set(frame_paths), name
    assert not set(splits["train"]) & (set(splits["interpolation"]) | set(splits["extrapolation"]))
    assert set(frame_paths) == set().union(*splits.values()), "only frames a split uses are written"
    on_disk = sorted(p.name for p in (tiny_scene / "images").iterdir())
    assert on_disk == sorted(Path(p).name for p in frame_paths)
    assert (tiny_scene / "gt_mesh.ply").is_file()
    assert meta["voxnerf_synthetic"]["seed"] == TINY.seed
    assert meta["voxnerf_synthetic"]["room_size"] == [5.0, 4.0, 2.6]


def test_point_prior_has_stated_noise(tiny_scene: Path):
    meta = _meta(tiny_scene)
    cloud = trimesh.load(tiny_scene / meta["prior_file_path"])
    assert isinstance(cloud, trimesh.PointCloud)
    points = np.asarray(cloud.vertices)
    assert len(points) == meta["voxnerf_synthetic"]["prior"]["n_points"]
    assert 0.8 * TINY.prior_max_points < len(points) <= 1.03 * TINY.prior_max_points
    dist = _distance_to_gt(tiny_scene, points)
    sigma = meta["prior_sigma"]
    assert sigma / 1.5 < _robust_sigma(dist) < sigma * 1.5
    far = np.mean(dist > 5 * sigma)
    assert 0.005 < far < 0.05, f"about 2% outliers expected, got {far:.3%}"
    for hole in meta["voxnerf_synthetic"]["prior"]["holes"]:
        inside = np.linalg.norm(points - hole["centre"], axis=1) < hole["radius"] - 1e-3
        assert not inside.any()


def test_depth_png_matches_rendered_z_depth(tiny_scene: Path):
    meta = _meta(tiny_scene)
    geom = build_room(TINY.seed)
    for frame in meta["frames"][::7]:
        rgb, depth = render_view(
            geom,
            np.asarray(frame["transform_matrix"]),
            meta["fl_x"],
            meta["cx"],
            meta["cy"],
            meta["w"],
            meta["h"],
            TINY.supersample,
        )
        assert rgb.dtype == np.float32 and depth.dtype == np.float32
        assert np.isfinite(depth).all() and rgb.min() >= 0.0 and rgb.max() <= 1.0
        png_depth = iio.imread(tiny_scene / frame["depth_file_path"]).astype(np.float64) * 0.001
        assert np.abs(png_depth - depth).max() <= 0.001
        png_rgb = iio.imread(tiny_scene / frame["file_path"]).astype(np.float64)
        assert np.abs(png_rgb - rgb * 255).max() <= 0.5 + 1e-3


def test_table_top_projects_to_its_depth(tiny_scene: Path):
    """Project the table top's centre through each camera (OpenGL axes) and intersect the pixel's ray with the
    top's plane analytically: the written depth must equal that z-depth, or be smaller where an object on the
    table occludes it -- never larger (which would mean a flipped axis shows the floor or a wall)."""
    meta = _meta(tiny_scene)
    lo, hi = (np.asarray(b) for b in meta["voxnerf_synthetic"]["objects"]["table_top"]["bounds"])
    top_z = hi[2]
    centre = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, top_z])
    fl, cx, cy, w, h = meta["fl_x"], meta["cx"], meta["cy"], meta["w"], meta["h"]
    matched = 0
    for frame in meta["frames"]:
        c2w = np.asarray(frame["transform_matrix"])
        x, y, z = np.linalg.inv(c2w)[:3] @ np.append(centre, 1.0)
        if z >= 0:
            continue  # behind the camera (it looks along -Z)
        u, v = cx + fl * x / -z, cy - fl * y / -z
        if not (1 <= u < w - 1 and 1 <= v < h - 1):
            continue
        px, py = int(u), int(v)
        ray_cam = np.array([(px + 0.5 - cx) / fl, -(py + 0.5 - cy) / fl, -1.0])
        ray_world = c2w[:3, :3] @ ray_cam
        t = (top_z - c2w[2, 3]) / ray_world[2]  # z-depth, as the camera z-component of ray_cam is -1
        hit = c2w[:3, 3] + t * ray_world
        assert lo[0] <= hit[0] <= hi[0] and lo[1] <= hit[1] <= hi[1], "the pixel ray should meet the top"
        depth = iio.imread(tiny_scene / frame["depth_file_path"])[py, px] * 0.001
        assert depth <= t + 0.002, frame["file_path"]
        matched += abs(depth - t) <= 0.002
    assert matched >= 2


def test_extrapolation_frames_are_far_from_training_frames(tiny_scene: Path):
    meta = _meta(tiny_scene)
    poses = {f["file_path"]: np.asarray(f["transform_matrix"]) for f in meta["frames"]}
    train = np.stack([poses[p] for p in meta["train_filenames"]])

    def nearest(names: list[str]) -> tuple[float, float]:
        dists, angles = [], []
        for name in names:
            c2w = poses[name]
            dists.append(np.linalg.norm(train[:, :3, 3] - c2w[:3, 3], axis=1).min())
            cos = np.clip(np.einsum("i,ni->n", c2w[:3, 2], train[:, :3, 2]), -1, 1)
            angles.append(np.degrees(np.arccos(cos)).min())
        return float(np.mean(dists)), float(np.mean(angles))

    interp = nearest(meta["eval_splits"]["interpolation"])
    extrap = nearest(meta["eval_splits"]["extrapolation"])
    assert extrap[0] > 1.5 * interp[0] and extrap[1] > 1.5 * interp[1]


def test_cameras_stay_clear_of_the_furniture(tiny_scene: Path):
    positions = camera_path(200)[:, :3, 3]
    assert (np.abs(positions[:, :2]) < [2.5, 2.0]).all()
    assert (positions[:, 2] >= 1.2).all() and (positions[:, 2] <= 1.7).all()
    assert _distance_to_gt(tiny_scene, positions).min() > 0.5


def test_generation_is_deterministic(tiny_scene: Path, tmp_path: Path):
    again = make_room_scene(tmp_path / "again", TINY)
    files = sorted(p.relative_to(tiny_scene) for p in tiny_scene.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(again) for p in again.rglob("*") if p.is_file())
    for rel in files:
        assert (tiny_scene / rel).read_bytes() == (again / rel).read_bytes(), rel


def test_mesh_prior_into_empty_dir(tmp_path: Path):
    out = tmp_path / "mesh"
    out.mkdir()
    spec = RoomSpec(
        width=32, height=24, n_frames=40, train_every=4, gap_len=10, prior_kind="mesh", write_depth=False
    )
    make_room_scene(out, spec)
    meta = _meta(out)
    assert "depth_unit_scale_factor" not in meta and all("depth_file_path" not in f for f in meta["frames"])
    mesh = trimesh.load(out / meta["prior_file_path"], process=False)
    assert isinstance(mesh, trimesh.Trimesh) and len(mesh.faces) > 10 * len(build_room(0).triangles)
    dist = _distance_to_gt(out, np.asarray(mesh.vertices))
    assert spec.prior_sigma / 1.5 < _robust_sigma(dist) < spec.prior_sigma * 1.5


def test_no_prior_and_refused_output(tmp_path: Path):
    spec = RoomSpec(width=32, height=24, n_frames=40, train_every=4, gap_len=10, prior_kind="none", seed=3)
    out = make_room_scene(tmp_path / "none", spec)
    meta = _meta(out)
    assert "prior_file_path" not in meta and "prior_sigma" not in meta and not (out / "prior.ply").exists()
    with pytest.raises(FileExistsError, match="none"):
        make_room_scene(out, spec)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["none"], "no temporary directory is left behind"
    with pytest.raises(ValueError, match="prior_kind"):
        make_room_scene(tmp_path / "bad", RoomSpec(prior_kind="tsdf"))


def test_default_splits_mimic_redkitchen():
    splits = split_frames(160, 10, 2, 30)
    assert splits.train == [0, 10, 20, 60, 70, 80, 90, 100, 140, 150]
    assert splits.interpolation == [5, 15, 65, 75, 85, 95, 145]
    assert splits.extrapolation == [30, 35, 40, 45, 50, 110, 115, 120, 125, 130]
    with pytest.raises(ValueError, match="training frame"):
        split_frames(60, 10, 2, 40)
    with pytest.raises(ValueError, match="train_every"):
        split_frames(60, 1, 0, 0)
