"""Scenes whose images differ in size: the synthetic room with portrait frames beside landscape ones, and a COLMAP
model of per-image OPENCV cameras of 24x16 beside 24x17 (the difference of COLMAP's undistorted crops to 1000x657
and 1000x659, scaled down) imported with ``import_colmap``. Each trains, evaluates every view at its own size,
renders ``--frame`` of each size, gives the viewer its cameras (``GET /jobs/{id}/cameras``) and exports geometry.
The old code stopped each run with ``ValueError: training images differ in size``."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pycolmap
import pytest
import trimesh
from fastapi.testclient import TestClient
from service_fixtures import start_service, zip_scene
from synthetic_fixtures import MICRO, make_micro_scene, micro_config

from app.core import jobstore
from app.core.settings import Settings
from app.main import create_app
from voxnerf.cameras.rules import Lens
from voxnerf.cli import main
from voxnerf.data.importers import import_colmap
from voxnerf.data.scene import load_scene
from voxnerf.inference.export import box_extent, export_geometry, export_views
from voxnerf.inference.render import load_model
from voxnerf.synthetic import build_room, render_view
from voxnerf.synthetic.writer import DEPTH_UNIT_SCALE
from voxnerf.training.run import train

PORTRAIT = (18, 24)  # w, h: the room's 24x18 landscape frames turned
FLIP = np.diag([1.0, -1.0, -1.0, 1.0])  # OpenGL <-> OpenCV camera axes


def _write_view(root: Path, frame: dict, geom, fl: float, cx: float, cy: float, w: int, h: int,
                lens: Lens | None = None, depth: bool = True) -> None:
    """Render the room from ``frame``'s pose into its image (and depth) file at ``w`` x ``h``."""
    rgb, z = render_view(geom, np.asarray(frame["transform_matrix"]), fl, cx, cy, w, h, MICRO.supersample, lens)
    iio.imwrite(root / frame["file_path"], np.round(rgb * 255).astype(np.uint8))
    if depth:
        mm = np.clip(np.round(z / DEPTH_UNIT_SCALE), 0, 65535).astype(np.uint16)
        iio.imwrite(root / frame["depth_file_path"], mm)


