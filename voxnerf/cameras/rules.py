"""The rules a camera must follow, shared by scene loading, the CLI, the Python API and the REST service.

numpy only: the API process imports this module and must not load torch.

Errors are :class:`CameraError` with a message that names no file: each caller adds where the value came
from (scene loading raises ``SceneError`` naming transforms.json and the key, the CLI names the pose file,
the REST schema lets pydantic report the field).
"""

from __future__ import annotations

import math
import numbers
from dataclasses import asdict, dataclass, replace

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


# Lens models as nerfstudio names them in transforms.json (``camera_model``), with the OpenCV coefficients each
# one uses; a coefficient a model does not use must be absent or zero.
PINHOLE, OPENCV, OPENCV_FISHEYE = "PINHOLE", "OPENCV", "OPENCV_FISHEYE"
CAMERA_MODELS = (PINHOLE, OPENCV, OPENCV_FISHEYE)
COEFFICIENT_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
MODEL_COEFFICIENTS = {PINHOLE: (), OPENCV: ("k1", "k2", "k3", "p1", "p2"), OPENCV_FISHEYE: ("k1", "k2", "k3", "k4")}
# The keys that ask a render for a lens (pose file of ``voxnerf render``, ``POST /render``): absent = pinhole.
LENS_KEYS = ("camera_model", *COEFFICIENT_KEYS)
# Pose-file keys (``voxnerf render --pose``, ``voxnerf remote render --pose``) of the intrinsics and the lens, by
# resolve_intrinsics' argument name (which POST /render's body uses too).
POSE_FILE_KEYS = {"fl_x": "fl_x", "fl_y": "fl_y", "cx": "cx", "cy": "cy", "width": "w", "height": "h",
                  **{key: key for key in LENS_KEYS}}


@dataclass(frozen=True)
class Lens:
    """OpenCV lens distortion, as nerfstudio's ``camera_model`` (OpenCV's conventions, normalised coordinates).

    ``OPENCV``: ``x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2)``, and likewise for y
    (``p1 (r^2 + 2 y^2) + 2 p2 x y``); ``k4`` must be 0. ``OPENCV_FISHEYE``: ``theta = atan(r)``,
    ``theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)``, ``x_d = theta_d / r * x``;
    ``p1, p2`` must be 0. Scaling an image leaves the coefficients unchanged. Invalid values raise
    :class:`CameraError` naming the coefficient (or ``camera_model``).
    """

    model: str
    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    k4: float = 0.0
    p1: float = 0.0
    p2: float = 0.0

    def __post_init__(self) -> None:
        if self.model not in (OPENCV, OPENCV_FISHEYE):
            raise CameraError(f"unsupported lens model {short_repr(self.model)} ({OPENCV} or {OPENCV_FISHEYE})",
                              "camera_model")
        for key in COEFFICIENT_KEYS:
            value = finite_number(getattr(self, key), key)
            if value != 0 and key not in MODEL_COEFFICIENTS[self.model]:
                raise CameraError(f"{self.model} has no {key} (got {value}; give it 0 or leave it out)", key)
            object.__setattr__(self, key, value)

    @property
    def coefficients(self) -> tuple[float, float, float, float, float, float]:
        """``(k1, k2, k3, k4, p1, p2)``."""
        return tuple(getattr(self, key) for key in COEFFICIENT_KEYS)

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class Intrinsics:
    """Intrinsics in pixels; ``cx, cy`` in continuous pixel coordinates (centre of a WxH image is W/2).

    ``lens`` is None for a pinhole camera; otherwise pixels map to rays through its inverse distortion.
    A dict for ``lens`` (as :meth:`as_dict` writes it, e.g. in a checkpoint) is read as a :class:`Lens`.
    """

    fl_x: float
    fl_y: float
    cx: float
    cy: float
    width: int
    height: int
    lens: Lens | None = None

    def __post_init__(self) -> None:
        if isinstance(self.lens, dict):
            object.__setattr__(self, "lens", Lens(**self.lens))

    def scaled(self, factor: float) -> Intrinsics:
        """Intrinsics of the image resized by ``factor`` (0.5 halves the resolution); the lens is unchanged."""
        return Intrinsics(
            self.fl_x * factor,
            self.fl_y * factor,
            self.cx * factor,
            self.cy * factor,
            max(1, int(round(self.width * factor))),
            max(1, int(round(self.height * factor))),
            self.lens,
        )

    def undistorted(self) -> Intrinsics:
        """The same camera without its lens: the undistorted (pinhole) view."""
        return replace(self, lens=None)

    def as_dict(self) -> dict:
        """The fields as a dict; ``lens`` only when there is one (so a pinhole's dict is what it always was)."""
        values = asdict(self)
        if self.lens is None:
            del values["lens"]
        return values


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


