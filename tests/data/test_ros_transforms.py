"""The bag importer's transform tree: quaternions, slerp, lookups through a common ancestor, stamps outside the
samples, and contradictory trees."""

from __future__ import annotations

import math

import numpy as np
import pytest

from voxnerf.data.importers.ros_transforms import (
    TransformTree,
    TransformTreeError,
    matrix_quaternion,
    quaternion_matrix,
    rigid,
    slerp,
)


def axis_angle(axis, angle: float) -> np.ndarray:
    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    return np.array([*(axis * math.sin(angle / 2)), math.cos(angle / 2)])


def random_rotations(n: int, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    rots = [quaternion_matrix(q / np.linalg.norm(q)) for q in rng.normal(size=(n, 4))]
    # the branches of Shepperd's method: half turns about each axis, and the identity
    return rots + [np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1]), np.eye(3)]


def test_quaternion_round_trip():
    for rot in random_rotations(50):
        q = matrix_quaternion(rot)
        assert abs(np.linalg.norm(q) - 1) < 1e-12 and q[3] >= 0
        np.testing.assert_allclose(quaternion_matrix(q), rot, atol=1e-12)


def test_slerp_follows_the_rotation_about_a_fixed_axis():
    axis = [0.2, -0.7, 0.4]
    q0, q1 = axis_angle(axis, 0.3), axis_angle(axis, 1.9)
    for s in (0.0, 0.25, 0.5, 0.9, 1.0):
        np.testing.assert_allclose(quaternion_matrix(slerp(q0, q1, s)),
                                   quaternion_matrix(axis_angle(axis, 0.3 + s * 1.6)), atol=1e-12)
    # the shorter arc when the samples' signs differ (q and -q are one rotation)
    np.testing.assert_allclose(quaternion_matrix(slerp(q0, -q1, 0.5)), quaternion_matrix(axis_angle(axis, 1.1)),
                               atol=1e-12)


def test_lookup_interpolates_and_composes_through_the_common_ancestor():
    tree = TransformTree()
    mount = rigid([0.1, 0.2, 0.3], axis_angle([0, 1, 0], 0.4))
    tree.add("base", "camera", 0, mount[:3, 3], matrix_quaternion(mount[:3, :3]), static=True)
    tree.add("/map", "base", 100, [0.0, 0.0, 0.0], axis_angle([0, 0, 1], 0.0), static=False)
    tree.add("map", "base", 300, [2.0, 0.0, 0.0], axis_angle([0, 0, 1], 1.0), static=False)
    tree.add("map", "landmark", 0, [5.0, 5.0, 0.0], [0, 0, 0, 1.0], static=True)
    tree.finish()
    t, missing = tree.lookup("map", "camera", 150)
    want = rigid([0.5, 0.0, 0.0], axis_angle([0, 0, 1], 0.25)) @ mount
    assert missing is None
    np.testing.assert_allclose(t, want, atol=1e-12)
    t, _ = tree.lookup("landmark", "camera", 150)  # map is the common ancestor
    np.testing.assert_allclose(t, np.linalg.inv(rigid([5.0, 5.0, 0.0], [0, 0, 0, 1.0])) @ want, atol=1e-12)
    assert tree.lookup("map", "camera", 99) == (None, "map -> base")
    assert tree.lookup("map", "camera", 301) == (None, "map -> base")
    assert tree.root("camera") == "map" and tree.connected("landmark", "camera")


def test_bad_samples_are_counted_and_contradictions_refused():
    tree = TransformTree()
    tree.add("a", "b", 0, [0, 0, float("nan")], [0, 0, 0, 1.0], static=False)
    tree.add("a", "b", 0, [0, 0, 0], [0, 0, 0, 2.0], static=False)  # not a rotation: norm 2
    tree.add("a", "b", 0, [0, 0, 0], [0, 0, 0, 1.0 + 1e-4], static=False)  # rounding: kept, normalised
    assert tree.ignored == 2 and len(tree.edges["b"].stamps) == 1
    with pytest.raises(TransformTreeError, match="frame 'b' has two parents, 'a' and 'c'"):
        tree.add("c", "b", 0, [0, 0, 0], [0, 0, 0, 1.0], static=False)
    with pytest.raises(TransformTreeError, match="both as static and as dynamic"):
        tree.add("a", "b", 0, [0, 0, 0], [0, 0, 0, 1.0], static=True)
    tree.add("b", "a", 0, [0, 0, 0], [0, 0, 0, 1.0], static=True)
    with pytest.raises(TransformTreeError, match="the transforms loop: b -> a -> b"):
        tree.finish()
