"""Camera paths for videos: nerfstudio's camera-path JSON, and paths through or around a scene's cameras.

numpy only (no torch, not even through another module): the API process imports this module to validate
camera paths before it queues a render.

A :class:`CameraPath` holds N camera-to-world poses ``[N, 4, 4]`` float64 in *scene units* (OpenGL axes: the
camera looks along -Z, +Y up, as in transforms.json) and one pinhole camera per frame, all of one size.

nerfstudio's camera-path JSON (what its viewer's "Render" panel writes, ``ns-render camera-path`` reads):

- top level: ``render_width``, ``render_height`` (pixels), ``fps``, ``seconds`` (the viewer writes
  ``int(fps * seconds)`` frames), ``camera_type`` (only ``perspective`` is rendered here; nerfstudio's
  fisheye, equirectangular, omnidirectional and vr180 are refused), and keys this module ignores
  (``keyframes``, ``smoothness_value``, ``is_cycle``, ``default_fov``, ``crop``, ``render_time``...).
- ``camera_path[]``: ``camera_to_world`` (16 numbers, the row-major 4x4; a nested 4x4 is read too, as
  nerfstudio's ``view(4, 4)`` does), ``fov`` (vertical, degrees) and ``aspect``. The image is
  ``render_width x render_height`` whatever ``aspect`` says (nerfstudio's renderer ignores it, and its Blender
  add-on writes 1), so ``aspect`` is only checked to be a positive number. The camera is
  ``fl_x = fl_y = 0.5 H / tan(fov / 2)``, ``cx = W / 2``, ``cy = H / 2``.
- VoxNeRF's extension: an entry may carry ``fl_x``, ``fl_y``, ``cx``, ``cy`` (pixels), which replace the values
  derived from ``fov``. :meth:`CameraPath.to_nerfstudio` writes them only for a camera that ``fov`` cannot
  describe (non-square pixels, off-centre principal point), so the saved path renders the same images here;
  nerfstudio ignores them.
- frames = ``len(camera_path)``. ``fps`` is the frame rate; when only ``seconds`` is given it is
  ``frames / seconds`` (what nerfstudio's renderer plays). Given both, ``fps * seconds`` must be within one
  frame of ``frames`` (the viewer truncates), else the file is refused naming ``seconds``.

Poses in a viewer's path are in nerfstudio's *dataparser* frame. ``dataparser_transforms.json`` of the
nerfstudio run (``{"transform": 3x4, "scale": s}``) maps them back to the scene: nerfstudio applied
``c2w' = [transform; 0 0 0 1] @ c2w`` and then ``c2w'[:3, 3] *= scale``; here positions are divided by ``scale``
and the homogeneous transform inverted. (When the scene's transforms.json has ``applied_transform``,
nerfstudio's saved transform maps from the coordinates *before* it, as its ``transform_poses_to_original_space``
does.)

Every refusal is a :class:`CameraPathError` whose message names the key, e.g.
``camera_path[2].fov: must be a number in (0, 180), got 190``.
"""

from __future__ import annotations

import json
import math
import numbers
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from voxnerf.cameras.rules import (
    ROTATION_TOLERANCE,
    CameraError,
    Intrinsics,
    as_finite,
    finite_number,
    pixel_count,
    positive_number,
    short_repr,
    validate_pose,
)
from voxnerf.errors import VoxNeRFError

MAX_FRAMES = 10_000
MAX_FPS = 1000.0
PERSPECTIVE = "perspective"
# Knot spacing of the centripetal Catmull-Rom spline through the cameras: |P_i+1 - P_i| ** ALPHA.
CATMULL_ROM_ALPHA = 0.5
# Points per spline segment for its arc-length table (constant speed along a segment).
ARC_SAMPLES = 64


class CameraPathError(VoxNeRFError, ValueError):
    """A camera path is unusable. ``str(err)`` is one line ``[<file>: ]<key>: <message>``.

    ``key`` names the value at fault (``camera_path[3].camera_to_world``, ``render_width``...), ``file`` the file
    it came from when one is known (:func:`read_nerfstudio` sets it).
    """

    def __init__(self, message: str, key: str | None = None, file: str | Path | None = None) -> None:
        self.message = message
        self.key = key
        self.file = None if file is None else str(file)
        super().__init__(": ".join(part for part in (self.file, key, message) if part))

    def in_file(self, file: str | Path) -> CameraPathError:
        """The same error, naming ``file``."""
        return CameraPathError(self.message, self.key, file)