def lens_of(model, coefficients: dict) -> Lens | None:
    """The lens of ``camera_model`` ``model`` with ``coefficients`` (``k1 ... p2`` -> value; absent or None = 0).

    None for ``PINHOLE`` (whose coefficients must all be zero), a :class:`Lens` for ``OPENCV`` and
    ``OPENCV_FISHEYE``. Raises CameraError naming ``camera_model`` for any other model, or the coefficient at
    fault (not a finite number, non-zero for a pinhole, not one the model has).
    """
    if not isinstance(model, str) or model not in CAMERA_MODELS:
        raise CameraError(f"unsupported camera model {short_repr(model)} ({', '.join(CAMERA_MODELS)})",
                          "camera_model")
    values = {key: finite_number(coefficients[key], key)
              for key in COEFFICIENT_KEYS if coefficients.get(key) is not None}
    if model == PINHOLE:
        for key, value in values.items():
            if value != 0:
                raise CameraError(f"distortion ({key}={value}) given with camera_model PINHOLE", key)
        return None
    return Lens(model, **values)


def resolve_lens(default: Lens | None, camera_model=None, **coefficients) -> Lens | None:
    """The lens to render through: none (the undistorted pinhole view) unless ``camera_model`` is given.

    With ``camera_model`` ``OPENCV`` or ``OPENCV_FISHEYE``, each coefficient left out (None) is ``default``'s
    when ``default`` is a lens of that model (the trained camera's), else 0. Coefficients without
    ``camera_model`` are refused (CameraError naming the coefficient), as are those :func:`lens_of` refuses.
    """
    given = {key: value for key, value in coefficients.items() if value is not None}
    unknown = set(coefficients) - set(COEFFICIENT_KEYS)
    if unknown:
        raise TypeError(f"unknown lens coefficients {sorted(unknown)}")
    if camera_model is None:
        if given:
            key = next(iter(given))
            raise CameraError("give camera_model with distortion coefficients (without it a render is the "
                              "undistorted pinhole view)", key)
        return None
    if default is not None and default.model == camera_model:
        given = {**{key: getattr(default, key) for key in COEFFICIENT_KEYS}, **given}
    return lens_of(camera_model, given)


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
    camera_model=None,
    **coefficients,
) -> Intrinsics:
    """The camera to render: given values, the rest from ``default``.

    ``width`` and ``height`` come together (or neither: the default size). Every missing value is the
    default's scaled by ``width / default.width`` (x: ``fl_x``, ``cx``) or ``height / default.height``
    (y: ``fl_y``, ``cy``). ``fl_x``, ``fl_y`` must be positive finite numbers, ``cx``, ``cy`` finite numbers,
    ``width``, ``height`` positive whole numbers; bools are refused. ``max_pixels`` bounds ``width x height``
    of the result. The lens is :func:`resolve_lens`'s of ``camera_model`` and ``coefficients`` (``k1 k2 k3 k4
    p1 p2``): without ``camera_model`` the result is a pinhole, the undistorted view of a distorted default.
    Raises CameraError naming the field at fault.
    """
    lens = resolve_lens(default.lens, camera_model, **coefficients)
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
        lens=lens,
    )
