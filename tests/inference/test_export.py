"""Geometry export (voxnerf/inference/export.py, ``voxnerf export``): a briefly trained small room's mesh and point
cloud
against the room's true mesh, in scene units; the failure paths on an untrained tiny run (tests/tiny_run.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
import trimesh
from tiny_run import DEFAULT_INTRINSICS, write_tiny_run

from voxnerf.cameras.rules import Intrinsics
from voxnerf.cli import main
from voxnerf.data.scene import Frame, Scene, load_scene
from voxnerf.errors import VoxNeRFError
from voxnerf.inference.export import (
    EXPORT_KINDS,
    ExportError,
    distances_to_mesh,
    export_geometry,
    export_views,
    fuse_mesh,
    point_cloud,
    render_view,
)
from voxnerf.inference.export_plan import view_count, view_size
from voxnerf.inference.render import load_model, render
from voxnerf.prior.depth_fusion import DepthView, backproject

# Measured on conftest's trained_small_room (small_room, 500 iterations of 1024 rays, CPU, seed 0; exports at
# 2 cm): see docs/engine.md, Geometry export. Bounds in metres (scene units), 2.5-3.5 times the measured values
# (margin for seeds and platforms).
VOXEL = "0.02"
MESH_ACCURACY = (0.03, 0.06)  # mean, 90th percentile: exported mesh vertices -> true mesh
MESH_COMPLETENESS = (0.03, 0.06)  # true surface the training cameras see -> exported mesh
CLOUD_ACCURACY = (0.03, 0.06)
CLOUD_COMPLETENESS = (0.03, 0.06)


@pytest.fixture(scope="module")
def exported(trained_small_room, tmp_path_factory) -> dict[str, Path]:
    """The room's mesh and point cloud, written by the CLI at 2 cm voxels."""
    out = tmp_path_factory.mktemp("geometry")
    paths = {"mesh": out / "room_mesh.ply", "pointcloud": out / "room_points.ply"}
    code = main(["export", str(trained_small_room), "--mesh", str(paths["mesh"]),
                 "--pointcloud", str(paths["pointcloud"]), "--voxel-size", VOXEL, "--device", "cpu"])
    assert code == 0
    return paths


def _distance_to(mesh: trimesh.Trimesh, points: np.ndarray) -> np.ndarray:
    return distances_to_mesh(points, mesh)


def _distance_to_points(cloud: np.ndarray, queries: np.ndarray) -> np.ndarray:
    tree = o3d.geometry.KDTreeFlann(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cloud.astype(np.float64))))
    return np.sqrt([tree.search_knn_vector_3d(q, 1)[2][0] for q in queries])


def _visible_truth(scene_dir: Path) -> np.ndarray:
    """Points [N, 3] of the true surface the training cameras see: their (synthetic, exact) depth maps."""
    scene = load_scene(scene_dir)
    return np.concatenate([backproject(DepthView(scene.depths[i], scene.intrinsics(i), scene.frames[i].c2w), 2)
                           for i in scene.train_indices])


def _summary(d: np.ndarray) -> tuple[float, float]:
    return float(d.mean()), float(np.percentile(d, 90))


def test_mesh_lies_on_the_true_room(exported, small_room):
    mesh = trimesh.load(exported["mesh"], process=False)
    truth = trimesh.load(small_room / "gt_mesh.ply", process=False)
    accuracy = _summary(_distance_to(truth, mesh.vertices))
    completeness = _summary(_distance_to(mesh, _visible_truth(small_room)))
    print(f"mesh: accuracy mean/p90 {accuracy}, completeness mean/p90 {completeness} m")
    assert accuracy[0] < MESH_ACCURACY[0] and accuracy[1] < MESH_ACCURACY[1], accuracy
    assert completeness[0] < MESH_COMPLETENESS[0] and completeness[1] < MESH_COMPLETENESS[1], completeness