def _checked(rule, value, key: str):
    """``rule(value, key)`` of :mod:`voxnerf.cameras.rules`, its CameraError as a CameraPathError naming ``key``."""
    try:
        return rule(value, key)
    except CameraError as err:
        raise CameraPathError(err.message, err.field or key) from None


def _checked_pose(value, key: str) -> np.ndarray:
    """:func:`validate_pose` of ``value``, refusals naming ``key``."""
    try:
        return validate_pose(value)
    except CameraError as err:
        raise CameraPathError(str(err), key) from None


def check_frame_count(n: int, max_frames: int, *, key: str = "frames") -> None:
    """CameraPathError naming ``key`` unless ``n`` is a whole number of frames in ``[1, max_frames]``."""
    whole = isinstance(n, numbers.Integral) and not isinstance(n, (bool, np.bool_))
    if not whole or not 1 <= n <= max_frames:
        raise CameraPathError(f"must be a whole number of frames from 1 to {max_frames}, got {short_repr(n)}", key)


def _check_fps(fps, key: str = "fps") -> float:
    value = as_finite(fps)
    if value is None or not 0 < value <= MAX_FPS:
        raise CameraPathError(f"must be a number of frames per second in (0, {MAX_FPS:g}], got {short_repr(fps)}",
                              key)
    return value


# ------------------------------------------------------------------------------------------------ the path


@dataclass
class CameraPath:
    """Frames of a video: poses ``[N, 4, 4]`` float64 camera-to-world (OpenGL axes, scene units), one pinhole
    :class:`Intrinsics` per frame (all of one size), played at ``fps``.

    Construction checks and normalises: every pose by :func:`validate_pose` (slightly skewed rotations come back
    re-orthonormalised), N >= 1 intrinsics of one size without a lens, ``fps`` in (0, MAX_FPS]. Refusals are
    CameraPathError naming ``poses[i]``, ``intrinsics[i]`` or ``fps``.
    """

    poses: np.ndarray
    intrinsics: list[Intrinsics]
    fps: float = 30.0

    def __post_init__(self) -> None:
        poses = np.asarray(self.poses, dtype=np.float64)
        if poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(poses) == 0:
            raise CameraPathError(f"must be an array [N, 4, 4] with N >= 1, got shape {list(poses.shape)}", "poses")
        self.poses = np.stack([_checked_pose(pose, f"poses[{i}]") for i, pose in enumerate(poses)])
        self.intrinsics = list(self.intrinsics)
        if len(self.intrinsics) != len(poses):
            raise CameraPathError(f"{len(self.intrinsics)} cameras for {len(poses)} poses", "intrinsics")
        first = self.intrinsics[0]
        for i, intr in enumerate(self.intrinsics):
            if not isinstance(intr, Intrinsics) or intr.lens is not None:
                raise CameraPathError("must be a pinhole Intrinsics (a path renders undistorted views)",
                                      f"intrinsics[{i}]")
            if (intr.width, intr.height) != (first.width, first.height):
                raise CameraPathError(f"{intr.width}x{intr.height} differs from the first frame's "
                                      f"{first.width}x{first.height}: a video has one size", f"intrinsics[{i}]")
        self.fps = _check_fps(self.fps)

    def __len__(self) -> int:
        return len(self.poses)

    @property
    def seconds(self) -> float:
        """Duration when played at ``fps``."""
        return len(self) / self.fps

    @property
    def size(self) -> tuple[int, int]:
        """``(width, height)`` of every frame, pixels."""
        return self.intrinsics[0].width, self.intrinsics[0].height

    def to_nerfstudio(self) -> dict:
        """nerfstudio's camera-path JSON of this path (poses in scene units); :func:`parse_nerfstudio` reads it
        back to the same path. ``fl_x fl_y cx cy`` are written for frames whose camera ``fov`` cannot describe."""
        width, height = self.size
        return {
            "camera_type": PERSPECTIVE,
            "render_width": width,
            "render_height": height,
            "fps": self.fps,
            "seconds": self.seconds,
            "camera_path": [_entry_json(pose, intr) for pose, intr in zip(self.poses, self.intrinsics, strict=True)],
        }


