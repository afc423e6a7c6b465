"""Camera paths: nerfstudio's camera-path JSON (parse, limits, round trip, dataparser frame), interpolation and
orbits. numpy only, like the module."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from voxnerf.cameras.paths import (
    MAX_FRAMES,
    CameraPath,
    CameraPathError,
    check_frame_count,
    from_dataparser_frame,
    interpolate_path,
    look_at,
    orbit_path,
    parse_nerfstudio,
    read_nerfstudio,
    rotation_angle,
    slerp,
    to_dataparser_frame,
)
from voxnerf.cameras.rules import Intrinsics

CAMERA = Intrinsics(fl_x=40.0, fl_y=40.0, cx=16.0, cy=12.0, width=32, height=24)


def _rotation(axis, degrees: float) -> np.ndarray:
    """Rodrigues' rotation [3, 3] about ``axis`` by ``degrees``."""
    k = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    skew = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    a = math.radians(degrees)
    return np.eye(3) + math.sin(a) * skew + (1 - math.cos(a)) * skew @ skew


def _pose(position, axis=(0, 0, 1), degrees: float = 0.0) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = _rotation(axis, degrees)
    pose[:3, 3] = position
    return pose


def _scene_poses(n: int = 5) -> np.ndarray:
    """A walk along x turning about z and tilting: distinct positions and rotations."""
    return np.stack([_pose([0.4 * i, 0.1 * i * i, 1.5], (0.2, 0.1, 1.0), 15.0 * i) for i in range(n)])


def _doc(poses: np.ndarray, fov: float = 60.0, width: int = 32, height: int = 24, fps: float = 24.0) -> dict:
    """A camera path as nerfstudio's viewer writes it (fps x seconds = frames)."""
    return {
        "keyframes": [], "camera_type": "perspective", "render_height": height, "render_width": width,
        "fps": fps, "seconds": len(poses) / fps, "is_cycle": False, "smoothness_value": 0.5,
        "camera_path": [{"camera_to_world": p.reshape(-1).tolist(), "fov": fov, "aspect": width / height}
                        for p in poses],
    }


# ------------------------------------------------------------------------------------------------ parsing


def test_module_does_not_import_torch():
    code = "import sys, voxnerf.cameras.paths; assert 'torch' not in sys.modules, 'torch imported'"
    subprocess.run([sys.executable, "-c", code], check=True)


def test_viewer_path_gives_poses_intrinsics_and_fps():
    poses = _scene_poses()
    path = parse_nerfstudio(_doc(poses, fov=60.0, width=32, height=24, fps=24.0))
    assert len(path) == 5 and path.fps == 24.0 and path.size == (32, 24)
    np.testing.assert_allclose(path.poses, poses, atol=1e-12)
    focal = 12.0 / math.tan(math.radians(30.0))  # 0.5 H / tan(fov / 2)
    for camera in path.intrinsics:
        assert camera.fl_x == pytest.approx(focal) and camera.fl_y == pytest.approx(focal)
        assert (camera.cx, camera.cy, camera.width, camera.height, camera.lens) == (16.0, 12.0, 32, 24, None)


def test_per_frame_fov_and_nested_matrix():
    doc = _doc(_scene_poses(2))
    doc["camera_path"][1]["fov"] = 90.0
    doc["camera_path"][1]["camera_to_world"] = _scene_poses(2)[1].tolist()  # 4 rows of 4, as view(4, 4) reads
    path = parse_nerfstudio(doc)
    assert path.intrinsics[1].fl_y == pytest.approx(12.0)
    np.testing.assert_allclose(path.poses[1], _scene_poses(2)[1], atol=1e-12)


def test_aspect_does_not_change_the_image():
    """nerfstudio renders render_width x render_height whatever aspect says (its Blender add-on writes 1)."""
    doc = _doc(_scene_poses(2))
    for entry in doc["camera_path"]:
        entry["aspect"] = 1
    assert parse_nerfstudio(doc).size == (32, 24)