def test_point_cloud_lies_on_the_true_room(exported, small_room):
    cloud = trimesh.load(exported["pointcloud"], process=False)
    truth = trimesh.load(small_room / "gt_mesh.ply", process=False)
    points = np.asarray(cloud.vertices)
    accuracy = _summary(_distance_to(truth, points))
    completeness = _summary(_distance_to_points(points, _visible_truth(small_room)[::4]))
    print(f"point cloud: accuracy mean/p90 {accuracy}, completeness mean/p90 {completeness} m")
    assert accuracy[0] < CLOUD_ACCURACY[0] and accuracy[1] < CLOUD_ACCURACY[1], accuracy
    assert completeness[0] < CLOUD_COMPLETENESS[0] and completeness[1] < CLOUD_COMPLETENESS[1], completeness


@pytest.mark.parametrize("kind", EXPORT_KINDS)
def test_geometry_is_in_scene_units_with_plausible_colours(exported, small_room, kind):
    geometry = trimesh.load(exported[kind], process=False)
    truth = trimesh.load(small_room / "gt_mesh.ply", process=False)  # the 5 x 4 x 2.6 m room, z up
    lo, hi = np.percentile(geometry.vertices, 1, axis=0), np.percentile(geometry.vertices, 99, axis=0)
    # the walls (x, y) are seen all round; the cameras look down, so the floor is seen and the ceiling hardly
    assert np.all(np.abs(lo[:2] - truth.bounds[0, :2]) < 0.25), lo
    assert np.all(np.abs(hi[:2] - truth.bounds[1, :2]) < 0.25), hi
    assert abs(geometry.vertices[:, 2].min() - truth.bounds[0, 2]) < 0.25 and hi[2] < truth.bounds[1, 2] + 0.25
    colours = np.asarray(geometry.visual.vertex_colors)[:, :3].astype(float)
    assert colours.mean() > 60 and colours.std() > 10  # neither black nor one flat colour
    if kind == "pointcloud":
        normals = np.asarray(o3d.io.read_point_cloud(str(exported[kind])).normals)
        assert len(normals) == len(geometry.vertices)
        np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-3)


def test_mesh_export_is_deterministic(trained_small_room, tmp_path):
    trained = load_model(trained_small_room, "cpu")
    first, second = (export_geometry(trained, tmp_path / f"{i}.ply", "mesh", voxel_size=0.05, max_views=12)
                     for i in range(2))
    assert first.faces > 0 and not first.stopped
    assert (tmp_path / "0.ply").read_bytes() == (tmp_path / "1.ply").read_bytes()
    assert set(first.summary()) == {"kind", "out", "views", "points", "faces", "voxel_size", "seconds", "stopped"}


# --- fusion pieces on exact synthetic views ---------------------------------------------------------------------

PLANE_CAMERA = DEFAULT_INTRINSICS.scaled(4.0)  # 64 x 48


def _plane_views(depth_value: float = 2.0) -> list[DepthView]:
    """Views of the plane z = -depth_value from cameras at z = 0 shifted sideways; left half red, right blue."""
    views = []
    for dx in (-0.1, 0.0, 0.1, 0.2):
        depth = np.full((PLANE_CAMERA.height, PLANE_CAMERA.width), depth_value, np.float32)
        rgb = np.zeros((*depth.shape, 3), np.uint8)
        rgb[..., 0] = 200
        c2w = np.eye(4)
        c2w[0, 3] = dx
        views.append(DepthView(depth, PLANE_CAMERA, c2w, rgb))
    return views


def test_fused_mesh_carries_the_views_colours():
    mesh = fuse_mesh(_plane_views(), 0.02)
    colours = np.asarray(mesh.visual.vertex_colors)
    assert len(mesh.faces) > 0 and np.all(np.abs(colours[:, 0].astype(int) - 200) <= 2) and colours[:, 2].max() == 0
    assert np.abs(mesh.vertices[:, 2] + 2.0).max() < 0.02