def fov_of(intrinsics: Intrinsics) -> float:
    """Vertical field of view in degrees: ``2 atan(H / (2 fl_y))``."""
    return math.degrees(2 * math.atan(0.5 * intrinsics.height / intrinsics.fl_y))


def intrinsics_of_fov(fov: float, width: int, height: int) -> Intrinsics:
    """nerfstudio's camera of a vertical ``fov`` (degrees): square pixels, principal point at the centre."""
    focal = 0.5 * height / math.tan(math.radians(fov) / 2)
    return Intrinsics(focal, focal, width / 2, height / 2, width, height)


def _is_fov_camera(intr: Intrinsics) -> bool:
    """Whether ``fov`` describes ``intr``: square pixels, principal point at the image centre (to 1e-9)."""
    fov_camera = intrinsics_of_fov(fov_of(intr), intr.width, intr.height)
    return all(math.isclose(getattr(intr, name), getattr(fov_camera, name), rel_tol=1e-9, abs_tol=1e-9)
               for name in ("fl_x", "fl_y", "cx", "cy"))


def _entry_json(pose: np.ndarray, intr: Intrinsics) -> dict:
    entry = {"camera_to_world": pose.reshape(-1).tolist(), "fov": fov_of(intr), "aspect": intr.width / intr.height}
    if not _is_fov_camera(intr):
        entry.update(fl_x=intr.fl_x, fl_y=intr.fl_y, cx=intr.cx, cy=intr.cy)
    return entry


# ------------------------------------------------------------------------------------------------ parsing


def _render_size(data: dict, max_pixels: int | None) -> tuple[int, int]:
    for key in ("render_width", "render_height"):
        if key not in data:
            raise CameraPathError("missing", key)
    width = _checked(pixel_count, data["render_width"], "render_width")
    height = _checked(pixel_count, data["render_height"], "render_height")
    if max_pixels is not None and width * height > max_pixels:
        raise CameraPathError(f"{width}x{height} exceeds the limit of {max_pixels} pixels",
                              "render_width, render_height")
    return width, height


def _check_camera_type(value) -> None:
    if value is not None and (not isinstance(value, str) or value.lower() != PERSPECTIVE):
        raise CameraPathError(f"only {PERSPECTIVE!r} cameras are rendered, got {short_repr(value)}", "camera_type")


def _frame_rate(data: dict, n_frames: int) -> float:
    """``fps`` of the file, or ``frames / seconds`` when only ``seconds`` is given; checks they agree."""
    fps, seconds = data.get("fps"), data.get("seconds")
    if fps is None and seconds is None:
        raise CameraPathError("missing (give fps, or seconds for the whole path)", "fps")
    if seconds is not None:
        seconds = _checked(positive_number, seconds, "seconds")
    if fps is None:
        return _check_fps(n_frames / seconds, "seconds")
    fps = _check_fps(fps)
    if seconds is not None and abs(fps * seconds - n_frames) > 1 + 1e-6:
        raise CameraPathError(f"{seconds:g} s at {fps:g} fps is {fps * seconds:g} frames, but camera_path has "
                              f"{n_frames}", "seconds")
    return fps


def _matrix_value(value, key: str):
    """``camera_to_world`` as nested 4x4 lists: 16 numbers row-major, or already 4 rows of 4."""
    if value is None:
        raise CameraPathError("missing", key)
    if isinstance(value, list) and value and not isinstance(value[0], list):
        if len(value) != 16:
            raise CameraPathError(f"must be 16 numbers (the row-major 4x4 matrix), got {len(value)}", key)
        return [value[row * 4 : row * 4 + 4] for row in range(4)]
    return value