@pytest.fixture(scope="module")
def room_scene(tmp_path_factory) -> Path:
    """The micro room, every other pair of frames rendered again as a portrait 18x24 view with its own intrinsics."""
    root = make_micro_scene(tmp_path_factory, "mixed")
    meta = json.loads((root / "transforms.json").read_text())
    geom = build_room(MICRO.seed, MICRO.room_style())
    w, h = PORTRAIT
    for k, frame in enumerate(meta["frames"]):
        if (k // 2) % 2:  # the frames alternate training and held-out: both kinds get both sizes
            _write_view(root, frame, geom, meta["fl_x"], w / 2, h / 2, w, h)
            frame.update(w=w, h=h, cx=w / 2, cy=h / 2)
    (root / "transforms.json").write_text(json.dumps(meta))
    return root


def _colmap_model(src: Path, room: Path) -> None:
    """``src/sparse/0`` (text) and ``src/images``: the micro room's frames through per-image OPENCV cameras of
    24x16 and 24x17 pixels (focal lengths, principal points and k1 differing image to image) and 400 of its
    prior's points, each observed by the views it projects into."""
    meta = json.loads((room / "transforms.json").read_text())
    geom = build_room(MICRO.seed, MICRO.room_style())
    (src / "images").mkdir(parents=True)
    model = src / "sparse" / "0"
    model.mkdir(parents=True)
    cameras, images, views = [], [], []
    for i, frame in enumerate(meta["frames"]):
        w, h = 24, 16 + (i + i // 8) % 2  # held out (every 8th frame) and training frames each of both sizes
        fl, cx, cy = meta["fl_x"] * (1 + 0.01 * (i % 3)), w / 2 + 0.3 * (i % 2), h / 2 - 0.2 * (i % 3)
        lens = Lens("OPENCV", k1=-0.05 - 0.01 * (i % 4), k2=0.01, p1=0.0, p2=0.0)
        name = f"images/view{i:02d}.png"
        _write_view(src, {**frame, "file_path": name}, geom, fl, cx, cy, w, h, lens, depth=False)
        cameras.append(f"{i + 1} OPENCV {w} {h} {fl!r} {fl!r} {cx!r} {cy!r} {lens.k1!r} {lens.k2!r} 0.0 0.0")
        w2c = np.linalg.inv(np.asarray(frame["transform_matrix"]) @ FLIP)
        views.append((w2c, fl, cx, cy, w, h))
        qx, qy, qz, qw = (float(q) for q in pycolmap.Rotation3d(w2c[:3, :3]).quat)
        images.append([f"{i + 1} {qw!r} {qx!r} {qy!r} {qz!r} {' '.join(repr(float(t)) for t in w2c[:3, 3])} "
                       f"{i + 1} view{i:02d}.png", []])
    vertices = np.asarray(trimesh.load(room / "prior.ply", process=False).vertices, dtype=np.float64)
    points = vertices[np.random.default_rng(0).choice(len(vertices), 400, replace=False)]
    lines = ["# POINT3D_ID X Y Z R G B ERROR TRACK[]"]
    for pid, xyz in enumerate(points):
        track = []
        for i, (w2c, fl, cx, cy, w, h) in enumerate(views):
            cam = w2c[:3, :3] @ xyz + w2c[:3, 3]
            u, v = float(fl * cam[0] / max(cam[2], 1e-9) + cx), float(fl * cam[1] / max(cam[2], 1e-9) + cy)
            if cam[2] > 0.1 and 0 <= u < w and 0 <= v < h and len(track) < 3:
                track.append(f"{i + 1} {len(images[i][1])}")
                images[i][1].append(f"{u!r} {v!r} {pid + 1}")
        if track:
            x, y, z = (repr(float(c)) for c in xyz)
            lines.append(f"{pid + 1} {x} {y} {z} 128 128 128 0.5 {' '.join(track)}")
    (model / "cameras.txt").write_text("# CAMERA_ID MODEL W H PARAMS\n" + "\n".join(cameras) + "\n")
    (model / "images.txt").write_text("".join(f"{head}\n{' '.join(obs)}\n" for head, obs in images))
    (model / "points3D.txt").write_text("\n".join(lines) + "\n")


@pytest.fixture(scope="module")
def colmap_scene(tmp_path_factory) -> Path:
    src = tmp_path_factory.mktemp("colmap") / "project"
    _colmap_model(src, make_micro_scene(tmp_path_factory, "colmap-room"))
    out = src.parent / "scene"
    import_colmap(src, out)
    return out


@pytest.fixture(scope="module", params=["room", "colmap"])
def trained(request, tmp_path_factory) -> tuple[Path, Path, dict]:
    scene = request.getfixturevalue(f"{request.param}_scene")
    run = tmp_path_factory.mktemp(f"run-{request.param}")
    # patches and prior rays (off by default) so that every sampler of training pixels runs on both sizes
    cfg = micro_config(smooth_patches=2, patch_size=4, prior_rays=16, prior_ray_colour=0.1)
    report = train(scene, run, cfg, progress_bar=False)
    return scene, run, report.to_json_dict()


def _sizes(scene: Path) -> dict[str, tuple[int, int]]:
    """file_path -> (width, height) of every frame."""
    return {f.file_path: (f.intrinsics.width, f.intrinsics.height) for f in load_scene(scene, load_images=False).frames}


def test_the_scenes_mix_sizes_in_training_and_held_out_frames(room_scene, colmap_scene):
    for scene in (room_scene, colmap_scene):
        loaded = load_scene(scene, load_images=False)
        train_sizes = {(loaded.frames[i].intrinsics.width, loaded.frames[i].intrinsics.height)
                       for i in loaded.train_indices}
        test_sizes = {(loaded.frames[i].intrinsics.width, loaded.frames[i].intrinsics.height)
                      for i in loaded.splits["test"]}
        assert len(train_sizes) == 2 and len(test_sizes) == 2, (scene, train_sizes, test_sizes)
    assert len({f.intrinsics for f in load_scene(colmap_scene, load_images=False).frames}) > 2  # per-image cameras
    assert load_scene(room_scene, load_images=False).summary()["image_sizes"] == {"24x18": 10, "18x24": 9}


def test_a_scene_of_mixed_sizes_trains_and_evaluates_every_view_at_its_own_size(trained):
    scene, run, report = trained
    assert report["status"] == "succeeded" and report["iteration"] == 3, report.get("error")
    sizes = _sizes(scene)
    loaded = load_scene(scene, load_images=False)
    for split, metrics in report["metrics"].items():
        assert all(math.isfinite(v["psnr"]) for v in metrics["views"])
        for i in loaded.splits[split]:
            name = Path(loaded.frames[i].file_path).stem
            rendered = iio.imread(run / "eval" / split / f"{name}.png")
            assert rendered.shape[1::-1] == sizes[loaded.frames[i].file_path]
    ran = {s["name"]: s["ran"] for s in report["stages"]}
    assert ran["octree"] and ran["pseudo_depth"] and ran["depth_target"] and ran["first_hit_cache"]
    assert ran["prior_rays"]
    why = next(s["why"] for s in report["stages"] if s["name"] == "load_scene")
    assert "training images of 2 sizes" in why and "padding" in why, why


def test_voxnerf_eval_scores_the_held_out_views_of_both_sizes(trained, tmp_path):
    scene, run, _ = trained
    assert main(["eval", str(run), "--device", "cpu", "--split", "test", "--json", str(tmp_path / "m.json")]) == 0
    metrics = json.loads((tmp_path / "m.json").read_text())
    loaded = load_scene(scene, load_images=False)
    held_out = [loaded.frames[i].file_path for i in loaded.splits["test"]]
    assert len(metrics["views"]) == len(held_out) and all(math.isfinite(v["psnr"]) for v in metrics["views"])
    assert len({_sizes(scene)[path] for path in held_out}) == 2


def test_render_frame_gives_each_frame_at_its_own_size(trained, tmp_path):
    scene, run, _ = trained
    one_per_size = {size: path for path, size in _sizes(scene).items()}
    assert len(one_per_size) == 2
    for size, path in one_per_size.items():
        out = tmp_path / f"{Path(path).stem}.png"
        assert main(["render", str(run), "--device", "cpu", "--frame", path, "--scene", str(scene),
                     "--out", str(out)]) == 0
        assert iio.imread(out).shape[1::-1] == size


def test_an_upload_of_mixed_sizes_is_stored_with_its_sizes(room_scene, tmp_path):
    """``POST /scenes`` of the room as a zip, through a real API process (validated out of process as always)."""
    service = start_service(tmp_path / "service", token="sizes-token", workers=False)
    try:
        with service.client() as client:
            response = client.post("/scenes", files={"file": ("mixed.zip", zip_scene(room_scene), "application/zip")})
    finally:
        service.stop()
    assert response.status_code == 201, response.text
    assert response.json()["summary"]["image_sizes"] == {"24x18": 10, "18x24": 9}


@pytest.mark.parametrize("name", ["room", "colmap"])
def test_the_viewers_cameras_carry_each_frames_size(request, tmp_path, name):
    """``GET /jobs/{id}/cameras`` of an in-process app (a queued job: the endpoint needs no worker)."""
    scene = request.getfixturevalue(f"{name}_scene")
    settings = Settings(_env_file=None, data_dir=tmp_path / "data", device="cpu", api_token="sizes-token",
                        sweep_interval_s=3600)
    with TestClient(create_app(settings), headers={"Authorization": "Bearer sizes-token"}) as client:
        scene_id = jobstore.new_id()
        shutil.copytree(scene, settings.scenes_dir / scene_id)
        jobstore.add_scene(settings, scene_id, name, {"frames": 19}, 1)
        job = jobstore.create_job(settings, scene_id, {"max_iters": 1}).id
        body = client.get(f"/jobs/{job}/cameras").json()
    loaded = load_scene(scene, load_images=False)
    sizes = _sizes(scene)
    assert {frame["name"]: (frame["width"], frame["height"]) for frame in body["frames"]} == sizes
    assert len(set(sizes.values())) == 2
    for frame, source in zip(body["frames"], loaded.frames, strict=True):
        undistorted = source.intrinsics.undistorted()
        assert (frame["fl_x"], frame["cx"], frame["cy"]) == pytest.approx(
            (undistorted.fl_x, undistorted.cx, undistorted.cy))


def test_export_renders_the_training_cameras_of_both_sizes(trained, tmp_path):
    scene, run, _ = trained
    model = load_model(run, "cpu")
    views = export_views(load_scene(scene, load_images=False), box_extent(model))
    assert len({(v.intrinsics.width, v.intrinsics.height) for v in views}) == 2
    result = export_geometry(model, tmp_path / "points.ply", "pointcloud", min_opacity=0.01, voxel_size=0.2)
    assert (tmp_path / "points.ply").is_file() and result.views == len(views)
