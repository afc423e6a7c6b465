"""Scene loading per docs/scene-format.md: splits, intrinsics, downscaling, and one clear error per problem."""

import json
import shutil
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from voxnerf.data.scene import SceneTransform, inspect_scene, load_scene, prior_file
from voxnerf.errors import SceneError


def _write_scene(root: Path, n: int = 10, w: int = 8, h: int = 6, **top) -> dict:
    (root / "images").mkdir(parents=True)
    frames = []
    for i in range(n):
        iio.imwrite(root / "images" / f"f{i:02d}.png", np.full((h, w, 3), i * 10, np.uint8))
        pose = np.eye(4)
        pose[0, 3] = i * 0.1
        frames.append({"file_path": f"images/f{i:02d}.png", "transform_matrix": pose.tolist()})
    meta = {"fl_x": 10.0, "fl_y": 10.0, "cx": w / 2, "cy": h / 2, "w": w, "h": h, "frames": frames, **top}
    (root / "transforms.json").write_text(json.dumps(meta))
    return meta


def _rewrite(root: Path, meta: dict) -> None:
    (root / "transforms.json").write_text(json.dumps(meta))


def test_default_split_holds_out_every_eighth(tmp_path):
    _write_scene(tmp_path, n=17)
    scene = load_scene(tmp_path)
    assert scene.splits["test"] == [0, 8, 16]
    assert len(scene.splits["train"]) == 14
    assert scene.images[3].shape == (6, 8, 3) and scene.images[3][0, 0, 0] == 30


def test_named_splits_and_eval_splits(tmp_path):
    meta = _write_scene(tmp_path, n=6)
    meta["test_filenames"] = ["images/f01.png"]
    meta["eval_splits"] = {"extrapolation": ["images/f05.png"]}
    _rewrite(tmp_path, meta)
    scene = load_scene(tmp_path)
    assert scene.splits["train"] == [0, 2, 3, 4]
    assert scene.eval_split_names == ["extrapolation", "test"]
    meta["train_filenames"] = ["images/f00.png"]
    _rewrite(tmp_path, meta)
    assert load_scene(tmp_path).splits["train"] == [0]


def test_only_frames_in_a_split_are_decoded(tmp_path):
    """A scan whose splits name a few of its frames decodes those and leaves the rest as None."""
    meta = _write_scene(tmp_path, n=6)
    meta["train_filenames"] = ["images/f00.png", "images/f02.png"]
    meta["test_filenames"] = ["images/f03.png"]
    meta["eval_splits"] = {"extrapolation": ["images/f05.png"]}
    _rewrite(tmp_path, meta)
    scene = load_scene(tmp_path)
    assert [i for i, image in enumerate(scene.images) if image is not None] == [0, 2, 3, 5]
    assert scene.images[5][0, 0, 0] == 50 and scene.depths[1] is None


def test_per_frame_intrinsics_and_downscale(tmp_path):
    meta = _write_scene(tmp_path, n=3, w=8, h=6)
    del meta["fl_x"]
    for f in meta["frames"]:
        f["fl_x"] = 20.0
    _rewrite(tmp_path, meta)
    scene = load_scene(tmp_path, downscale=2)
    intr = scene.intrinsics(0)
    assert (intr.width, intr.height, intr.fl_x, intr.cx) == (4, 3, 10.0, 2.0)
    assert scene.images[0].shape == (3, 4, 3)