def test_fps_from_seconds_alone_and_seconds_within_one_frame():
    doc = _doc(_scene_poses(4))
    del doc["fps"]
    doc["seconds"] = 2.0
    assert parse_nerfstudio(doc).fps == 2.0  # 4 frames in 2 s
    doc = _doc(_scene_poses(4), fps=30.0)
    doc["seconds"] = 4.9 / 30  # the viewer writes int(fps * seconds) frames: 4.9 -> 4
    assert parse_nerfstudio(doc).fps == 30.0


def _mutated(key_path, value):
    doc = _doc(_scene_poses(3))
    target = doc
    for key in key_path[:-1]:
        target = target[key]
    if value is _DELETE:
        del target[key_path[-1]]
    else:
        target[key_path[-1]] = value
    return doc


_DELETE = object()


@pytest.mark.parametrize(
    ("key_path", "value", "named", "words"),
    [
        (["render_width"], _DELETE, "render_width", "missing"),
        (["render_height"], 0, "render_height", "positive integer"),
        (["render_width"], 12.5, "render_width", "positive integer"),
        (["render_width"], True, "render_width", "positive integer"),
        (["fps"], float("nan"), "fps", "frames per second"),
        (["fps"], -1, "fps", "frames per second"),
        (["seconds"], 10.0, "seconds", "but camera_path has 3"),
        (["seconds"], "1", "seconds", "positive finite"),
        (["camera_type"], "fisheye", "camera_type", "perspective"),
        (["camera_path"], _DELETE, "camera_path", "missing"),
        (["camera_path"], {}, "camera_path", "list"),
        (["camera_path"], [], "camera_path", "from 1 to"),
        (["camera_path", 1], "x", "camera_path[1]", "object"),
        (["camera_path", 2, "camera_to_world"], _DELETE, "camera_path[2].camera_to_world", "missing"),
        (["camera_path", 2, "camera_to_world"], [1.0] * 15, "camera_path[2].camera_to_world", "16 numbers"),
        (["camera_path", 2, "camera_to_world"], [float("nan")] + [0.0] * 15, "camera_path[2].camera_to_world",
         "NaN"),
        (["camera_path", 2, "camera_to_world"], [2.0, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1],
         "camera_path[2].camera_to_world", "orthonormal"),
        (["camera_path", 2, "camera_to_world"], [1.0, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, True],
         "camera_path[2].camera_to_world", "numbers only"),
        (["camera_path", 0, "fov"], _DELETE, "camera_path[0].fov", "missing"),
        (["camera_path", 0, "fov"], 180, "camera_path[0].fov", "(0, 180)"),
        (["camera_path", 0, "fov"], float("inf"), "camera_path[0].fov", "(0, 180)"),
        (["camera_path", 0, "aspect"], -1, "camera_path[0].aspect", "positive"),
        (["camera_path", 1, "fl_x"], 0, "camera_path[1].fl_x", "positive"),
        (["camera_path", 1, "cy"], "a", "camera_path[1].cy", "finite"),
    ],
)
def test_each_malformed_key_is_named(key_path, value, named, words):
    with pytest.raises(CameraPathError) as err:
        parse_nerfstudio(_mutated(key_path, value))
    assert err.value.key == named and words in err.value.message
    assert str(err.value).startswith(f"{named}: ") and "\n" not in str(err.value)


def test_not_an_object():
    with pytest.raises(CameraPathError, match="JSON object"):
        parse_nerfstudio([1, 2])


def test_limits_on_frames_and_pixels():
    doc = _doc(_scene_poses(3))
    parse_nerfstudio(doc, max_frames=3, max_pixels=32 * 24)
    with pytest.raises(CameraPathError, match=r"^camera_path: .*from 1 to 2, got 3"):
        parse_nerfstudio(doc, max_frames=2)
    with pytest.raises(CameraPathError, match=r"^render_width, render_height: 32x24 exceeds the limit of 700"):
        parse_nerfstudio(doc, max_pixels=700)


