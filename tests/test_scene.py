"""Scene loading per SCENE_FORMAT.md: splits, intrinsics, downscaling, and one clear error per problem."""

import json
import shutil
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from voxnerf.errors import SceneError
from voxnerf.scene import SceneTransform, inspect_scene, load_scene


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
        (lambda m: m.update(camera_model="OPENCV", k1=0.1), "frames[0].k1"),
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
    root = Path(__file__).resolve().parents[2] / "shared" / "data" / "redkitchen"
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


@pytest.mark.parametrize(("value", "words"), [("missing.ply", "file not found"), ("../outside.ply", "outside"),
                                              (3, "non-empty relative path")])
def test_a_bad_ply_file_path_names_the_key(tmp_path, value, words):
    (tmp_path / "outside.ply").write_text("ply")
    _write_scene(tmp_path / "scene", ply_file_path=value)
    with pytest.raises(SceneError) as info:
        load_scene(tmp_path / "scene", load_images=False)
    assert info.value.key == "ply_file_path" and words in info.value.message