def test_non_finite_depth_never_becomes_a_point():
    views = _plane_views()
    for view in views:
        view.depth[::3, ::5] = np.inf
        view.depth[1::4, ::2] = np.nan
        view.depth[2::7] = -1.0
    points, colours, normals = point_cloud(views, 0.02)
    assert len(points) > 0 and np.isfinite(points).all() and np.isfinite(normals).all()
    assert np.abs(points[:, 2] + 2.0).max() < 1e-3
    np.testing.assert_allclose(normals, np.tile([0.0, 0.0, 1.0], (len(normals), 1)), atol=1e-3)  # toward cameras
    assert np.all(colours[:, 0] == 200)


# --- failure paths on an untrained tiny run (box [-2, 2]^3, renders in milliseconds) --------------------------------


def _scene(tmp_path: Path, look_away: bool = False) -> Scene:
    """A two-frame scene (no files needed: images are not read) of cameras at z = 3 looking at the box, or away."""
    frames = []
    for dx in (0.0, 0.3):
        c2w = np.eye(4)
        c2w[:3, 3] = (dx, 0.0, 3.0)
        if look_away:
            c2w[:3, :3] = np.diag([-1.0, 1.0, -1.0])
        frames.append(Frame(f"images/{dx}.png", tmp_path / f"{dx}.png", c2w, DEFAULT_INTRINSICS))
    return Scene(tmp_path, frames, {"train": [0, 1]}, None, None, 0.001)


@pytest.fixture
def tiny(tmp_path):
    return load_model(write_tiny_run(tmp_path / "tiny"), "cpu")


def test_views_are_fused_from_centre_rays_whatever_the_run_renders(tiny, tmp_path):
    view = export_views(_scene(tmp_path), 2.0)[0]
    assert tiny.model.config.model.antialias  # the run renders antialiased images
    fused = render_view(tiny, view, 0.0)
    centre = render(tiny, view.c2w, view.intrinsics, ("rgb",), antialias=False)["rgb"]
    np.testing.assert_array_equal(fused.rgb, np.round(np.clip(centre, 0.0, 1.0) * 255).astype(np.uint8))


def test_nothing_opaque_is_a_clear_error(tiny, tmp_path):
    out = tmp_path / "empty.ply"
    with pytest.raises(ExportError, match="opacity"):
        export_geometry(tiny, out, "mesh", scene=_scene(tmp_path, look_away=True))
    assert not out.exists()


def test_should_stop_ends_between_views_and_writes_nothing(tiny, tmp_path):
    out = tmp_path / "stopped.ply"
    asked, seen = [], []

    def should_stop() -> bool:
        asked.append(1)
        return len(asked) > 2

    result = export_geometry(tiny, out, "pointcloud", scene=_scene(tmp_path), min_opacity=0.01,
                             on_view=lambda done, total: seen.append((done, total)), should_stop=should_stop)
    assert result.stopped and result.views == 2 and result.points == 0
    assert seen == [(1, 10), (2, 10)]  # 2 training cameras, each with 4 offsets
    assert not out.exists() and not list(tmp_path.glob(".stopped.ply.*"))


def test_max_views_limits_the_views(tiny, tmp_path):
    seen = []
    result = export_geometry(tiny, tmp_path / "few.ply", "pointcloud", scene=_scene(tmp_path), min_opacity=0.01,
                             max_views=3, should_stop=lambda: len(seen) >= 2,
                             on_view=lambda done, total: seen.append(total))
    assert seen == [3, 3] and result.views == 2 and result.stopped


def test_default_voxel_is_the_box_over_512(tiny, tmp_path):
    result = export_geometry(tiny, tmp_path / "x.ply", "mesh", scene=_scene(tmp_path), should_stop=lambda: True)
    assert result.stopped and result.voxel_size == pytest.approx(4.0 / 512)  # tiny_run's box: [-2, 2]^3


def test_run_without_a_recorded_scene_needs_one(tiny, tmp_path):
    with pytest.raises(ExportError, match="scene"):
        export_geometry(tiny, tmp_path / "x.ply", "mesh")