@pytest.mark.parametrize("n", [0, -3, MAX_FRAMES + 1, 2.0, True, None])
def test_frame_counts_refused(n):
    with pytest.raises(CameraPathError, match=r"^frames: must be a whole number of frames from 1 to 10000"):
        check_frame_count(n, MAX_FRAMES)


def test_read_names_the_file(tmp_path):
    good = tmp_path / "path.json"
    good.write_text(json.dumps(_doc(_scene_poses(2))))
    assert len(read_nerfstudio(good, max_frames=2)) == 2
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(_mutated(["camera_path", 1, "fov"], 0)))
    with pytest.raises(CameraPathError, match=rf"^{bad}: camera_path\[1\].fov: must be a number in \(0, 180\)"):
        read_nerfstudio(bad)
    (tmp_path / "broken.json").write_text("{")
    with pytest.raises(CameraPathError, match=r"broken.json: cannot read JSON"):
        read_nerfstudio(tmp_path / "broken.json")
    with pytest.raises(CameraPathError, match=r"^" + str(tmp_path / "absent.json")):
        read_nerfstudio(tmp_path / "absent.json")


# ------------------------------------------------------------------------------------------------ round trips


def test_to_nerfstudio_round_trips():
    path = CameraPath(_scene_poses(), [CAMERA] * 5, fps=12.5)
    doc = json.loads(json.dumps(path.to_nerfstudio()))
    assert doc["seconds"] * doc["fps"] == pytest.approx(5) and doc["render_width"] == 32
    assert "fl_x" not in doc["camera_path"][0]  # fov describes this camera
    back = parse_nerfstudio(doc)
    np.testing.assert_array_equal(back.poses, path.poses)
    assert back.fps == 12.5
    for a, b in zip(back.intrinsics, path.intrinsics, strict=True):
        np.testing.assert_allclose([a.fl_x, a.fl_y, a.cx, a.cy], [b.fl_x, b.fl_y, b.cx, b.cy], rtol=1e-12)


def test_a_camera_fov_cannot_describe_keeps_its_intrinsics():
    camera = Intrinsics(fl_x=41.0, fl_y=39.0, cx=15.0, cy=13.0, width=32, height=24)
    doc = json.loads(json.dumps(CameraPath(_scene_poses(2), [camera] * 2).to_nerfstudio()))
    assert doc["camera_path"][0]["fl_x"] == 41.0
    assert parse_nerfstudio(doc).intrinsics[0] == camera


def _dataparser(poses: np.ndarray) -> tuple[dict, np.ndarray, float]:
    """A transform and scale as nerfstudio's dataparser computes them (auto_orient_and_center_poses 'up':
    rotate the mean up to +z, centre the positions; scale so the largest |coordinate| is 1)."""
    rot = _rotation((0.3, -0.5, 0.8), 40.0)
    transform = np.concatenate([rot, (-rot @ poses[:, :3, 3].mean(axis=0))[:, None]], axis=1)  # 3x4
    homogeneous = np.vstack([transform, [0, 0, 0, 1]])
    oriented = homogeneous @ poses
    scale = 1.0 / float(np.abs(oriented[:, :3, 3]).max())
    return {"transform": transform.tolist(), "scale": scale}, homogeneous, scale


