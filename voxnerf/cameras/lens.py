"""Lens distortion in torch: OpenCV's radial-tangential model (``OPENCV``) and its fisheye model
(``OPENCV_FISHEYE``), forward and inverse, batched, as nerfstudio uses them: rays go through the inverse
distortion, images are never resampled.

Conventions (OpenCV's): normalised camera coordinates, x right, y down, z forward. A continuous pixel
``(px, py)`` of a camera ``fl_x fl_y cx cy`` has the *distorted* coordinates ``((px - cx) / fl_x,
(py - cy) / fl_y)``; the *undistorted* coordinates of a point ``(X, Y, Z)`` in front of the camera are
``(X / Z, Y / Z)``. Coefficient tensors are ``[..., 6]`` in the order ``(k1, k2, k3, k4, p1, p2)``
(:data:`voxnerf.cameras.rules.COEFFICIENT_KEYS`); they broadcast against the points' leading dimensions.
Every function keeps its input's dtype (float32 in training, float64 in the synthetic generator) and device,
and returns finite values for any finite input: Newton steps are guarded, radii clamped.
The torch-free description of a lens (:class:`voxnerf.cameras.rules.Lens`) and its rules live in
:mod:`voxnerf.cameras.rules`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from voxnerf.cameras.rules import OPENCV, OPENCV_FISHEYE, Lens

PINHOLE_CODE, OPENCV_CODE, FISHEYE_CODE = 0, 1, 2
MODEL_CODES = {OPENCV: OPENCV_CODE, OPENCV_FISHEYE: FISHEYE_CODE}
NEWTON_ITERS = 12
MAX_RADIUS = 1e3
"""Undistorted radius (normalised units, ~89.94 degrees off axis) the OPENCV inverse never exceeds."""
MAX_THETA = math.pi
"""Largest angle (radians) off the optical axis the fisheye inverse returns."""
MAX_PINHOLE_THETA = math.atan(MAX_RADIUS)
MIN_SLOPE = 1e-3
"""Smallest |derivative| (|Jacobian determinant|) a Newton step divides by."""
_TINY = 1e-12

__all__ = [
    "LensBatch",
    "distort",
    "distort_fisheye",
    "distort_opencv",
    "fisheye_theta",
    "lens_directions",
    "undistort",
    "undistort_fisheye",
    "undistort_opencv",
]


# ------------------------------------------------------------------------------------------------ OPENCV


def _opencv_terms(xy: Tensor, coeffs: Tensor) -> tuple[Tensor, ...]:
    """Distorted ``(xd, yd)`` and the Jacobian ``d(xd, yd) / d(x, y)`` of the OPENCV model at ``xy``."""
    x, y = xy.unbind(-1)
    k1, k2, k3, _, p1, p2 = coeffs.unbind(-1)
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    slope = 2 * (k1 + r2 * (2 * k2 + 3 * k3 * r2))  # d radial / d r2, doubled
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    dxd_dx = radial + slope * x * x + 2 * p1 * y + 6 * p2 * x
    dxd_dy = slope * x * y + 2 * p1 * x + 2 * p2 * y
    dyd_dx = slope * x * y + 2 * p1 * x + 2 * p2 * y
    dyd_dy = radial + slope * y * y + 6 * p1 * y + 2 * p2 * x
    return xd, yd, dxd_dx, dxd_dy, dyd_dx, dyd_dy


def distort_opencv(xy: Tensor, coeffs: Tensor) -> Tensor:
    """OPENCV forward model: undistorted ``xy`` [..., 2] -> distorted [..., 2] (normalised, OpenCV axes).

    ``coeffs`` [..., 6] ``(k1, k2, k3, k4, p1, p2)``, k4 unused. Matches ``cv2.projectPoints``.
    """
    xd, yd = _opencv_terms(xy, coeffs)[:2]
    return torch.stack([xd, yd], dim=-1)


def _guarded(det: Tensor) -> Tensor:
    """``det`` with magnitude at least :data:`MIN_SLOPE`, its sign kept (0 counts as positive)."""
    sign = torch.where(det < 0, -torch.ones_like(det), torch.ones_like(det))
    return sign * det.abs().clamp_min(MIN_SLOPE)


def _clamp_radius(xy: Tensor, limit: float | Tensor) -> Tensor:
    """``xy`` [..., 2] scaled down where longer than ``limit`` (a number, or [..., 1])."""
    radius = torch.linalg.vector_norm(xy, dim=-1, keepdim=True)
    return xy * (limit / radius.clamp_min(limit))


def undistort_opencv(uv: Tensor, coeffs: Tensor, iters: int = NEWTON_ITERS) -> Tensor:
    """OPENCV inverse by Newton iteration: distorted ``uv`` [..., 2] -> undistorted [..., 2].

    Starts at ``uv`` and takes ``iters`` full Newton steps on ``distort_opencv(xy) - uv`` (a fixed count, so
    no device sync); a near-singular Jacobian is bounded away from 0, a step is at most the current radius
    plus one, and the result stays within :data:`MAX_RADIUS`. Where the model folds over (no inverse, e.g.
    strong barrel distortion past the image corners) the result is finite but meaningless.
    """
    xy = uv
    for _ in range(iters):
        xd, yd, a, b, c, d = _opencv_terms(xy, coeffs)
        fx, fy = xd - uv[..., 0], yd - uv[..., 1]
        det = _guarded(a * d - b * c)
        step = torch.stack([(d * fx - b * fy) / det, (a * fy - c * fx) / det], dim=-1)
        step = torch.nan_to_num(step, nan=0.0, posinf=0.0, neginf=0.0)
        bound = torch.linalg.vector_norm(xy, dim=-1, keepdim=True) + 1.0
        xy = _clamp_radius(xy - _clamp_radius(step, bound), MAX_RADIUS)
    return xy


# ------------------------------------------------------------------------------------------------ OPENCV_FISHEYE


def _theta_poly(theta: Tensor, coeffs: Tensor) -> tuple[Tensor, Tensor]:
    """``theta_d(theta)`` of the fisheye model and its derivative."""
    k1, k2, k3, k4 = coeffs.unbind(-1)[:4]
    t2 = theta * theta
    poly = 1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))
    slope = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
    return theta * poly, slope


def distort_fisheye(xy: Tensor, coeffs: Tensor) -> Tensor:
    """OPENCV_FISHEYE forward model: undistorted ``xy`` [..., 2] -> distorted [..., 2] (normalised).

    ``theta = atan(|xy|)``, ``theta_d`` the polynomial in ``theta`` (k1..k4; p1, p2 unused), the distorted
    point ``xy * theta_d / |xy|``. Matches ``cv2.fisheye.projectPoints``.
    """
    r = torch.linalg.vector_norm(xy, dim=-1)
    theta_d, _ = _theta_poly(torch.atan(r), coeffs)
    scale = torch.where(r > _TINY, theta_d / r.clamp_min(_TINY), torch.ones_like(r))
    return xy * scale[..., None]


def fisheye_theta(uv: Tensor, coeffs: Tensor, iters: int = NEWTON_ITERS) -> Tensor:
    """Angle off the optical axis [...] (radians, in ``[0, MAX_THETA]``) of distorted fisheye points
    ``uv`` [..., 2]: Newton's solution of ``theta_d(theta) = |uv|``, its slope bounded away from 0."""
    theta_d = torch.linalg.vector_norm(uv, dim=-1)
    theta = theta_d.clamp_max(MAX_THETA)
    for _ in range(iters):
        value, slope = _theta_poly(theta, coeffs)
        step = torch.nan_to_num((value - theta_d) / _guarded(slope), nan=0.0, posinf=0.0, neginf=0.0)
        theta = (theta - step.clamp(-1.0, 1.0)).clamp(0.0, MAX_THETA)
    return theta