@pytest.mark.parametrize(
    ("mutate", "key"),
    [
        (lambda m: m.pop("frames"), "frames"),
        (lambda m: m.pop("fl_x"), "frames[0].fl_x"),
        (lambda m: m.update(fl_y=-1), "frames[0].fl_y"),
        (lambda m: m.update(w=9), None),  # image size mismatch, reported on the image file
        (lambda m: m["frames"][1].update(file_path="images/missing.png"), "frames[1].file_path"),
        (lambda m: m["frames"][1].update(file_path="../outside.png"), "frames[1].file_path"),
        (lambda m: m["frames"][2].update(transform_matrix=[[1, 0, 0], [0, 1, 0]]), "frames[2].transform_matrix"),
        (lambda m: m["frames"][2]["transform_matrix"][0].__setitem__(0, float("nan")), "frames[2].transform_matrix"),
        (lambda m: m["frames"][2]["transform_matrix"][0].__setitem__(0, 3.0), "frames[2].transform_matrix"),
        (lambda m: m.update(test_filenames=["images/nope.png"]), "test_filenames"),
        (lambda m: m.update(eval_splits={"far": ["images/nope.png"]}), "eval_splits.far"),
        (lambda m: m.update(camera_model="FISHEYE"), "frames[0].camera_model"),
        (lambda m: m.update(camera_model="OPENCV", k1="0.1"), "frames[0].k1"),
        (lambda m: m.update(prior_file_path="prior.ply"), "prior_file_path"),
        (lambda m: m.update(prior_sigma=0), "prior_sigma"),
        (lambda m: m.update(depth_unit_scale_factor="mm"), "depth_unit_scale_factor"),
    ],
)
def test_each_problem_names_file_and_key(tmp_path, mutate, key):
    meta = _write_scene(tmp_path, n=4)
    meta = json.loads(json.dumps(meta))
    mutate(meta)
    _rewrite(tmp_path, meta)
    with pytest.raises(SceneError) as info:
        load_scene(tmp_path)
    err = info.value
    assert err.key == key if key else err.key == "size"
    assert "\n" not in str(err)
    if key:
        assert err.file.endswith("transforms.json") and key in str(err)


def test_invalid_json_and_missing_dir(tmp_path):
    with pytest.raises(SceneError, match="scene directory not found"):
        load_scene(tmp_path / "nope")
    tmp_path.joinpath("transforms.json").write_text("{not json")
    with pytest.raises(SceneError, match="invalid JSON"):
        load_scene(tmp_path)


def test_slightly_skewed_rotation_is_repaired_with_warning(tmp_path):
    meta = _write_scene(tmp_path, n=3)
    meta["frames"][1]["transform_matrix"][0][1] = 0.01
    _rewrite(tmp_path, meta)
    scene = load_scene(tmp_path)
    rot = scene.frames[1].c2w[:3, :3]
    np.testing.assert_allclose(rot.T @ rot, np.eye(3), atol=1e-9)
    assert any("re-orthonormalised" in w for w in scene.warnings)


def test_many_repaired_rotations_give_one_warning(tmp_path):
    meta = _write_scene(tmp_path, n=6)
    for i, frame in enumerate(meta["frames"]):
        frame["transform_matrix"][0][1] = 0.001 * (i + 1)
    _rewrite(tmp_path, meta)
    [warning] = [w for w in load_scene(tmp_path).warnings if "re-orthonormalised" in w]
    assert warning.startswith("frames[0].transform_matrix, frames[1].transform_matrix, frames[2].transform_matrix"
                              " and 3 more: rotation re-orthonormalised (max |R^T R - I| was 0.006")


def test_scene_transform_round_trip():
    pts = np.random.default_rng(0).uniform(-3, 7, size=(100, 3)) + 1e5
    tf = SceneTransform.fit(pts)
    norm = tf.points_to_normalized(pts)
    assert np.abs(norm).max() <= 0.95 + 1e-9
    np.testing.assert_allclose(norm / tf.scale + np.asarray(tf.center), pts, rtol=0, atol=1e-6)


def test_inspect_real_scene_summary():
    root = Path(__file__).resolve().parents[3] / "shared" / "data" / "redkitchen"
    if not root.is_dir():
        pytest.skip("shared redkitchen data absent")
    scene = load_scene(root, load_images=False)
    summary = scene.summary()
    assert summary["splits"]["train"] == 70
    assert summary["splits"]["interpolation"] == 35 and summary["splits"]["extrapolation"] == 20
    assert summary["image_size"] == [640, 480] and summary["depth"]
    assert summary["prior"]["sigma"] == 0.02