def _fov(value, key: str) -> float:
    fov = as_finite(value)
    if fov is None or not 0 < fov < 180:
        raise CameraPathError(f"must be a number in (0, 180) degrees, got {short_repr(value)}", key)
    return fov


def _entry_camera(entry: dict, key: str, width: int, height: int) -> tuple[np.ndarray, Intrinsics]:
    """Pose and camera of one ``camera_path`` entry."""
    if not isinstance(entry, dict):
        raise CameraPathError(f"must be an object with camera_to_world and fov, got {short_repr(entry)}", key)
    pose = _checked_pose(_matrix_value(entry.get("camera_to_world"), f"{key}.camera_to_world"),
                         f"{key}.camera_to_world")
    if "fov" not in entry:
        raise CameraPathError("missing", f"{key}.fov")
    camera = intrinsics_of_fov(_fov(entry["fov"], f"{key}.fov"), width, height)
    if entry.get("aspect") is not None:
        _checked(positive_number, entry["aspect"], f"{key}.aspect")
    given = {name: entry[name] for name in ("fl_x", "fl_y", "cx", "cy") if entry.get(name) is not None}
    for name in given:
        rule = positive_number if name.startswith("fl") else finite_number
        given[name] = _checked(rule, given[name], f"{key}.{name}")
    return pose, Intrinsics(**{**camera.as_dict(), **given})


def _dataparser_transform(data) -> tuple[np.ndarray, float]:
    """The homogeneous ``[4, 4]`` transform and the scale of a ``dataparser_transforms.json`` document."""
    if not isinstance(data, dict):
        raise CameraPathError("must be a JSON object with transform and scale")
    for key in ("transform", "scale"):
        if key not in data:
            raise CameraPathError("missing", key)
    rows = data["transform"]
    if not isinstance(rows, list) or len(rows) != 3 or not all(isinstance(r, list) and len(r) == 4 for r in rows):
        raise CameraPathError(f"must be 3 rows of 4 numbers, got {short_repr(rows)}", "transform")
    for row in rows:
        for x in row:
            if as_finite(x) is None:
                raise CameraPathError(f"must hold finite numbers only, got {short_repr(x)}", "transform")
    matrix = np.eye(4)
    matrix[:3] = np.array(rows, dtype=np.float64)
    rot = matrix[:3, :3]
    if np.abs(rot.T @ rot - np.eye(3)).max() > ROTATION_TOLERANCE or np.linalg.det(rot) <= 0:
        raise CameraPathError("its first 3 columns must be a rotation (orthonormal, det > 0)", "transform")
    return matrix, _checked(positive_number, data["scale"], "scale")


def from_dataparser_frame(poses: np.ndarray, transform: np.ndarray, scale: float) -> np.ndarray:
    """Poses ``[N, 4, 4]`` in nerfstudio's dataparser frame -> scene units (the inverse of ``c2w' = T @ c2w``,
    then ``positions *= scale``). ``transform``: homogeneous ``[4, 4]``."""
    unscaled = np.array(poses, dtype=np.float64, copy=True)
    unscaled[:, :3, 3] /= scale
    return np.linalg.inv(transform) @ unscaled


def to_dataparser_frame(poses: np.ndarray, transform: np.ndarray, scale: float) -> np.ndarray:
    """Scene poses ``[N, 4, 4]`` -> nerfstudio's dataparser frame, as its dataparser maps them."""
    mapped = transform @ np.asarray(poses, dtype=np.float64)
    mapped[:, :3, 3] *= scale
    return mapped


