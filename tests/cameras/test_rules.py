"""voxnerf.cameras.rules: the pose and intrinsics rules shared by scenes, the CLI, the Python API and REST."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from voxnerf.cameras.rules import (
    REPAIR_WARNING_ABOVE,
    ROTATION_TOLERANCE,
    CameraError,
    Intrinsics,
    Lens,
    lens_of,
    resolve_intrinsics,
    resolve_lens,
    validate_pose,
    validate_pose_deviation,
)

DEFAULT = Intrinsics(fl_x=50.0, fl_y=40.0, cx=32.0, cy=24.0, width=64, height=48)


def _rotation_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _pose(rot: np.ndarray | None = None, t=(1.0, -2.0, 3.0)) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = _rotation_z(0.3) if rot is None else rot
    pose[:3, 3] = t
    return pose


# ------------------------------------------------------------------------------------------------ poses


def test_valid_pose_comes_back_unchanged_as_float64():
    pose = _pose()
    for value in (pose.tolist(), pose, tuple(map(tuple, pose))):
        out = validate_pose(value)
        assert out.dtype == np.float64 and out.shape == (4, 4)
        np.testing.assert_array_equal(out, np.asarray(value, dtype=np.float64))


def test_integer_matrices_and_arrays_are_accepted():
    out = validate_pose([[1, 0, 0, 2], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    assert out.dtype == np.float64 and out[0, 3] == 2.0
    assert validate_pose(np.eye(4, dtype=np.int64)).dtype == np.float64


@pytest.mark.parametrize(
    ("value", "needle"),
    [
        (np.eye(3).tolist(), "4x4"),
        (np.eye(4)[:3].tolist(), "4x4"),
        ([[1, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "4x4"),
        ([], "4x4"),
        (np.eye(5).tolist(), "4x4"),
        (np.eye(3), "4x4"),
        ("eye", "4x4"),
        (None, "4x4"),
        ({"a": 1}, "4x4"),
        ([1, 2, 3, 4], "4x4"),
        ([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, "1"]], "numbers"),
        ([[True, False, False, False], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "numbers"),
        ([[1, 0, 0, None], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "numbers"),
        ([[1, 0, 0, [0]], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "numbers"),
        (np.eye(4, dtype=bool), "numbers"),
        (np.array([["1"] * 4] * 4), "numbers"),
        ([[1, 0, 0, 10**400], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "too large"),
        ([[1, 0, 0, float("nan")], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "NaN or inf"),
        ([[1, 0, 0, float("inf")], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "NaN or inf"),
        ((np.eye(4) * 2).tolist(), "last row"),
        ([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1e-3, 1]], "last row"),
        (np.diag([2.0, 1, 1, 1]).tolist(), "not a proper orthonormal"),
        (np.diag([-1.0, 1, 1, 1]).tolist(), "det = -1"),
        (np.diag([0.0, 1, 1, 1]).tolist(), "not a proper orthonormal"),
        (_pose(np.diag([1.0, 1.0, 1.0 + 2 * ROTATION_TOLERANCE])).tolist(), "orthonormal"),
    ],
)
def test_bad_poses_are_refused_with_one_line_naming_no_file(value, needle):
    with pytest.raises(CameraError) as info:
        validate_pose(value)
    message = str(info.value)
    assert needle in message, message
    assert "\n" not in message and len(message) < 200
    assert info.value.field is None and info.value.message == message
    assert isinstance(info.value, ValueError)


def test_slightly_skewed_rotation_is_reorthonormalised_and_its_deviation_reported():
    pose = _pose()
    pose[0, 1] += 0.01
    out, deviation = validate_pose_deviation(pose.tolist())
    rot = out[:3, :3]
    np.testing.assert_allclose(rot.T @ rot, np.eye(3), atol=1e-12)
    assert np.linalg.det(rot) == pytest.approx(1.0)
    assert 0.005 < deviation < ROTATION_TOLERANCE
    np.testing.assert_allclose(rot, _rotation_z(0.3), atol=0.01)  # the nearest rotation
    np.testing.assert_array_equal(out[:3, 3], pose[:3, 3])  # translation untouched
    np.testing.assert_array_equal(validate_pose(pose), out)


def test_rounding_level_deviation_is_used_as_given_and_reported():
    pose = np.round(_pose(), 7)  # a pose file with 7 decimals
    out, deviation = validate_pose_deviation(pose)
    assert 1e-9 < deviation < REPAIR_WARNING_ABOVE
    np.testing.assert_array_equal(out, pose)


def test_exact_rotation_reports_no_deviation_and_is_not_touched():
    pose = np.eye(4)
    out, deviation = validate_pose_deviation(pose)
    assert deviation == 0.0
    np.testing.assert_array_equal(out, pose)
    assert out is not pose  # a copy: the caller's array is never modified


def test_caller_array_is_not_modified_by_the_repair():
    pose = _pose()
    pose[0, 1] += 0.01
    before = pose.copy()
    validate_pose(pose)
    np.testing.assert_array_equal(pose, before)


def test_rotation_just_inside_the_tolerance_is_accepted_and_just_outside_refused():
    inside = _pose(np.diag([1.0, 1.0, np.sqrt(1 + 0.9 * ROTATION_TOLERANCE)]))
    validate_pose(inside)
    outside = _pose(np.diag([1.0, 1.0, np.sqrt(1 + 1.1 * ROTATION_TOLERANCE)]))
    with pytest.raises(CameraError, match="orthonormal"):
        validate_pose(outside)


# ------------------------------------------------------------------------------------------------ intrinsics


def test_nothing_given_is_the_default():
    assert resolve_intrinsics(DEFAULT) == DEFAULT


def test_size_scales_every_missing_value_per_axis():
    out = resolve_intrinsics(DEFAULT, width=32, height=96)
    assert out == Intrinsics(fl_x=25.0, fl_y=80.0, cx=16.0, cy=48.0, width=32, height=96)


def test_given_values_are_kept_unscaled():
    out = resolve_intrinsics(DEFAULT, width=128, height=96, fl_x=10, fl_y=11.5, cx=-3, cy=0)
    assert out == Intrinsics(fl_x=10.0, fl_y=11.5, cx=-3.0, cy=0.0, width=128, height=96)
    assert isinstance(out.fl_x, float) and isinstance(out.cx, float)
    assert isinstance(out.width, int) and isinstance(out.height, int)


def test_whole_float_sizes_are_integers():
    out = resolve_intrinsics(DEFAULT, width=32.0, height=24.0)
    assert (out.width, out.height) == (32, 24) and isinstance(out.width, int)


def test_matches_the_rest_schema_rule_for_partial_intrinsics():
    """Only fl_x given at a new size: fl_y, cx, cy still follow the default, scaled."""
    out = resolve_intrinsics(DEFAULT, width=640, height=480, fl_x=123.0)
    assert out.fl_x == 123.0 and out.fl_y == pytest.approx(400.0)
    assert (out.cx, out.cy) == (pytest.approx(320.0), pytest.approx(240.0))


@pytest.mark.parametrize(
    ("kwargs", "field", "needle"),
    [
        ({"width": 32}, "width, height", "together"),
        ({"height": 24}, "width, height", "together"),
        ({"width": 0, "height": 24}, "width", "positive integer"),
        ({"width": -32, "height": 24}, "width", "positive integer"),
        ({"width": 32.5, "height": 24}, "width", "positive integer"),
        ({"width": True, "height": 24}, "width", "positive integer"),
        ({"width": "32", "height": 24}, "width", "positive integer"),
        ({"width": float("inf"), "height": 24}, "width", "positive integer"),
        ({"width": 32, "height": float("nan")}, "height", "positive integer"),
        ({"width": 32, "height": 10**400}, "height", "positive integer"),
        ({"fl_x": 0}, "fl_x", "positive finite"),
        ({"fl_x": -3}, "fl_x", "positive finite"),
        ({"fl_y": float("nan")}, "fl_y", "positive finite"),
        ({"fl_y": float("inf")}, "fl_y", "positive finite"),
        ({"fl_x": True}, "fl_x", "positive finite"),
        ({"fl_x": "50"}, "fl_x", "positive finite"),
        ({"cx": float("nan")}, "cx", "finite number"),
        ({"cy": float("-inf")}, "cy", "finite number"),
        ({"cx": False}, "cx", "finite number"),
        ({"cy": [1]}, "cy", "finite number"),
        ({"width": 100, "height": 100, "max_pixels": 9999}, "width, height", "exceeds the limit of 9999"),
        ({"max_pixels": 64 * 48 - 1}, "width, height", "64x48 exceeds"),
    ],
)
def test_bad_intrinsics_are_refused_naming_the_field(kwargs, field, needle):
    with pytest.raises(CameraError) as info:
        resolve_intrinsics(DEFAULT, **kwargs)
    assert info.value.field == field
    assert needle in info.value.message, info.value.message
    assert str(info.value) == f"{field}: {info.value.message}"
    assert "\n" not in str(info.value)


def test_max_pixels_is_inclusive():
    assert resolve_intrinsics(DEFAULT, width=10, height=10, max_pixels=100).width == 10


def test_intrinsics_scaled_and_as_dict():
    half = DEFAULT.scaled(0.5)
    assert half == Intrinsics(25.0, 20.0, 16.0, 12.0, 32, 24)
    assert DEFAULT.scaled(0.001).width == 1  # never below one pixel
    assert DEFAULT.as_dict() == {"fl_x": 50.0, "fl_y": 40.0, "cx": 32.0, "cy": 24.0, "width": 64, "height": 48}
    assert Intrinsics(**DEFAULT.as_dict()) == DEFAULT


def test_cameras_and_scene_re_export_the_same_objects():
    from voxnerf.cameras import rays as cameras
    from voxnerf.data import scene

    assert cameras.Intrinsics is Intrinsics
    assert scene.ROTATION_TOLERANCE is ROTATION_TOLERANCE


def test_camera_rules_and_outputs_import_no_torch():
    code = "import sys, voxnerf.cameras.rules, voxnerf.inference.encoding; sys.exit(1 if 'torch' in sys.modules else 0)"
    assert subprocess.run([sys.executable, "-c", code], check=False).returncode == 0


# ------------------------------------------------------------------------------------------------ lenses

FISHEYE = Lens("OPENCV_FISHEYE", k1=0.05, k2=-0.02, k3=0.01, k4=-0.002)


@pytest.mark.parametrize(
    ("model", "values", "field"),
    [
        ("PINHOLE", {}, "camera_model"),
        ("FISHEYE", {}, "camera_model"),
        ("OPENCV", {"k1": float("inf")}, "k1"),
        ("OPENCV", {"k2": "0.1"}, "k2"),
        ("OPENCV", {"p1": True}, "p1"),
        ("OPENCV", {"k4": 0.1}, "k4"),
        ("OPENCV_FISHEYE", {"p2": -0.1}, "p2"),
    ],
)
def test_a_lens_refuses_bad_values_naming_them(model, values, field):
    with pytest.raises(CameraError) as info:
        Lens(model, **values)
    assert info.value.field == field and "\n" not in str(info.value)


def test_lens_of_follows_the_camera_model():
    assert lens_of("PINHOLE", {"k1": 0, "p2": None}) is None
    assert lens_of("OPENCV", {"k1": -0.1, "k3": None}) == Lens("OPENCV", k1=-0.1)
    assert lens_of("OPENCV_FISHEYE", {"k4": 1}).k4 == 1.0
    for model, values, field in [("PINHOLE", {"k1": 0.1}, "k1"), (None, {}, "camera_model"),
                                 ("opencv", {}, "camera_model")]:
        with pytest.raises(CameraError) as info:
            lens_of(model, values)
        assert info.value.field == field


def test_intrinsics_carry_their_lens_through_scaling_and_dicts():
    intr = Intrinsics(50.0, 40.0, 32.0, 24.0, 64, 48, FISHEYE)
    assert intr.scaled(0.5) == Intrinsics(25.0, 20.0, 16.0, 12.0, 32, 24, FISHEYE)
    assert intr.as_dict()["lens"] == {"model": "OPENCV_FISHEYE", "k1": 0.05, "k2": -0.02, "k3": 0.01, "k4": -0.002,
                                      "p1": 0.0, "p2": 0.0}
    assert Intrinsics(**intr.as_dict()) == intr  # as a checkpoint stores and reads it
    assert intr.undistorted() == DEFAULT.scaled(1.0) and "lens" not in DEFAULT.as_dict()


def test_a_render_is_a_pinhole_unless_it_names_a_camera_model():
    trained = Intrinsics(50.0, 40.0, 32.0, 24.0, 64, 48, Lens("OPENCV", k1=-0.1, p1=0.01))
    assert resolve_intrinsics(trained).lens is None  # the undistorted view of the trained camera
    assert resolve_intrinsics(trained, width=32, height=24) == Intrinsics(25.0, 20.0, 16.0, 12.0, 32, 24)
    same = resolve_intrinsics(trained, camera_model="OPENCV", k2=0.01)  # the trained coefficients, k2 changed
    assert same.lens == Lens("OPENCV", k1=-0.1, k2=0.01, p1=0.01)
    other = resolve_intrinsics(trained, camera_model="OPENCV_FISHEYE", k1=0.2)  # another model: from zero
    assert other.lens == Lens("OPENCV_FISHEYE", k1=0.2)
    assert resolve_intrinsics(trained, camera_model="PINHOLE").lens is None
    assert resolve_lens(None, "OPENCV") == Lens("OPENCV")


@pytest.mark.parametrize(
    ("given", "field"),
    [
        ({"k1": 0.1}, "k1"),  # coefficients need camera_model
        ({"camera_model": "PINHOLE", "p1": 0.1}, "p1"),
        ({"camera_model": "OPENCV", "k4": 0.1}, "k4"),
        ({"camera_model": "OPENCV", "k1": float("nan")}, "k1"),
        ({"camera_model": "OPENCV", "k1": False}, "k1"),
        ({"camera_model": "THETA"}, "camera_model"),
    ],
)
def test_bad_render_lenses_name_the_field(given, field):
    with pytest.raises(CameraError) as info:
        resolve_intrinsics(DEFAULT, **given)
    assert info.value.field == field