def test_inspect_scene_reports_prior(tmp_path):
    from voxnerf.synthetic import RoomSpec, make_room_scene

    make_room_scene(tmp_path / "s", RoomSpec(width=32, height=24, n_frames=80, gap_len=20, prior_max_points=20_000,
                                             supersample=1))
    summary = inspect_scene(tmp_path / "s")
    assert summary["prior"]["kind"] == "points" and summary["prior"]["sigma"] == 0.02
    shutil.rmtree(tmp_path / "s")


def _write_cloud(path: Path, n: int = 400) -> None:
    """A noisy plane of points as a PLY point cloud (no faces)."""
    import trimesh

    rng = np.random.default_rng(0)
    points = np.c_[rng.uniform(-1, 1, (n, 2)), rng.normal(0, 0.01, n)]
    trimesh.PointCloud(points).export(path)


def test_ply_file_path_is_the_prior_when_prior_file_path_is_absent(tmp_path):
    _write_scene(tmp_path, ply_file_path="sparse_pc.ply")
    _write_cloud(tmp_path / "sparse_pc.ply")
    scene = load_scene(tmp_path, load_images=False)
    assert scene.prior_path == (tmp_path / "sparse_pc.ply").resolve() and scene.prior_key == "ply_file_path"
    assert not scene.warnings
    summary = inspect_scene(tmp_path)
    assert summary["prior"]["file"] == "sparse_pc.ply" and summary["prior"]["source"] == "ply_file_path"
    assert summary["prior"]["sigma_estimated"] and 0 < summary["prior"]["sigma"] < 0.1


def test_prior_file_path_wins_over_ply_file_path(tmp_path):
    _write_scene(tmp_path, prior_file_path="prior_mesh.ply", ply_file_path="sparse_pc.ply")
    _write_cloud(tmp_path / "prior_mesh.ply")
    _write_cloud(tmp_path / "sparse_pc.ply")
    scene = load_scene(tmp_path, load_images=False)
    assert scene.prior_path.name == "prior_mesh.ply" and scene.prior_key == "prior_file_path"


def test_prior_file_is_the_prior_load_scene_takes(tmp_path):
    _write_scene(tmp_path, prior_file_path="prior_mesh.ply", ply_file_path="sparse_pc.ply")
    _write_cloud(tmp_path / "prior_mesh.ply")
    _write_cloud(tmp_path / "sparse_pc.ply")
    meta = json.loads((tmp_path / "transforms.json").read_text())
    assert prior_file(tmp_path, meta) == load_scene(tmp_path, load_images=False).prior_path
    del meta["prior_file_path"], meta["ply_file_path"]
    assert prior_file(tmp_path, meta) is None
    meta["ply_file_path"] = "../outside.ply"
    with pytest.raises(SceneError) as info:
        prior_file(tmp_path, meta)
    assert info.value.key == "ply_file_path"


@pytest.mark.parametrize(("value", "words"), [("missing.ply", "file not found"), ("../outside.ply", "outside"),
                                              (3, "non-empty relative path")])
def test_a_bad_ply_file_path_names_the_key(tmp_path, value, words):
    (tmp_path / "outside.ply").write_text("ply")
    _write_scene(tmp_path / "scene", ply_file_path=value)
    with pytest.raises(SceneError) as info:
        load_scene(tmp_path / "scene", load_images=False)
    assert info.value.key == "ply_file_path" and words in info.value.message


# ------------------------------------------------------------------------------------------------ lens distortion
# camera_model OPENCV / OPENCV_FISHEYE (nerfstudio), coefficients without camera_model (instant-ngp).


def _lens_scene(tmp_path, **top) -> dict:
    return json.loads(json.dumps(_write_scene(tmp_path, n=4, **top)))


