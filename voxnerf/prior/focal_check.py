"""The colour camera's focal length checked against the scan's geometry.

A scan can state its colour camera's focal length wrongly: 7-Scenes, for one, gives the depth sensor's 585 px
for colour images taken at about 525 px. A wrong focal length bends every ray by an angle that grows from the
image centre outwards, so two views of the same surface point disagree, more at the image borders, and neither
the field nor a pose correction can reconcile them (a correction moves a whole image; this stretches it).

The check measures how well the training images agree through the geometry prior's mesh at candidate scales of
the stated focal length. For a pair of neighbouring training images (A, B) and a scale ``s``: rays through a
grid of A's pixels, with focal lengths ``s * fl``, are cast to the mesh; each hit that B sees (B's ray towards
it meets no other surface first) is projected into B with the same focal lengths; the error is the mean
absolute difference of the grey levels at the two ends, after one gain per pair (the exposure). The scale with
the least error over all pairs is the measured one. The geometry keeps the stated camera: the prior and the
depth maps were measured through it, not through the colour camera.

Everything here is in the scene's own units (poses and mesh alike); the mesh is cast by
:class:`voxnerf.prior.pseudo_depth.MeshCaster`, as the prior's pseudo depth is.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from voxnerf.cameras.neighbours import nearest_cameras
from voxnerf.cameras.rules import Intrinsics
from voxnerf.prior.pseudo_depth import MeshCaster

COARSE_SCALES = tuple(np.round(np.arange(0.80, 1.2001, 0.04), 4))  # first pass, the stated focal among them
FINE_STEP = 0.01  # second pass: every FINE_STEP within one coarse step of the coarse minimum
MAX_PAIRS = 24  # image pairs measured (evenly spread over the training images)
PIXELS_PER_IMAGE = 8192  # rays cast from each pair's first image (a regular grid)
VISIBLE_TOLERANCE = 0.02  # B sees a hit when its ray meets the mesh within this fraction of the distance


@dataclass(frozen=True)
class FocalCheck:
    """What the check measured: the error at each scale tried and the scale with the least."""

    errors: dict[float, float]  # scale of the stated focal length -> mean grey-level error (0-1 units)
    best: float  # the scale with the least error (refined between the grid's points)
    pairs: int  # image pairs measured
    points: int  # surface points compared at the stated focal length, over all pairs

    @property
    def stated_error(self) -> float:
        return self.errors[1.0]

    @property
    def best_error(self) -> float:
        return min(self.errors.values())

    @property
    def gain(self) -> float:
        """Fraction of the stated focal length's error that the best scale removes."""
        return 1.0 - self.best_error / self.stated_error if self.stated_error > 0 else 0.0

    @property
    def interior(self) -> bool:
        """Whether the least error lies inside the scales tried (not at an end of the range)."""
        return min(COARSE_SCALES) < self.best < max(COARSE_SCALES)


def image_pairs(c2ws: np.ndarray, most: int = MAX_PAIRS) -> list[tuple[int, int]]:
    """Pairs (i, j) of each camera ``c2ws`` [N, 4, 4] and its nearest other camera (each pair once), at most
    ``most`` of them, evenly spread."""
    if len(c2ws) < 2:
        return []
    poses = torch.from_numpy(np.asarray(c2ws, dtype=np.float64))
    index, _ = nearest_cameras(poses, poses, k=2)
    pairs = sorted({tuple(sorted((i, int(row[1] if int(row[0]) == i else row[0]))))
                    for i, row in enumerate(index.tolist())})
    if len(pairs) > most:
        pairs = [pairs[k] for k in np.linspace(0, len(pairs) - 1, most).round().astype(int)]
    return pairs


def grey(image: np.ndarray) -> np.ndarray:
    """float32 [H, W] in [0, 1]: the mean of an 8-bit [H, W, 3] image's channels."""
    return image.astype(np.float32).mean(axis=-1) / 255.0