def test_viewer_path_maps_back_to_scene_units_with_dataparser_transforms(tmp_path):
    scene = _scene_poses(6)
    scene[:, :3, 3] += [3.0, -2.0, 0.5]  # far from the origin, like a real scan
    transforms, homogeneous, scale = _dataparser(scene)
    # the dataparser's mapping, written out as nerfstudio does it: c2w' = T @ c2w, then positions *= scale
    viewer = np.stack([homogeneous @ pose for pose in scene])
    viewer[:, :3, 3] *= scale
    np.testing.assert_allclose(to_dataparser_frame(scene, homogeneous, scale), viewer, atol=1e-12)
    (tmp_path / "camera_path.json").write_text(json.dumps(_doc(viewer)))
    (tmp_path / "dataparser_transforms.json").write_text(json.dumps(transforms, indent=4))
    path = read_nerfstudio(tmp_path / "camera_path.json",
                           dataparser_transforms=tmp_path / "dataparser_transforms.json")
    np.testing.assert_allclose(path.poses, scene, atol=1e-9)
    np.testing.assert_allclose(from_dataparser_frame(viewer, homogeneous, scale), scene, atol=1e-9)
    # without the transforms the poses are the viewer's, not the scene's
    assert np.abs(read_nerfstudio(tmp_path / "camera_path.json").poses - scene).max() > 0.1


@pytest.mark.parametrize(
    ("transforms", "key"),
    [
        ({"scale": 1.0}, "transform"),
        ({"transform": np.eye(4)[:3].tolist()}, "scale"),
        ({"transform": np.eye(4)[:3].tolist(), "scale": 0}, "scale"),
        ({"transform": np.eye(4).tolist(), "scale": 1}, "transform"),
        ({"transform": (np.eye(4)[:3] * 2).tolist(), "scale": 1}, "transform"),
        ({"transform": [[1, 0, 0, float("nan")], [0, 1, 0, 0], [0, 0, 1, 0]], "scale": 1}, "transform"),
    ],
)
def test_bad_dataparser_transforms_name_file_and_key(tmp_path, transforms, key):
    (tmp_path / "path.json").write_text(json.dumps(_doc(_scene_poses(2))))
    (tmp_path / "dp.json").write_text(json.dumps(transforms))
    with pytest.raises(CameraPathError, match=rf"^{tmp_path / 'dp.json'}: {key}: "):
        read_nerfstudio(tmp_path / "path.json", dataparser_transforms=tmp_path / "dp.json")


# ------------------------------------------------------------------------------------------------ paths


def _orthonormal(poses: np.ndarray) -> None:
    rot = poses[:, :3, :3]
    np.testing.assert_allclose(np.swapaxes(rot, 1, 2) @ rot, np.broadcast_to(np.eye(3), rot.shape), atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-9)


def test_interpolation_passes_through_the_cameras_at_key_frames():
    keys = _scene_poses(5)
    path = interpolate_path(keys, CAMERA, n_frames=41, fps=20.0)
    assert len(path) == 41 and path.fps == 20.0 and path.intrinsics[0] == CAMERA
    _orthonormal(path.poses)
    index = [int(np.argmin(np.abs(path.poses - key).sum(axis=(1, 2)))) for key in keys]
    assert index[0] == 0 and index[-1] == 40 and index == sorted(index)
    np.testing.assert_allclose(path.poses[index], keys, atol=1e-12)
    # smooth: no step much longer than the average one
    steps = np.linalg.norm(np.diff(path.poses[:, :3, 3], axis=0), axis=1)
    assert steps.max() < 3 * steps.mean()