def parse_nerfstudio(
    data: dict, *, dataparser_transforms: dict | None = None, max_frames: int = MAX_FRAMES,
    max_pixels: int | None = None,
) -> CameraPath:
    """A camera path from nerfstudio's camera-path JSON (parsed), see the module's docstring.

    ``dataparser_transforms``: the parsed ``dataparser_transforms.json`` of the nerfstudio run whose viewer wrote
    the path; its poses are then mapped back to scene units. ``max_frames`` bounds ``len(camera_path)``,
    ``max_pixels`` bounds ``render_width * render_height``. Raises CameraPathError naming the key.
    """
    if not isinstance(data, dict):
        raise CameraPathError(f"must be a JSON object with camera_path, got {short_repr(data)}")
    _check_camera_type(data.get("camera_type"))
    width, height = _render_size(data, max_pixels)
    entries = data.get("camera_path")
    if not isinstance(entries, list):
        raise CameraPathError("missing" if entries is None else "must be a list of cameras", "camera_path")
    check_frame_count(len(entries), max_frames, key="camera_path")
    fps = _frame_rate(data, len(entries))
    cameras = [_entry_camera(entry, f"camera_path[{i}]", width, height) for i, entry in enumerate(entries)]
    poses = np.stack([pose for pose, _ in cameras])
    if dataparser_transforms is not None:
        poses = from_dataparser_frame(poses, *_dataparser_transform(dataparser_transforms))
    return CameraPath(poses, [camera for _, camera in cameras], fps)


def _read_json(path: Path):
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError, RecursionError) as exc:  # ValueError: bad UTF-8 or JSON
        raise CameraPathError(f"cannot read JSON ({short_repr(str(exc))})", file=path) from None


def read_nerfstudio(path: Path, *, dataparser_transforms: Path | None = None, **limits) -> CameraPath:
    """:func:`parse_nerfstudio` of the file ``path`` (and of ``dataparser_transforms``, a file, when given);
    errors name the file at fault. ``limits``: ``max_frames``, ``max_pixels``."""
    transforms = None
    if dataparser_transforms is not None:
        transforms = _read_json(dataparser_transforms)
        try:
            _dataparser_transform(transforms)
        except CameraPathError as err:
            raise err.in_file(dataparser_transforms) from None
    data = _read_json(path)
    try:
        return parse_nerfstudio(data, dataparser_transforms=transforms, **limits)
    except CameraPathError as err:
        raise err.in_file(path) from None


# ------------------------------------------------------------------------------------------------ rotations


def _quaternions(rotations: np.ndarray) -> np.ndarray:
    """Unit quaternions ``[N, 4]`` (w, x, y, z) of rotation matrices ``[N, 3, 3]`` (Shepperd's method)."""
    quats = np.empty((len(rotations), 4))
    for i, r in enumerate(rotations):
        trace = np.trace(r)
        k = int(np.argmax([trace, r[0, 0], r[1, 1], r[2, 2]]))
        if k == 0:
            s = 2 * math.sqrt(1 + trace)
            q = [s / 4, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
        else:
            a, b, c = k - 1, k % 3, (k + 1) % 3
            s = 2 * math.sqrt(1 + r[a, a] - r[b, b] - r[c, c])
            q = [0.0] * 4
            q[0] = (r[c, b] - r[b, c]) / s
            q[1 + a] = s / 4
            q[1 + b] = (r[b, a] + r[a, b]) / s
            q[1 + c] = (r[c, a] + r[a, c]) / s
        quats[i] = q
    return quats / np.linalg.norm(quats, axis=1, keepdims=True)


def _rotation_matrices(quats: np.ndarray) -> np.ndarray:
    """Rotation matrices ``[N, 3, 3]`` of quaternions ``[N, 4]`` (w, x, y, z; normalised here)."""
    w, x, y, z = (quats / np.linalg.norm(quats, axis=1, keepdims=True)).T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], 1)


