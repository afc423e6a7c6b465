"""The rules a camera must follow, shared by scene loading, the CLI, the Python API and the REST service.

numpy only: the API process imports this module and must not load torch.

Errors are :class:`CameraError` with a message that names no file: each caller adds where the value came
from (scene loading raises ``SceneError`` naming transforms.json and the key, the CLI names the pose file,
the REST schema lets pydantic report the field).
"""

from __future__ import annotations

import math
import numbers
from dataclasses import asdict, dataclass

import numpy as np

# A rotation whose columns deviate from orthonormal (max |R^T R - I|) by at most this is re-orthonormalised;
# more is refused.
ROTATION_TOLERANCE = 0.05
# Above this deviation the rotation is replaced by its nearest orthonormal matrix (SVD), and scene loading
# tells the user; below it, it is rounding in the pose file and the pose is used as given.
REORTHONORMALISE_ABOVE = 1e-5
REPAIR_WARNING_ABOVE = REORTHONORMALISE_ABOVE
# Tolerance on the last row of a pose, [0, 0, 0, 1].
LAST_ROW_TOLERANCE = 1e-6


class CameraError(ValueError):
    """A pose or a camera is unusable. ``field`` names the value at fault when it is not the whole pose.

    ``str(err)`` is ``<field>: <message>`` (or the message alone); ``err.message`` is the message alone.
    """

    def __init__(self, message: str, field: str | None = None) -> None:
        self.message = message
        self.field = field
        super().__init__(f"{field}: {message}" if field else message)


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels; ``cx, cy`` in continuous pixel coordinates (centre of a WxH image is W/2)."""

    fl_x: float
    fl_y: float
    cx: float
    cy: float
    width: int
    height: int

    def scaled(self, factor: float) -> Intrinsics:
        """Intrinsics of the image resized by ``factor`` (0.5 halves the resolution)."""
        return Intrinsics(
            self.fl_x * factor,
            self.fl_y * factor,
            self.cx * factor,
            self.cy * factor,
            max(1, int(round(self.width * factor))),
            max(1, int(round(self.height * factor))),
        )

    def as_dict(self) -> dict:
        return asdict(self)


# ------------------------------------------------------------------------------------------------ numbers


def one_line(text: str) -> str:
    """``text`` on one line, at most about 80 characters, and encodable as UTF-8 (hostile input can hold
    anything, lone surrogates from ``\\udc80`` JSON escapes included: those become ``\\udc80`` again)."""
    text = text.replace("\n", " ").replace("\r", " ").encode("utf-8", "backslashreplace").decode("utf-8")
    return text if len(text) <= 80 else f"{text[:60]}... ({len(text)} characters)"


def short_repr(value) -> str:
    """``repr(value)`` as :func:`one_line` gives it, for quoting a bad value in an error message."""
    return one_line(repr(value))


def _is_number(value) -> bool:
    """A real number that is not a bool (numpy scalars included)."""
    return isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))


def as_finite(value) -> float | None:
    """``value`` as a finite float, or None for non-numbers, bools, NaN, inf and integers too large for a float."""
    if not _is_number(value):
        return None
    try:
        number = float(value)
    except OverflowError:  # a JSON integer literal of hundreds of digits
        return None
    return number if math.isfinite(number) else None


def finite_number(value, field: str) -> float:
    """``value`` as a float; CameraError naming ``field`` unless it is a finite number."""
    number = as_finite(value)
    if number is None:
        raise CameraError(f"must be a finite number, got {short_repr(value)}", field)
    return number


def positive_number(value, field: str) -> float:
    """``value`` as a float; CameraError naming ``field`` unless it is a finite number > 0."""
    number = as_finite(value)
    if number is None or number <= 0:
        raise CameraError(f"must be a positive finite number, got {short_repr(value)}", field)
    return number


def pixel_count(value, field: str) -> int:
    """``value`` as an int; CameraError naming ``field`` unless it is a positive whole number (2.0 is 2)."""
    number = as_finite(value)
    if number is None or number <= 0 or number != int(number):
        raise CameraError(f"must be a positive integer pixel count, got {short_repr(value)}", field)
    return int(number)


# ------------------------------------------------------------------------------------------------ poses


def _matrix_of_numbers(value) -> np.ndarray:
    """``value`` (nested lists or tuples, or an array) as a float64 array; CameraError for anything else."""
    if isinstance(value, np.ndarray):
        if value.dtype.kind not in "iuf":
            raise CameraError(f"must be a 4x4 matrix of numbers, got an array of {value.dtype}")
        return value.astype(np.float64)
    shape_hint = "must be a 4x4 matrix (a list of 4 rows of 4 numbers)"
    if not isinstance(value, (list, tuple)) or not all(isinstance(row, (list, tuple)) for row in value):
        raise CameraError(f"{shape_hint}, got {short_repr(value)}")
    if len(value) != 4 or any(len(row) != 4 for row in value):
        lengths = "/".join(str(n) for n in sorted({len(row) for row in value})) or "0"
        raise CameraError(f"{shape_hint}, got {len(value)} rows of {lengths} numbers")
    for row in value:
        for x in row:
            if not _is_number(x):
                raise CameraError(f"must hold numbers only, got {short_repr(x)}")
    try:
        return np.array([[float(x) for x in row] for row in value], dtype=np.float64)
    except OverflowError:
        raise CameraError("holds an integer too large for a float") from None


def validate_pose_deviation(value) -> tuple[np.ndarray, float]:
    """:func:`validate_pose`, also returning the rotation's deviation from orthonormal before the repair.

    The deviation is ``max |R^T R - I|`` of the given rotation; the pose came back re-orthonormalised when it
    exceeds :data:`REORTHONORMALISE_ABOVE`.
    """
    mat = _matrix_of_numbers(value)
    if mat.shape != (4, 4):
        raise CameraError(f"must be a 4x4 matrix (a list of 4 rows of 4 numbers), got shape {list(mat.shape)}")
    if not np.isfinite(mat).all():
        raise CameraError("contains NaN or inf")
    if not np.allclose(mat[3], [0, 0, 0, 1], atol=LAST_ROW_TOLERANCE):
        raise CameraError(f"last row must be [0, 0, 0, 1], got {mat[3].tolist()}")
    rot = mat[:3, :3]
    deviation = float(np.abs(rot.T @ rot - np.eye(3)).max())
    det = float(np.linalg.det(rot))
    if deviation > ROTATION_TOLERANCE or det <= 0:
        raise CameraError(
            f"rotation is not a proper orthonormal matrix (max |R^T R - I| = {deviation:.3g}, det = {det:.3g})"
        )
    if deviation > REORTHONORMALISE_ABOVE:
        u, _, vt = np.linalg.svd(rot)
        mat[:3, :3] = u @ vt
    return mat, deviation


def validate_pose(value) -> np.ndarray:
    """A camera-to-world pose checked and returned as float64 ``[4, 4]``.

    ``value`` is a nested list (as parsed from JSON) or an array. It must be 4x4, finite, numbers only (bools
    refused), with last row ``[0, 0, 0, 1]`` and a proper rotation (det > 0) whose deviation from orthonormal
    is at most :data:`ROTATION_TOLERANCE`; a deviating rotation comes back re-orthonormalised by SVD.
    Raises CameraError otherwise.
    """
    return validate_pose_deviation(value)[0]


# ------------------------------------------------------------------------------------------------ intrinsics


def resolve_intrinsics(
    default: Intrinsics,
    *,
    width=None,
    height=None,
    fl_x=None,
    fl_y=None,
    cx=None,
    cy=None,
    max_pixels: int | None = None,
) -> Intrinsics:
    """The camera to render: given values, the rest from ``default``.

    ``width`` and ``height`` come together (or neither: the default size). Every missing value is the
    default's scaled by ``width / default.width`` (x: ``fl_x``, ``cx``) or ``height / default.height``
    (y: ``fl_y``, ``cy``). ``fl_x``, ``fl_y`` must be positive finite numbers, ``cx``, ``cy`` finite numbers,
    ``width``, ``height`` positive whole numbers; bools are refused. ``max_pixels`` bounds ``width x height``
    of the result. Raises CameraError naming the field at fault.
    """
    if (width is None) != (height is None):
        raise CameraError("give width and height together (or neither, for the scene's size)", "width, height")
    w = default.width if width is None else pixel_count(width, "width")
    h = default.height if height is None else pixel_count(height, "height")
    if max_pixels is not None and w * h > max_pixels:
        raise CameraError(f"{w}x{h} exceeds the limit of {max_pixels} pixels", "width, height")
    sx, sy = w / default.width, h / default.height
    return Intrinsics(
        fl_x=default.fl_x * sx if fl_x is None else positive_number(fl_x, "fl_x"),
        fl_y=default.fl_y * sy if fl_y is None else positive_number(fl_y, "fl_y"),
        cx=default.cx * sx if cx is None else finite_number(cx, "cx"),
        cy=default.cy * sy if cy is None else finite_number(cy, "cy"),
        width=w,
        height=h,
    )