def test_slerp_midpoint_is_half_the_rotation():
    a, b = _pose([0, 0, 0]), _pose([2, 0, 0], (1, 1, 0), 80.0)
    path = interpolate_path(np.stack([a, b]), CAMERA, n_frames=3)
    np.testing.assert_allclose(path.poses[1, :3, :3], _rotation((1, 1, 0), 40.0), atol=1e-12)
    np.testing.assert_allclose(path.poses[1, :3, 3], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(slerp(a[:3, :3], b[:3, :3], np.array([0.25]))[0], _rotation((1, 1, 0), 20.0),
                               atol=1e-12)


def test_slerp_takes_the_short_way_round():
    """60 to 250 degrees about z is 170 degrees the short way (down through 0), 190 the long way."""
    a, b = _rotation((0, 0, 1), 60.0), _rotation((0, 0, 1), 250.0)
    half = slerp(a, b, np.array([0.5]))[0]
    assert rotation_angle(a, half) == pytest.approx(math.radians(85.0))
    np.testing.assert_allclose(half, _rotation((0, 0, 1), -25.0), atol=1e-12)


def test_a_camera_that_only_turns_gets_frames():
    keys = np.stack([_pose([0, 0, 0]), _pose([1, 0, 0]), _pose([1, 0, 0], (0, 0, 1), 90.0)])
    path = interpolate_path(keys, CAMERA, n_frames=21)
    turning = [rotation_angle(a[:3, :3], b[:3, :3]) for a, b in zip(path.poses[:-1], path.poses[1:], strict=True)]
    assert max(turning) < math.radians(15)  # the 90 degree turn is spread over several frames


@pytest.mark.parametrize(
    ("poses", "n_frames", "key"),
    [
        (_scene_poses(1), 10, "poses"),
        (_scene_poses(5), 4, "n_frames"),
        (_scene_poses(3), 0, "n_frames"),
        (np.stack([np.eye(4)] * 3), 10, "poses"),
        (np.stack([np.eye(4), np.full((4, 4), np.nan)]), 10, "poses[1]"),
    ],
)
def test_interpolation_refusals(poses, n_frames, key):
    with pytest.raises(CameraPathError) as err:
        interpolate_path(poses, CAMERA, n_frames=n_frames)
    assert err.value.key == key


def test_orbit_looks_at_the_centre_at_radius_and_height():
    center, up = np.array([1.0, 2.0, 0.5]), np.array([0.0, 1.0, 1.0]) / math.sqrt(2)
    path = orbit_path(center, radius=2.0, height=0.7, n_frames=12, intrinsics=CAMERA, fps=6.0, up=up)
    assert len(path) == 12 and path.fps == 6.0
    _orthonormal(path.poses)
    offsets = path.poses[:, :3, 3] - center
    np.testing.assert_allclose(offsets @ up, 0.7, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(offsets - np.outer(offsets @ up, up), axis=1), 2.0, atol=1e-12)
    # the camera's -Z points at the centre, its +X is level (no roll)
    np.testing.assert_allclose(-path.poses[:, :3, 2], -offsets / np.linalg.norm(offsets, axis=1)[:, None],
                               atol=1e-12)
    np.testing.assert_allclose(path.poses[:, :3, 0] @ up, 0.0, atol=1e-12)
    assert np.all(path.poses[:, :3, 1] @ up > 0)
    # one full turn in equal steps
    steps = np.linalg.norm(np.diff(path.poses[:, :3, 3], axis=0), axis=1)
    np.testing.assert_allclose(steps, 2 * 2.0 * math.sin(math.pi / 12), atol=1e-12)


@pytest.mark.parametrize(
    ("kwargs", "key"),
    [({"radius": 0.0}, "radius"), ({"height": float("nan")}, "height"), ({"n_frames": 0}, "n_frames"),
     ({"up": (0, 0, 0)}, "up"), ({"fps": 0}, "fps")],
)
def test_orbit_refusals(kwargs, key):
    args = {"radius": 1.0, "height": 0.0, "n_frames": 4, "intrinsics": CAMERA, **kwargs}
    with pytest.raises(CameraPathError) as err:
        orbit_path(np.zeros(3), **args)
    assert err.value.key == key


def test_look_at_refuses_looking_along_up():
    with pytest.raises(CameraPathError, match="^up: "):
        look_at(np.array([0.0, 0, 2]), np.zeros(3), np.array([0.0, 0, 1]))


@pytest.mark.parametrize(
    ("intrinsics", "key"),
    [
        ([CAMERA], "intrinsics"),
        ([CAMERA, Intrinsics(40.0, 40.0, 16.0, 12.0, 30, 24)], "intrinsics[1]"),
        ([CAMERA, Intrinsics(40.0, 40.0, 16.0, 12.0, 32, 24, {"model": "OPENCV", "k1": 0.1})], "intrinsics[1]"),
    ],
)
def test_camera_path_refuses_mixed_sizes_lenses_and_count_mismatch(intrinsics, key):
    with pytest.raises(CameraPathError) as err:
        CameraPath(_scene_poses(2), intrinsics)
    assert err.value.key == key


def _ring(n: int) -> np.ndarray:
    """n cameras on a horizontal circle of radius 2 (z up), looking at the origin, in capture order."""
    from voxnerf.cameras.paths import look_at

    angles = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.stack([look_at(np.array([2 * np.cos(a), 2 * np.sin(a), 0.0]), np.zeros(3), np.array([0.0, 0, 1]))
                     for a in angles])


def test_generated_interpolation_thins_the_cameras_to_one_per_eight_frames():
    from voxnerf.cameras.paths import FRAMES_PER_KEY, generated_path

    poses = _ring(20)
    path = generated_path("interpolate", poses, CAMERA, n_frames=4 * FRAMES_PER_KEY, fps=10.0)
    assert len(path) == 4 * FRAMES_PER_KEY and path.fps == 10.0
    hits = [np.abs(path.poses - p).sum(axis=(1, 2)).min() < 1e-6 for p in poses]
    assert sum(hits) == 4 and hits[0] and hits[-1]  # 4 key cameras, first and last among them
    assert len(generated_path("interpolate", poses, CAMERA, n_frames=100, keyframes=20)) == 100


def test_generated_orbit_circles_the_cameras_centre_at_their_radius():
    from voxnerf.cameras.paths import generated_path

    path = generated_path("orbit", _ring(12), CAMERA, n_frames=8)
    np.testing.assert_allclose(np.linalg.norm(path.poses[:, :2, 3], axis=1), 2.0, atol=1e-9)
    np.testing.assert_allclose(path.poses[:, 2, 3], 0.0, atol=1e-9)


@pytest.mark.parametrize(
    ("kind", "poses", "options", "key"),
    [
        ("spiral", _ring(4), {}, "path"),
        ("orbit", np.stack([np.eye(4)] * 3), {}, "radius"),  # cameras on one vertical line: no default radius
        ("interpolate", _ring(4), {"keyframes": 1}, "keyframes"),
        ("interpolate", _ring(4), {"n_frames": 0}, "n_frames"),
    ],
)
def test_generated_paths_refuse_what_they_cannot_make(kind, poses, options, key):
    from voxnerf.cameras.paths import generated_path

    with pytest.raises(CameraPathError) as err:
        generated_path(kind, poses, CAMERA, **{"n_frames": 16, **options})
    assert err.value.key == key


def test_one_camera_gives_a_still_path():
    from voxnerf.cameras.paths import generated_path

    path = generated_path("interpolate", _ring(1), CAMERA, n_frames=5)
    assert len(path) == 5 and np.allclose(path.poses, _ring(1)[0])


def test_rotation_angle_is_accurate_for_small_and_large_angles():
    for degrees in (0.0, 1e-9, 1e-4, 30.0, 179.9):
        a, b = _rotation((1, 2, 3), 10.0), _rotation((1, 2, 3), 10.0 + degrees)
        assert rotation_angle(a, b) == pytest.approx(math.radians(degrees), rel=1e-6, abs=1e-15)


def test_two_keyframes_at_the_same_pose_are_refused():
    """The same pose twice (as a viewer sends it: float32 rounded) has no path through it."""
    pose = _pose((0.3, -0.2, 1.0), (1, 2, 3), 37.0).astype(np.float32).astype(np.float64)
    with pytest.raises(CameraPathError, match="all at one pose"):
        interpolate_path(np.stack([pose, pose.copy()]), CAMERA, n_frames=10)