def _grid(intr: Intrinsics, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel centres (u, v) [P] of a regular grid of about ``count`` pixels over the image."""
    stride = max(1, int(np.sqrt(intr.width * intr.height / count)))
    v, u = np.mgrid[stride // 2: intr.height: stride, stride // 2: intr.width: stride]
    return u.ravel().astype(np.float64) + 0.5, v.ravel().astype(np.float64) + 0.5


def _bilinear(image: np.ndarray, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(values, inside): ``image`` [H, W] at continuous pixel coordinates (u, v), for the points inside it."""
    h, w = image.shape
    x, y = u - 0.5, v - 0.5
    inside = (x >= 0) & (y >= 0) & (x <= w - 1) & (y <= h - 1)
    x0 = np.clip(np.floor(x[inside]).astype(np.int64), 0, w - 2)
    y0 = np.clip(np.floor(y[inside]).astype(np.int64), 0, h - 2)
    fx, fy = x[inside] - x0, y[inside] - y0
    top = image[y0, x0] * (1 - fx) + image[y0, x0 + 1] * fx
    bottom = image[y0 + 1, x0] * (1 - fx) + image[y0 + 1, x0 + 1] * fx
    return top * (1 - fy) + bottom * fy, inside


def pair_error(caster: MeshCaster, grey_a: np.ndarray, grey_b: np.ndarray, c2w_a: np.ndarray, c2w_b: np.ndarray,
               intr: Intrinsics, scale: float) -> tuple[float, int]:
    """(sum of absolute grey-level differences, points compared) of images A and B through the mesh, both seen
    through ``intr`` with its focal lengths times ``scale`` (OpenGL camera axes, as the poses)."""
    fx, fy = intr.fl_x * scale, intr.fl_y * scale
    u, v = _grid(intr, PIXELS_PER_IMAGE)
    cam = np.stack([(u - intr.cx) / fx, -(v - intr.cy) / fy, -np.ones_like(u)], axis=1)
    dirs = cam @ c2w_a[:3, :3].T
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    t = caster.distance(np.broadcast_to(c2w_a[:3, 3], dirs.shape), dirs)
    hit = np.isfinite(t)
    points = c2w_a[:3, 3] + t[hit, None] * dirs[hit]
    u, v = u[hit], v[hit]
    world_to_b = np.linalg.inv(c2w_b)
    in_b = points @ world_to_b[:3, :3].T + world_to_b[:3, 3]
    ahead = -in_b[:, 2] > 1e-6
    points, u, v, in_b = points[ahead], u[ahead], v[ahead], in_b[ahead]
    to_point = points - c2w_b[:3, 3]
    dist = np.linalg.norm(to_point, axis=1)
    seen = np.abs(caster.distance(np.broadcast_to(c2w_b[:3, 3], to_point.shape), to_point / dist[:, None]) - dist)
    visible = seen <= VISIBLE_TOLERANCE * dist
    in_b, u, v = in_b[visible], u[visible], v[visible]
    ub = fx * in_b[:, 0] / -in_b[:, 2] + intr.cx
    vb = -fy * in_b[:, 1] / -in_b[:, 2] + intr.cy
    value_b, inside = _bilinear(grey_b, ub, vb)
    value_a = grey_a[v[inside].astype(np.int64), u[inside].astype(np.int64)]
    if len(value_a) == 0:
        return 0.0, 0
    gain = value_a.mean() / max(float(value_b.mean()), 1e-6)
    return float(np.abs(value_a - gain * value_b).sum()), len(value_a)


def consistency_error(caster: MeshCaster, greys: list[np.ndarray], c2ws: np.ndarray, intr: Intrinsics,
                      pairs: list[tuple[int, int]], scale: float) -> tuple[float, int]:
    """(mean absolute grey-level error over every pair's compared points, points compared) at ``scale``."""
    total, count = 0.0, 0
    for a, b in pairs:
        err, n = pair_error(caster, greys[a], greys[b], c2ws[a], c2ws[b], intr, scale)
        total, count = total + err, count + n
    return (total / count if count else float("inf")), count


def _refined(errors: dict[float, float]) -> float:
    """The scale of least error, moved to the vertex of the parabola through it and its two neighbours."""
    scales = sorted(errors)
    k = min(range(len(scales)), key=lambda i: errors[scales[i]])
    if k == 0 or k == len(scales) - 1:
        return scales[k]
    (x0, x1, x2), (y0, y1, y2) = scales[k - 1: k + 2], (errors[s] for s in scales[k - 1: k + 2])
    denom = (x0 - x1) * (x0 - x2) * (x1 - x2)
    a = (x2 * (y1 - y0) + x1 * (y0 - y2) + x0 * (y2 - y1)) / denom
    b = (x2 * x2 * (y0 - y1) + x1 * x1 * (y2 - y0) + x0 * x0 * (y1 - y2)) / denom
    return float(np.clip(-b / (2 * a), x0, x2)) if a > 0 else scales[k]


def check_focal(caster: MeshCaster, images: list[np.ndarray], c2ws: np.ndarray, intr: Intrinsics) -> FocalCheck:
    """Measure the scale of ``intr``'s focal lengths at which the training ``images`` (uint8 [H, W, 3], all
    seen through ``intr``, posed by ``c2ws`` [N, 4, 4] in the mesh's units) agree best through the mesh.

    Raises ValueError when fewer than two images are given or no pair shares a surface point.
    """
    pairs = image_pairs(np.asarray(c2ws))
    if not pairs:
        raise ValueError("the focal check needs at least two training images")
    used = sorted({i for pair in pairs for i in pair})
    greys = {i: grey(images[i]) for i in used}
    greys_list = [greys.get(i) for i in range(len(images))]
    errors: dict[float, float] = {}
    counts: dict[float, int] = {}

    def measure(scale: float) -> None:
        scale = round(float(scale), 4)
        if scale not in errors:
            errors[scale], counts[scale] = consistency_error(caster, greys_list, c2ws, intr, pairs, scale)

    for scale in COARSE_SCALES:
        measure(scale)
    if counts[1.0] == 0:
        raise ValueError("no surface point of the prior is seen by two neighbouring training images")
    coarse_best = min(errors, key=errors.get)
    step = COARSE_SCALES[1] - COARSE_SCALES[0]
    for scale in np.arange(coarse_best - step + FINE_STEP, coarse_best + step - FINE_STEP / 2, FINE_STEP):
        if min(COARSE_SCALES) <= scale <= max(COARSE_SCALES):
            measure(scale)
    return FocalCheck(errors=dict(sorted(errors.items())), best=_refined(errors), pairs=len(pairs),
                      points=counts[1.0])