def test_opencv_at_the_top_level_gives_every_frame_the_lens(tmp_path):
    _lens_scene(tmp_path, camera_model="OPENCV", k1=-0.1, k2=0.01, p1=0.001, p2=0.0)
    scene = load_scene(tmp_path, downscale=2)
    lens = scene.intrinsics(3).lens
    assert (lens.model, lens.k1, lens.k2, lens.k3, lens.p1) == ("OPENCV", -0.1, 0.01, 0.0, 0.001)
    assert scene.intrinsics(3).fl_x == 5.0  # downscaling scales the focal length, never the coefficients
    assert scene.summary()["camera_models"] == {"OPENCV (camera_model)": 4}


def test_a_frame_overrides_the_top_level_model_and_coefficients(tmp_path):
    meta = _lens_scene(tmp_path, camera_model="OPENCV", k1=-0.1)
    meta["frames"][1].update(k1=0.2)
    meta["frames"][2].update(camera_model="OPENCV_FISHEYE", k4=0.01)  # the top level's k1 is OPENCV's, not its own
    meta["frames"][3].update(camera_model="PINHOLE")
    _rewrite(tmp_path, meta)
    scene = load_scene(tmp_path)
    lenses = [f.intrinsics.lens for f in scene.frames]
    assert lenses[0].k1 == -0.1 and lenses[1].k1 == 0.2
    assert (lenses[2].model, lenses[2].k1, lenses[2].k4) == ("OPENCV_FISHEYE", 0.0, 0.01) and lenses[3] is None
    assert scene.summary()["camera_models"] == {
        "OPENCV (camera_model)": 2, "OPENCV_FISHEYE (camera_model)": 1, "PINHOLE (camera_model)": 1}


def test_instant_ngp_keys(tmp_path):
    """camera_angle_x instead of fl_x/fl_y, coefficients without camera_model, is_fisheye, aabb_scale, sharpness."""
    meta = _lens_scene(tmp_path, aabb_scale=16, k1=-0.05, p2=0.001, camera_angle_x=2 * np.arctan(0.4))
    del meta["fl_x"], meta["fl_y"]
    for f in meta["frames"]:
        f["sharpness"] = 42.0
    meta["frames"][1].update(is_fisheye=True, k1=0.1, k4=0.02, p2=0.0)
    meta["frames"][2].update(k1=0.0, p2=0.0)
    _rewrite(tmp_path, meta)
    scene = load_scene(tmp_path)
    intr = scene.frames[0].intrinsics
    assert intr.fl_x == pytest.approx(10.0) and intr.fl_y == pytest.approx(10.0)  # 0.5 * 8 / 0.4, square pixels
    assert (intr.lens.model, intr.lens.k1, intr.lens.p2) == ("OPENCV", -0.05, 0.001)
    fisheye = scene.frames[1].intrinsics.lens
    assert (fisheye.model, fisheye.k1, fisheye.k4) == ("OPENCV_FISHEYE", 0.1, 0.02)
    assert scene.frames[2].intrinsics.lens is None
    assert scene.summary()["camera_models"] == {
        "OPENCV (coefficients without camera_model, as instant-ngp)": 2,
        "OPENCV_FISHEYE (coefficients without camera_model, as instant-ngp)": 1,
        "PINHOLE (default)": 1,
    }


def test_camera_angles_give_each_axis_its_focal_length(tmp_path):
    meta = _lens_scene(tmp_path, camera_angle_x=2 * np.arctan(0.4), camera_angle_y=2 * np.arctan(0.5))
    del meta["fl_x"], meta["fl_y"]
    _rewrite(tmp_path, meta)
    intr = load_scene(tmp_path).frames[0].intrinsics
    assert (intr.fl_x, intr.fl_y, intr.lens) == (pytest.approx(10.0), pytest.approx(6.0), None)


