"""The similarity fits that compare poses from structure from motion with given ones."""

from __future__ import annotations

import numpy as np
import pytest

from voxnerf.data.importers.alignment import fit_similarity, fit_similarity_to_poses, pose_errors


def random_rotation(rng) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def poses_along_a_line(rng, n: int = 12) -> np.ndarray:
    """Camera-to-world poses whose centres lie near one line (a short video's), each turned its own way."""
    poses = np.tile(np.eye(4), (n, 1, 1))
    for i in range(n):
        poses[i, :3, :3] = random_rotation(rng)
        poses[i, :3, 3] = [0.1 * i, 0.001 * rng.normal(), 0.001 * rng.normal()]
    return poses


def transformed(poses: np.ndarray, scale: float, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    out = poses.copy()
    out[:, :3, :3] = rotation @ poses[:, :3, :3]
    out[:, :3, 3] = scale * poses[:, :3, 3] @ rotation.T + translation
    return out


def test_point_fit_recovers_a_known_similarity():
    rng = np.random.default_rng(0)
    points = rng.normal(size=(20, 3))
    rotation, translation = random_rotation(rng), np.array([1.0, -2.0, 0.5])
    fit = fit_similarity(points, 3.5 * points @ rotation.T + translation)
    assert fit.scale == pytest.approx(3.5)
    np.testing.assert_allclose(fit.rotation, rotation, atol=1e-9)
    np.testing.assert_allclose(fit.translation, translation, atol=1e-9)


def test_pose_fit_is_exact_even_when_the_centres_lie_near_a_line():
    rng = np.random.default_rng(1)
    given = poses_along_a_line(rng)
    rotation = random_rotation(rng)
    estimated = transformed(given, 0.2, rotation, np.array([3.0, 1.0, -1.0]))
    # the fit maps estimated onto given: its inverse similarity
    fit = fit_similarity_to_poses(estimated, given)
    np.testing.assert_allclose(fit.rotation, rotation.T, atol=1e-9)
    assert fit.scale == pytest.approx(5.0)
    errors = pose_errors(estimated, given)
    assert errors.rotation_deg_max < 1e-5 and errors.centre_max < 1e-9
    assert errors.trajectory_length == pytest.approx(1.1, rel=1e-3)


def test_pose_errors_see_one_camera_turned_and_one_moved():
    rng = np.random.default_rng(2)
    given = poses_along_a_line(rng, 20)
    estimated = given.copy()
    angle = np.radians(3.0)
    turn = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    estimated[4, :3, :3] = given[4, :3, :3] @ turn
    estimated[9, :3, 3] += [0.0, 0.05, 0.0]
    errors = pose_errors(estimated, given)
    assert errors.rotation_deg_max == pytest.approx(3.0, abs=0.3)
    assert errors.rotation_deg_median < 0.3
    assert errors.centre_max == pytest.approx(0.05, abs=0.01)
    assert errors.centre_median < 0.01


def test_degenerate_inputs_are_refused():
    with pytest.raises(ValueError, match="N >= 3"):
        fit_similarity(np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="coincide"):
        fit_similarity(np.zeros((4, 3)), np.ones((4, 3)))