def test_unknown_kind(tiny, tmp_path):
    with pytest.raises(ExportError, match="kind"):
        export_geometry(tiny, tmp_path / "x.ply", "voxels", scene=_scene(tmp_path))


@pytest.mark.parametrize("voxel", [0.0, -0.1, float("nan"), float("inf"), "0.1", True, 1e-6])
def test_bad_voxel_size(tiny, tmp_path, voxel):
    with pytest.raises(ExportError, match="voxel_size"):
        export_geometry(tiny, tmp_path / "x.ply", "mesh", scene=_scene(tmp_path), voxel_size=voxel)


@pytest.mark.parametrize(("option", "value"), [("min_opacity", 0.0), ("min_opacity", 1.5),
                                               ("min_opacity", float("nan")), ("max_views", 0)])
def test_bad_options(tiny, tmp_path, option, value):
    with pytest.raises(ExportError, match=option):
        export_geometry(tiny, tmp_path / "x.ply", "mesh", scene=_scene(tmp_path), **{option: value})


def test_output_must_be_ply(tiny, tmp_path):
    with pytest.raises(ExportError, match="ply"):
        export_geometry(tiny, tmp_path / "x.obj", "mesh", scene=_scene(tmp_path))


def test_export_error_is_an_engine_error():
    assert issubclass(ExportError, VoxNeRFError)


# --- CLI -------------------------------------------------------------------------------------------------------------


def test_cli_without_checkpoint(tmp_path, capsys):
    assert main(["export", str(tmp_path), "--mesh", str(tmp_path / "m.ply")]) == 2
    err = capsys.readouterr().err.strip()
    assert "checkpoint" in err and str(tmp_path) in err and len(err.splitlines()) == 1


def test_cli_without_scene(tmp_path, capsys):
    run = write_tiny_run(tmp_path / "tiny")
    assert main(["export", str(run), "--pointcloud", str(tmp_path / "p.ply")]) == 2
    err = capsys.readouterr().err.strip()
    assert "--scene" in err and str(run) in err and len(err.splitlines()) == 1


def test_cli_needs_an_output(tmp_path, capsys):
    assert main(["export", str(write_tiny_run(tmp_path / "tiny"))]) == 2
    assert "--mesh" in capsys.readouterr().err


def test_cli_bad_voxel_size(trained_small_room, tmp_path, capsys):
    assert main(["export", str(trained_small_room), "--mesh", str(tmp_path / "m.ply"), "--voxel-size", "nan"]) == 2
    assert "voxel_size" in capsys.readouterr().err
    assert not (tmp_path / "m.ply").exists()


def test_cli_prints_progress_and_a_summary(exported, capsys, trained_small_room, tmp_path):
    out = tmp_path / "coarse.ply"
    assert main(["export", str(trained_small_room), "--pointcloud", str(out), "--voxel-size", "0.1",
                 "--max-views", "5"]) == 0
    captured = capsys.readouterr()
    assert "pointcloud: 5/5 views" in captured.err
    assert captured.out.startswith(f"wrote {out}: ") and "voxel 0.1," in captured.out and "5 views" in captured.out
    assert out.is_file()


@pytest.mark.parametrize("max_views", [None, 1, 3, 9, 10, 11, 1000])
def test_the_torch_free_plan_counts_and_sizes_the_views_an_export_renders(tmp_path, max_views):
    """The service bounds an export's cost with :mod:`voxnerf.inference.export_plan` before queueing it: its
    count and size are those of the views the export renders."""
    camera = Intrinsics(500.0, 500.0, 320.0, 240.0, 640, 481)
    frames = [Frame(f"images/{i}.png", tmp_path / f"{i}.png", np.eye(4), camera) for i in range(2)]
    scene = Scene(tmp_path, frames, {"train": [0, 1]}, None, None, 0.001)
    views = export_views(scene, 1.0, max_views)
    assert len(views) == view_count(2, max_views)
    assert {(v.intrinsics.width, v.intrinsics.height) for v in views} == {view_size(640, 481)} == {(320, 240)}