@pytest.mark.parametrize(
    ("mutate", "key"),
    [
        (lambda m: m.update(camera_model="OPENCV", k1=float("nan")), "frames[0].k1"),
        (lambda m: m.update(camera_model="OPENCV", k2="0.1"), "frames[0].k2"),
        (lambda m: m.update(camera_model="OPENCV", p1=True), "frames[0].p1"),
        (lambda m: m.update(camera_model="OPENCV", k4=0.1), "frames[0].k4"),
        (lambda m: m.update(camera_model="OPENCV_FISHEYE", p2=0.1), "frames[0].p2"),
        (lambda m: m.update(camera_model="SIMPLE_RADIAL"), "frames[0].camera_model"),
        (lambda m: m.update(camera_model=7), "frames[0].camera_model"),
        (lambda m: m["frames"][2].update(camera_model="PINHOLE", k2=0.1), "frames[2].k2"),
        (lambda m: m.update(camera_model="PINHOLE", k3=0.1), "frames[0].k3"),
        (lambda m: m.update(k4=0.1), "frames[0].k4"),  # instant-ngp without is_fisheye: OPENCV, which has no k4
        (lambda m: m.update(is_fisheye="yes", k1=0.1), "frames[0].is_fisheye"),
        (lambda m: m.update(k1=[0.1]), "frames[0].k1"),
        (lambda m: (m.pop("fl_x"), m.pop("fl_y"), m.update(camera_angle_x=4.0)), "frames[0].camera_angle_x"),
    ],
)
def test_each_lens_problem_names_file_and_key(tmp_path, mutate, key):
    meta = _lens_scene(tmp_path)
    mutate(meta)
    _rewrite(tmp_path, meta)
    with pytest.raises(SceneError) as info:
        load_scene(tmp_path)
    err = info.value
    assert err.key == key and err.file.endswith("transforms.json") and key in str(err) and "\n" not in str(err)


# --- sensor depth: validity, registration to the image, training frames only -------------------------------


def _depth_scene(tmp_path, depth_size=(8, 6), depth_mm=None, **top) -> dict:
    """A 4-frame scene (frame 0 held out) whose frames carry 16-bit depth maps of ``depth_size`` (w, h)."""
    meta = _write_scene(tmp_path, n=4, w=8, h=6, depth_unit_scale_factor=0.001, **top)
    (tmp_path / "depth").mkdir()
    dw, dh = depth_size
    for i, frame in enumerate(meta["frames"]):
        mm = depth_mm if depth_mm is not None else (1000 + 10 * i + np.arange(dw)[None] + 100 * np.arange(dh)[:, None])
        iio.imwrite(tmp_path / "depth" / f"d{i}.png", np.asarray(mm, np.uint16) * np.ones((dh, dw), np.uint16))
        frame["depth_file_path"] = f"depth/d{i}.png"
    meta["test_filenames"] = ["images/f00.png"]
    _rewrite(tmp_path, meta)
    return meta


def test_depth_is_read_for_training_frames_only(tmp_path):
    _depth_scene(tmp_path)
    scene = load_scene(tmp_path)
    assert scene.depths[0] is None  # held out: never read for training
    assert [i for i, d in enumerate(scene.depths) if d is not None] == scene.train_indices == [1, 2, 3]
    assert scene.depths[1][0, 0] == pytest.approx(1.010) and scene.depths[1].dtype == np.float32
    assert scene.summary()["depth_frames"] == {"all": 4, "train": 3}


def test_zero_saturation_and_depth_max_are_no_measurement(tmp_path):
    meta = _depth_scene(tmp_path, depth_mm=np.array([[0, 65535, 1000, 5000, 1500, 1500, 1500, 1500]] * 6))
    meta["depth_max"] = 4.0
    _rewrite(tmp_path, meta)
    depth = load_scene(tmp_path).depths[1]
    assert np.isnan(depth[:, :2]).all() and np.isnan(depth[:, 3]).all()  # 0, 65535, and 5 m beyond 4 m
    assert depth[0, 2] == pytest.approx(1.0) and depth[0, 4] == pytest.approx(1.5)