def slerp(r0: np.ndarray, r1: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Rotations ``[T, 3, 3]`` along the shortest arc from ``r0`` to ``r1`` ([3, 3] each) at fractions ``t`` [T]."""
    q0, q1 = _quaternions(np.stack([r0, r1]))
    dot = float(q0 @ q1)
    if dot < 0:  # q and -q are the same rotation: take the shorter way round
        q1, dot = -q1, -dot
    t = np.asarray(t, dtype=np.float64)[:, None]
    angle = math.acos(min(dot, 1.0))
    if angle < 1e-9:
        quats = q0 * (1 - t) + q1 * t
    else:
        quats = (np.sin((1 - t) * angle) * q0 + np.sin(t * angle) * q1) / math.sin(angle)
    return _rotation_matrices(quats)


def rotation_angle(r0: np.ndarray, r1: np.ndarray) -> float:
    """Angle in radians of the rotation taking ``r0`` to ``r1`` ([3, 3] each), accurate near 0 and pi alike
    (from both its sine and its cosine: ``acos`` of the cosine alone loses half the digits of a small angle)."""
    r = r0.T @ r1
    sin2 = np.linalg.norm([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])  # 2 sin(angle)
    return math.atan2(sin2, np.trace(r) - 1.0)  # atan2(2 sin, 2 cos)


# ------------------------------------------------------------------------------------------------ interpolation


def _catmull_rom_tangents(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Hermite tangents ``[K-1, 3]`` at the start and end of each segment of the centripetal Catmull-Rom
    spline through ``points`` [K, 3] (ends extended by reflection), scaled to a unit segment parameter."""
    ext = np.concatenate([2 * points[:1] - points[1:2], points, 2 * points[-1:] - points[-2:-1]])
    # knot spacing |P_i+1 - P_i|^alpha; a tiny floor keeps repeated points finite (their terms are 0 / floor)
    scale = max(1.0, float(np.abs(points).max()))
    dt = np.maximum(np.linalg.norm(np.diff(ext, axis=0), axis=1) ** CATMULL_ROM_ALPHA, 1e-12 * scale)
    chord = np.diff(ext, axis=0) / dt[:, None]  # (P_i+1 - P_i) / dt_i
    # tangent at P_i (ext index i+1) in knot units, from the neighbours' chords (Yuksel et al.)
    tangent = (chord[:-1] * dt[1:, None] + chord[1:] * dt[:-1, None]) / (dt[:-1] + dt[1:])[:, None]
    seg_dt = dt[1:-1, None]  # segment i runs from points[i] to points[i+1]
    return tangent[:-1] * seg_dt, tangent[1:] * seg_dt


def _hermite(p0: np.ndarray, p1: np.ndarray, m0: np.ndarray, m1: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Points ``[U, 3]`` of the cubic Hermite segment at parameters ``u`` [U] in [0, 1]."""
    u = u[:, None]
    u2, u3 = u * u, u * u * u
    return (2 * u3 - 3 * u2 + 1) * p0 + (u3 - 2 * u2 + u) * m0 + (-2 * u3 + 3 * u2) * p1 + (u3 - u2) * m1


def _constant_speed(p0, p1, m0, m1, fractions: np.ndarray) -> np.ndarray:
    """Segment parameters at which the segment has covered ``fractions`` [F] of its arc length."""
    u = np.linspace(0.0, 1.0, ARC_SAMPLES + 1)
    lengths = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(_hermite(p0, p1, m0, m1, u), axis=0), axis=1))])
    if lengths[-1] <= 0:
        return fractions
    return np.interp(fractions * lengths[-1], lengths, u)


def _key_frames(poses: np.ndarray, n_frames: int) -> np.ndarray:
    """Frame index of each key camera: segments get frames in proportion to their share of the path's
    distance plus their share of its turning, the first camera at frame 0 and the last at ``n_frames - 1``."""
    distance = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    turning = np.array([rotation_angle(a[:3, :3], b[:3, :3]) for a, b in zip(poses[:-1], poses[1:], strict=True)])
    shares = [part / part.sum() for part in (distance, turning) if part.sum() > 1e-12]
    if not shares:
        raise CameraPathError("the cameras are all at one pose: nothing to interpolate", "poses")
    weight = np.sum(shares, axis=0)
    cumulative = np.concatenate([[0.0], np.cumsum(weight)]) / weight.sum()
    return np.round(cumulative * (n_frames - 1)).astype(int)


def interpolate_path(poses: np.ndarray, intrinsics: Intrinsics, *, n_frames: int, fps: float = 30.0) -> CameraPath:
    """``n_frames`` poses through the key ``poses`` [K, 4, 4] (scene units, in the order given: a capture's
    training cameras), each key camera exactly at one frame.

    Positions follow the centripetal Catmull-Rom spline through the key positions at constant speed along
    each segment; rotations are slerped at constant angular speed. Segments get frames in proportion to their
    share of the path's distance plus their share of its turning, so a camera that only turns still gets time.
    Every frame uses ``intrinsics`` (its undistorted view). Raises CameraPathError for fewer than 2 key poses,
    more key poses than frames, key poses all equal, or a bad pose or count.
    """
    check_frame_count(n_frames, MAX_FRAMES, key="n_frames")
    keys = np.asarray(poses, dtype=np.float64)
    if keys.ndim != 3 or keys.shape[1:] != (4, 4) or len(keys) < 2:
        raise CameraPathError(f"must be an array [K, 4, 4] with K >= 2, got shape {list(keys.shape)}", "poses")
    keys = np.stack([_checked_pose(pose, f"poses[{i}]") for i, pose in enumerate(keys)])
    if n_frames < len(keys):
        raise CameraPathError(f"{n_frames} frames cannot pass through {len(keys)} cameras (one frame each)",
                              "n_frames")
    key_index = _key_frames(keys, n_frames)
    if np.any(np.diff(key_index) < 1):
        key_index = _spread(key_index)
    start_tangents, end_tangents = _catmull_rom_tangents(keys[:, :3, 3])
    out = np.tile(np.eye(4), (n_frames, 1, 1))
    for seg in range(len(keys) - 1):
        first, last = key_index[seg], key_index[seg + 1]
        fractions = (np.arange(first, last + 1) - first) / (last - first)
        p0, p1 = keys[seg, :3, 3], keys[seg + 1, :3, 3]
        u = _constant_speed(p0, p1, start_tangents[seg], end_tangents[seg], fractions)
        out[first : last + 1, :3, 3] = _hermite(p0, p1, start_tangents[seg], end_tangents[seg], u)
        out[first : last + 1, :3, :3] = slerp(keys[seg, :3, :3], keys[seg + 1, :3, :3], fractions)
    out[key_index] = keys  # exactly the key cameras at their frames
    return CameraPath(out, [intrinsics.undistorted()] * n_frames, fps)


def _spread(key_index: np.ndarray) -> np.ndarray:
    """Key frame indices made strictly increasing (at least one frame per segment), ends kept."""
    fixed = key_index.copy()
    n_keys, last = len(fixed), int(fixed[-1])
    for i in range(1, n_keys):
        fixed[i] = min(max(fixed[i], fixed[i - 1] + 1), last - (n_keys - 1 - i))
    return fixed


# ------------------------------------------------------------------------------------------------ orbits


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Camera-to-world ``[4, 4]`` at ``eye`` looking at ``target`` (OpenGL: -Z toward it), +Y toward ``up``,
    no roll. CameraPathError when the view direction is (nearly) parallel to ``up``."""
    forward = np.asarray(target, dtype=np.float64) - np.asarray(eye, dtype=np.float64)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-6:
        raise CameraPathError("the camera looks along the up direction: no horizon to keep level", "up")
    right /= np.linalg.norm(right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, np.cross(right, forward), -forward, eye
    return c2w


def mean_up(poses: np.ndarray) -> np.ndarray:
    """Unit mean of the cameras' +Y axes (``poses`` [N, 4, 4]): the scene's up as the capture held it."""
    up = np.asarray(poses, dtype=np.float64)[:, :3, 1].mean(axis=0)
    norm = np.linalg.norm(up)
    if not norm > 1e-6:
        raise CameraPathError("the cameras' up axes cancel out: there is no mean up direction", "up")
    return up / norm


def orbit_defaults(poses: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, float]:
    """Centre (mean camera position) and radius (mean distance of the cameras from the vertical line through
    it, along ``up``) of an orbit around cameras ``poses`` [N, 4, 4], scene units."""
    positions = np.asarray(poses, dtype=np.float64)[:, :3, 3]
    center = positions.mean(axis=0)
    offsets = positions - center
    horizontal = offsets - np.outer(offsets @ up, up)
    return center, float(np.linalg.norm(horizontal, axis=1).mean())


def _unit(value, key: str) -> np.ndarray:
    vector = np.asarray(value, dtype=np.float64)
    if vector.shape != (3,) or not np.isfinite(vector).all() or not np.linalg.norm(vector) > 0:
        raise CameraPathError(f"must be 3 finite numbers, not all 0, got {short_repr(vector.tolist())}", key)
    return vector / np.linalg.norm(vector)


def orbit_path(
    center: np.ndarray, *, radius: float, height: float, n_frames: int, intrinsics: Intrinsics,
    fps: float = 30.0, up: np.ndarray = (0.0, 0.0, 1.0),
) -> CameraPath:
    """``n_frames`` cameras on a circle of ``radius`` around ``center`` (scene units), ``height`` above it along
    ``up``, each looking at ``center`` with its +Y toward ``up``; one turn, the last frame one step before the
    first (the video loops). Every frame uses ``intrinsics`` (its undistorted view).
    """
    check_frame_count(n_frames, MAX_FRAMES, key="n_frames")
    center = np.asarray(center, dtype=np.float64)
    if center.shape != (3,) or not np.isfinite(center).all():
        raise CameraPathError(f"must be 3 finite numbers, got {short_repr(center.tolist())}", "center")
    radius = _checked(positive_number, radius, "radius")
    height = _checked(finite_number, height, "height")
    up = _unit(up, "up")
    first = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    first /= np.linalg.norm(first)
    second = np.cross(up, first)
    angles = 2 * np.pi * np.arange(n_frames) / n_frames
    eyes = center + height * up + radius * (np.cos(angles)[:, None] * first + np.sin(angles)[:, None] * second)
    poses = np.stack([look_at(eye, center, up) for eye in eyes])
    return CameraPath(poses, [intrinsics.undistorted()] * n_frames, fps)


FRAMES_PER_KEY = 8  # an interpolated path passes through one key camera per this many frames, at most
GENERATED_PATHS = ("interpolate", "orbit")


def key_cameras(poses: np.ndarray, n_frames: int, keyframes: int | None = None) -> np.ndarray:
    """Evenly spaced cameras of ``poses`` [N, 4, 4] (capture order) for an interpolated path of ``n_frames``,
    first and last kept: ``keyframes`` of them when given (at least 2), else as many as leave
    :data:`FRAMES_PER_KEY` frames between two (at least 2 when N allows)."""
    if keyframes is not None and keyframes < 2:
        raise CameraPathError(f"must be at least 2, got {keyframes}", "keyframes")
    count = min(len(poses), keyframes if keyframes is not None else max(2, n_frames // FRAMES_PER_KEY))
    return poses[np.unique(np.linspace(0, len(poses) - 1, count).round().astype(int))]


def generated_path(kind: str, poses: np.ndarray, intrinsics: Intrinsics, *, n_frames: int, fps: float = 30.0,
                   radius: float | None = None, height: float = 0.0, keyframes: int | None = None) -> CameraPath:
    """The ``interpolate`` or ``orbit`` path around cameras ``poses`` [N, 4, 4] (the training cameras in capture
    order, scene units): ``interpolate`` through their :func:`key_cameras`; ``orbit`` around their centre at
    ``radius`` (default: their mean distance from the vertical through it) and ``height`` above it, up being
    their mean +Y axis. One camera (or one frame) gives a still path at the first camera."""
    check_frame_count(n_frames, MAX_FRAMES, key="n_frames")
    poses = np.asarray(poses, dtype=np.float64)
    if kind == "interpolate":
        keys = key_cameras(poses, n_frames, keyframes)
        if n_frames < 2 or len(keys) < 2:
            return CameraPath(np.repeat(keys[:1], n_frames, axis=0), [intrinsics] * n_frames, fps)
        return interpolate_path(keys, intrinsics, n_frames=n_frames, fps=fps)
    if kind != "orbit":
        raise CameraPathError(f"must be one of {list(GENERATED_PATHS)}, got {kind!r}", "path")
    up = mean_up(poses)
    center, default_radius = orbit_defaults(poses, up)
    if radius is None and default_radius < 1e-6:
        raise CameraPathError("the cameras lie on one vertical line (no default radius); give one", "radius")
    return orbit_path(center, radius=default_radius if radius is None else radius, height=height,
                      n_frames=n_frames, intrinsics=intrinsics, fps=fps, up=up)