def _fisheye_unit(uv: Tensor) -> tuple[Tensor, Tensor]:
    """``uv / |uv|`` (0 at the centre) [..., 2] and ``|uv|`` [...]."""
    r = torch.linalg.vector_norm(uv, dim=-1)
    return uv / r.clamp_min(_TINY)[..., None], r


def undistort_fisheye(uv: Tensor, coeffs: Tensor, iters: int = NEWTON_ITERS) -> Tensor:
    """OPENCV_FISHEYE inverse: distorted ``uv`` [..., 2] -> undistorted pinhole coordinates [..., 2].

    ``tan(theta) * uv / |uv|``; theta is clamped below 90 degrees (:data:`MAX_PINHOLE_THETA`), since a
    direction past it has no pinhole coordinates (:func:`lens_directions` has them all).
    """
    unit, _ = _fisheye_unit(uv)
    theta = fisheye_theta(uv, coeffs, iters).clamp_max(MAX_PINHOLE_THETA)
    return unit * torch.tan(theta)[..., None]


# ------------------------------------------------------------------------------------------------ both models


def distort(xy: Tensor, coeffs: Tensor, model: str) -> Tensor:
    """The forward model of ``model`` (``OPENCV`` or ``OPENCV_FISHEYE``): undistorted [..., 2] -> distorted."""
    return distort_opencv(xy, coeffs) if MODEL_CODES[model] == OPENCV_CODE else distort_fisheye(xy, coeffs)