def test_a_smaller_depth_map_with_the_same_aspect_is_scaled_to_the_image(tmp_path):
    _depth_scene(tmp_path, depth_size=(4, 3))  # 7-Scenes / ScanNet-like: same field of view, fewer pixels
    depth = load_scene(tmp_path).depths[1]
    assert depth.shape == (6, 8)
    # each image pixel takes the depth pixel its centre falls in: column c of the image -> c // 2 of the map
    expected = 1.010 + np.arange(4)[None].repeat(2, 1) * 0.001 + 0.1 * np.arange(3)[:, None].repeat(2, 0)
    np.testing.assert_allclose(depth, expected, atol=1e-6)


def test_depth_intrinsics_register_another_camera(tmp_path):
    # The depth camera sees twice the image's field of view: the image covers its middle half.
    meta = _depth_scene(tmp_path, depth_size=(8, 6))
    meta["depth_intrinsics"] = {"fl_x": 5.0, "fl_y": 5.0, "cx": 4.0, "cy": 3.0, "w": 8, "h": 6}
    _rewrite(tmp_path, meta)
    depth = load_scene(tmp_path).depths[1]
    cols = np.floor(5.0 * (np.arange(8) + 0.5 - 4.0) / 10.0 + 4.0).astype(int)
    rows = np.floor(5.0 * (np.arange(6) + 0.5 - 3.0) / 10.0 + 3.0).astype(int)
    np.testing.assert_allclose(depth, (1010 + cols[None] + 100 * rows[:, None]) / 1000, atol=1e-6)


def test_depth_registration_at_a_downscale_keeps_the_image_grid(tmp_path):
    _depth_scene(tmp_path, depth_size=(16, 12))
    scene = load_scene(tmp_path, downscale=2)
    assert scene.depths[1].shape == scene.images[1].shape[:2] == (3, 4)
    assert np.isfinite(scene.depths[1]).all()


@pytest.mark.parametrize(("size", "top", "words"), [
    ((8, 8), {}, "a different aspect ratio needs the depth camera's depth_intrinsics"),
    ((8, 6), {"depth_intrinsics": {"fl_x": 5.0, "fl_y": 5.0, "cx": 4.0, "cy": 3.0, "w": 16, "h": 12}},
     "but depth_intrinsics say w=16 h=12"),
])
def test_a_depth_map_of_the_wrong_size_names_the_file(tmp_path, size, top, words):
    _depth_scene(tmp_path, depth_size=size, **top)
    with pytest.raises(SceneError, match=words) as info:
        load_scene(tmp_path)
    assert info.value.file.endswith("d1.png") and info.value.key == "size"
    with pytest.raises(SceneError, match=words):  # the upload check reads every frame's depth, held-out ones too
        inspect_scene(tmp_path)


@pytest.mark.parametrize(("mutate", "key"), [
    (lambda m: m.update(depth_intrinsics=[1, 2]), "depth_intrinsics"),
    (lambda m: m.update(depth_intrinsics={"fl_x": 5.0}), "depth_intrinsics.cx"),
    (lambda m: m["frames"][2].update(depth_intrinsics={"fl_x": -1, "fl_y": 5, "cx": 1, "cy": 1, "w": 8, "h": 6}),
     "frames[2].depth_intrinsics.fl_x"),
    (lambda m: m.update(depth_max=0), "depth_max"),
    (lambda m: m.update(depth_max="far"), "depth_max"),
    (lambda m: m["frames"][1].update(depth_file_path="depth/missing.png"), "frames[1].depth_file_path"),
])
def test_each_depth_problem_names_file_and_key(tmp_path, mutate, key):
    meta = _depth_scene(tmp_path)
    mutate(meta)
    _rewrite(tmp_path, meta)
    with pytest.raises(SceneError) as info:
        load_scene(tmp_path)
    assert info.value.file.endswith("transforms.json") and info.value.key == key
