"""How far poses from structure from motion are from given ones, once the similarity between their frames is fit.

SfM's world frame and scale are arbitrary, so poses are compared after a similarity (scale, rotation,
translation) between the two frames: :func:`fit_similarity` fits point sets (Umeyama 1991, "Least-squares
estimation of transformation parameters between two point patterns"); :func:`fit_similarity_to_poses` fits
camera poses, its rotation from the cameras' orientations. Used by the importers' tests and by
``benchmarks/import_captures.py``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Similarity:
    """``x -> scale * rotation @ x + translation``."""

    scale: float
    rotation: np.ndarray
    translation: np.ndarray

    def apply(self, points: np.ndarray) -> np.ndarray:
        return self.scale * points @ self.rotation.T + self.translation


@dataclass(frozen=True)
class PoseErrors:
    """Errors of estimated camera-to-world poses against given ones after the centres' similarity fit."""

    rotation_deg_max: float
    rotation_deg_median: float
    centre_max: float
    centre_median: float
    trajectory_length: float
    scale: float

    @property
    def centre_max_fraction(self) -> float:
        """Largest centre error as a fraction of the given trajectory's length."""
        return self.centre_max / self.trajectory_length

    @property
    def centre_median_fraction(self) -> float:
        return self.centre_median / self.trajectory_length

    def as_dict(self) -> dict:
        return {"rotation_deg_max": self.rotation_deg_max, "rotation_deg_median": self.rotation_deg_median,
                "centre_error_max_fraction": self.centre_max_fraction,
                "centre_error_median_fraction": self.centre_median_fraction,
                "trajectory_length": self.trajectory_length, "scale": self.scale}


def fit_similarity(source: np.ndarray, target: np.ndarray) -> Similarity:
    """The similarity taking points ``source`` [N, 3] closest to ``target`` [N, 3] (N >= 3, not collinear)."""
    source, target = _point_sets(source, target)
    mean_s, mean_t = source.mean(axis=0), target.mean(axis=0)
    centred_s, centred_t = source - mean_s, target - mean_t
    u, d, vt = np.linalg.svd(centred_t.T @ centred_s / len(source))
    sign = np.diag([1.0, 1.0, -1.0 if np.linalg.det(u) * np.linalg.det(vt) < 0 else 1.0])
    rotation = u @ sign @ vt
    scale = float(np.trace(np.diag(d) @ sign) / _variance(centred_s))
    return Similarity(scale, rotation, mean_t - scale * rotation @ mean_s)


def fit_similarity_to_poses(estimated: np.ndarray, given: np.ndarray) -> Similarity:
    """The similarity between two sets of camera-to-world poses [N, 4, 4]: its rotation is the chordal mean of
    ``R_given @ R_estimated^T`` over the cameras (well defined even when the centres lie near a line, where a fit
    to centres alone leaves the rotation about that line free); scale and translation are then the least-squares
    fit of the centres."""
    source, target = _point_sets(estimated[:, :3, 3], given[:, :3, 3])
    total = sum(_nearest_rotation(ref[:3, :3]) @ _nearest_rotation(est[:3, :3]).T
                for est, ref in zip(estimated, given, strict=True))
    rotation = _nearest_rotation(total)
    centred_s, centred_t = source - source.mean(axis=0), target - target.mean(axis=0)
    scale = float(np.sum(centred_t * (centred_s @ rotation.T)) / (_variance(centred_s) * len(source)))
    return Similarity(scale, rotation, target.mean(axis=0) - scale * rotation @ source.mean(axis=0))


def _point_sets(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    source, target = np.asarray(source, dtype=np.float64), np.asarray(target, dtype=np.float64)
    if source.shape != target.shape or source.ndim != 2 or source.shape[1] != 3 or len(source) < 3:
        raise ValueError(f"need two [N, 3] point sets with N >= 3, got {source.shape} and {target.shape}")
    return source, target


def _variance(centred: np.ndarray) -> float:
    variance = float((centred**2).sum() / len(centred))
    if variance <= 0:
        raise ValueError("the source points all coincide")
    return variance


def pose_errors(estimated: np.ndarray, given: np.ndarray) -> PoseErrors:
    """Errors of camera-to-world poses ``estimated`` [N, 4, 4] against ``given`` [N, 4, 4] (same camera axes,
    same order) after :func:`fit_similarity_to_poses`. The trajectory length is the sum of the given centres'
    steps in that order."""
    estimated, given = np.asarray(estimated, dtype=np.float64), np.asarray(given, dtype=np.float64)
    fit = fit_similarity_to_poses(estimated, given)
    centre_errors = np.linalg.norm(fit.apply(estimated[:, :3, 3]) - given[:, :3, 3], axis=1)
    angles = []
    for est, ref in zip(estimated, given, strict=True):
        ref_rot = _nearest_rotation(ref[:3, :3])
        relative = ref_rot.T @ fit.rotation @ _nearest_rotation(est[:3, :3])
        angles.append(np.degrees(np.arccos(np.clip((np.trace(relative) - 1) / 2, -1.0, 1.0))))
    length = float(np.linalg.norm(np.diff(given[:, :3, 3], axis=0), axis=1).sum())
    return PoseErrors(float(np.max(angles)), float(np.median(angles)), float(centre_errors.max()),
                      float(np.median(centre_errors)), length, fit.scale)


def _nearest_rotation(matrix: np.ndarray) -> np.ndarray:
    """The rotation nearest ``matrix`` (7-Scenes' given rotations are slightly scaled)."""
    u, _, vt = np.linalg.svd(matrix)
    return u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
