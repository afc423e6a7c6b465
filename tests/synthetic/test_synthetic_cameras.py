"""voxnerf.synthetic.cameras: the camera path stays clear of the furniture; redkitchen-style splits."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from synthetic_fixtures import distance_to_gt, make_tiny_scene, meta_of

from voxnerf.synthetic import camera_path, look_at_c2w, split_frames


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory) -> Path:
    return make_tiny_scene(tmp_path_factory)


def test_extrapolation_frames_are_far_from_training_frames(tiny_scene: Path):
    meta = meta_of(tiny_scene)
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
    assert distance_to_gt(tiny_scene, positions).min() > 0.5


def test_look_at_follows_the_opengl_convention():
    forward = np.array([1.0, 1.0, -0.5])
    c2w = look_at_c2w(np.array([0.1, 0.2, 1.5]), forward)
    np.testing.assert_allclose(-c2w[:3, 2], forward / np.linalg.norm(forward))  # looks along -Z
    np.testing.assert_allclose(c2w[:3, :3] @ c2w[:3, :3].T, np.eye(3), atol=1e-12)
    assert c2w[2, 0] == pytest.approx(0.0, abs=1e-12), "no roll: +X stays horizontal"
    assert c2w[2, 1] > 0, "+Y points toward world +Z"
    np.testing.assert_allclose(c2w[:3, 3], [0.1, 0.2, 1.5])


def test_default_splits_mimic_redkitchen():
    splits = split_frames(160, 10, 2, 30)
    assert splits.train == [0, 10, 20, 60, 70, 80, 90, 100, 140, 150]
    assert splits.interpolation == [5, 15, 65, 75, 85, 95, 145]
    assert splits.extrapolation == [30, 35, 40, 45, 50, 110, 115, 120, 125, 130]
    with pytest.raises(ValueError, match="training frame"):
        split_frames(60, 10, 2, 40)
    with pytest.raises(ValueError, match="train_every"):
        split_frames(60, 1, 0, 0)