def undistort(uv: Tensor, coeffs: Tensor, model: str, iters: int = NEWTON_ITERS) -> Tensor:
    """The inverse of ``model``: distorted [..., 2] -> undistorted pinhole coordinates [..., 2]."""
    if MODEL_CODES[model] == OPENCV_CODE:
        return undistort_opencv(uv, coeffs, iters)
    return undistort_fisheye(uv, coeffs, iters)


def _pinhole_dirs(uv: Tensor, coeffs: Tensor) -> Tensor:
    d = torch.cat([uv, torch.ones_like(uv[..., :1])], dim=-1)
    return d / torch.linalg.vector_norm(d, dim=-1, keepdim=True)


def _opencv_dirs(uv: Tensor, coeffs: Tensor) -> Tensor:
    return _pinhole_dirs(undistort_opencv(uv, coeffs), coeffs)


def _fisheye_dirs(uv: Tensor, coeffs: Tensor) -> Tensor:
    unit, _ = _fisheye_unit(uv)
    theta = fisheye_theta(uv, coeffs)
    return torch.cat([unit * torch.sin(theta)[..., None], torch.cos(theta)[..., None]], dim=-1)


_DIRECTIONS = {PINHOLE_CODE: _pinhole_dirs, OPENCV_CODE: _opencv_dirs, FISHEYE_CODE: _fisheye_dirs}


@dataclass(frozen=True)
class LensBatch:
    """The lenses of a batch of cameras, as tensors.

    ``coeffs``: float [N, 6] ``(k1, k2, k3, k4, p1, p2)`` (0 for a pinhole); ``codes``: int64 [N]
    (:data:`PINHOLE_CODE`, :data:`OPENCV_CODE`, :data:`FISHEYE_CODE`); ``models``: the codes present, known
    on the host so that picking the models to evaluate needs no device sync.
    """

    coeffs: Tensor
    codes: Tensor
    models: tuple[int, ...]

    @staticmethod
    def of(lenses: Sequence[Lens | None], device: torch.device | str = "cpu",
           dtype: torch.dtype = torch.float32) -> LensBatch | None:
        """The batch of ``lenses`` (None: a pinhole); None when none of them has a lens."""
        if all(lens is None for lens in lenses):
            return None
        codes = [PINHOLE_CODE if lens is None else MODEL_CODES[lens.model] for lens in lenses]
        coeffs = [(0.0,) * 6 if lens is None else lens.coefficients for lens in lenses]
        return LensBatch(torch.tensor(coeffs, dtype=dtype, device=device),
                         torch.tensor(codes, dtype=torch.int64, device=device), tuple(sorted(set(codes))))

    def select(self, index: Tensor) -> LensBatch:
        """The lenses of cameras ``index`` [R] (one per ray)."""
        return LensBatch(self.coeffs[index], self.codes[index], self.models)


def lens_directions(uv: Tensor, lens: LensBatch) -> Tensor:
    """Unit ray directions [N, 3] in OpenCV camera axes (x right, y down, z forward) of distorted
    normalised points ``uv`` [N, 2] (same dtype as ``coeffs``).

    ``lens`` holds one camera ([1, 6] coefficients, shared) or one per point ([N, 6]). OPENCV points go
    through :func:`undistort_opencv`; fisheye points get ``(sin theta * uv / |uv|, cos theta)``, which also
    covers directions past 90 degrees. Only the models present are evaluated.
    """
    dirs = {code: _DIRECTIONS[code](uv, lens.coeffs) for code in lens.models}
    out = dirs[lens.models[0]]
    for code in lens.models[1:]:
        out = torch.where((lens.codes == code)[..., None], dirs[code], out)
    return out
