"""What the LiDAR phone-app importers share: ARKit's conventions and writing an RGB-D capture as a scene.

Record3D, Polycam and Stray Scanner all record through Apple's ARKit, so one set of rules serves them:

- **Poses.** ARKit's camera looks along its -Z axis with +Y up and +X right: OpenGL / nerfstudio camera axes,
  the scene format's own. Its world frame is gravity-aligned (+Y up) with the origin where the session
  started, in metres; imported scenes keep the app's world frame as it is (no re-orientation, no rescaling).
  An app that re-expresses the camera in OpenCV axes (Stray Scanner) converts back with
  :data:`writer.OPENCV_TO_OPENGL`.
- **Quaternions** are read in the apps' order ``qx qy qz qw`` (scalar last, Hamilton convention, as ARKit's
  ``simd_quatf.vector`` and scipy's ``Rotation.from_quat`` order them) and turned into the rotation of the
  camera-to-world pose. One whose norm is not within :data:`QUATERNION_NORM_TOLERANCE` of 1, or that is not
  finite, makes the frame a counted skip (``invalid pose (...)``); others are normalised.
- **Depth** is ARKit's ``sceneDepth``: z-depth in metres on a lower-resolution map (256 x 192 on current
  iPhones and iPads) covering the colour camera's field of view from the same pose. Each depth map keeps its own
  resolution and is registered through the colour intrinsics scaled to its size (``depth_intrinsics``, written per
  frame when they differ from the top level); a map whose aspect ratio is not the colour image's is an error
  naming it, since no scaling of the intrinsics would register it.
- **Confidence.** ARKit grades each depth pixel low / medium / high (``ARConfidenceLevel`` 0 / 1 / 2); depth
  below ``min_confidence`` (default medium) is written as 0, the scene format's "no measurement". A frame whose
  depth map has no confidence map keeps no depth unless ``min_confidence`` is low, and is counted.
- Depth is written as 16-bit PNG millimetres (``depth_unit_scale_factor`` 0.001; 0 = no measurement).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from voxnerf.data.image_io import encode_depth_png16, image_size, write_atomic
from voxnerf.data.importers import writer
from voxnerf.data.importers.splits import PaperSplitRule, SplitError, split_keys
from voxnerf.errors import SceneError

DEPTH_UNIT_SCALE = 0.001
"""Metres per unit of the written depth PNGs (millimetres, as the apps record them)."""
QUATERNION_NORM_TOLERANCE = 1e-3
"""Largest |norm - 1| of a stored quaternion still taken as a rotation (the apps write float32 values)."""
ASPECT_TOLERANCE = 0.01
"""Largest relative difference between a depth map's and its colour image's aspect ratio."""
CONFIDENCE_LEVELS = {"low": 0, "medium": 1, "high": 2}
"""ARKit's ``ARConfidenceLevel`` values by name."""
DEFAULT_MIN_CONFIDENCE = "medium"


@dataclass(frozen=True)
class Camera:
    """A pinhole camera in this project's continuous pixel coordinates (the centre of a W x H image at W/2)."""

    fl_x: float
    fl_y: float
    cx: float
    cy: float
    w: int
    h: int

    def as_keys(self) -> dict:
        """The scene format's ``fl_x fl_y cx cy w h`` keys."""
        return {"fl_x": self.fl_x, "fl_y": self.fl_y, "cx": self.cx, "cy": self.cy, "w": self.w, "h": self.h}

    def scaled_to(self, width: int, height: int) -> Camera:
        """The same field of view on a ``width`` x ``height`` grid (a depth map's): every term scaled per axis."""
        sx, sy = width / self.w, height / self.h
        return Camera(self.fl_x * sx, self.fl_y * sy, self.cx * sx, self.cy * sy, int(width), int(height))


def camera_from_k(k: np.ndarray, width: int, height: int, source: Path) -> Camera:
    """A :class:`Camera` from a 3x3 K (row-major, ``fx 0 cx / 0 fy cy / 0 0 1``); SceneError naming ``source``."""
    k = np.asarray(k, dtype=np.float64)
    if k.shape != (3, 3) or not np.isfinite(k).all():
        raise SceneError(source, f"intrinsic matrix must be 3x3 and finite, got {writer.one_line(k.tolist())}")
    if k[0, 0] <= 0 or k[1, 1] <= 0 or width <= 0 or height <= 0:
        raise SceneError(source, "focal lengths and the image size must be positive")
    return Camera(float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]), int(width), int(height))


def quaternion_rotation(qx: float, qy: float, qz: float, qw: float) -> np.ndarray:
    """The 3x3 rotation of the unit quaternion ``w + xi + yj + zk`` (normalised first; ValueError if unusable)."""
    q = np.array([qw, qx, qy, qz], dtype=np.float64)
    if not np.isfinite(q).all():
        raise ValueError("non-finite values")
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
        raise ValueError(f"quaternion norm {norm:.6g}, expected 1")
    w, x, y, z = q / norm
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def pose_from_quaternion(q_xyzw: list[float], t_xyz: list[float]) -> np.ndarray:
    """The 4x4 camera-to-world pose of rotation ``qx qy qz qw`` and position ``x y z`` (ValueError if unusable)."""
    t = np.asarray(t_xyz, dtype=np.float64)
    if t.shape != (3,) or not np.isfinite(t).all():
        raise ValueError("non-finite values")
    pose = np.eye(4)
    pose[:3, :3] = quaternion_rotation(*q_xyzw)
    pose[:3, 3] = t
    return pose


def confidence_threshold(name: str) -> int:
    """ARKit's level for ``low``/``medium``/``high``; ValueError naming the choices otherwise."""
    if name not in CONFIDENCE_LEVELS:
        raise ValueError(f"min_confidence must be one of {', '.join(CONFIDENCE_LEVELS)}, got {name!r}")
    return CONFIDENCE_LEVELS[name]


@dataclass
class DepthSource:
    """One frame's depth map and its confidence, read when the frame is written.

    ``read_depth()`` returns float metres ``[h, w]`` (0, NaN and inf: no measurement) and raises SceneError naming
    its file; ``read_confidence()`` returns ARKit levels (0 / 1 / 2) of the same shape, or is None when the app
    wrote no confidence map for this frame.
    """

    path: Path
    read_depth: Callable[[], np.ndarray]
    read_confidence: Callable[[], np.ndarray] | None
    confidence_path: Path | None = None


@dataclass
class CaptureFrame:
    """One frame of a capture in capture order: its colour image, OpenGL camera-to-world pose and camera."""

    stem: str
    c2w: np.ndarray
    camera: Camera
    write_image: Callable[[Path], None]  # writes the colour image to the given path
    image_suffix: str
    origin: Path  # where the image comes from (the app's file, or its video), named in errors
    depth: DepthSource | None = None
    depth_camera: Camera | None = None  # the camera the depth was measured through, when not the colour one


@dataclass
class Capture:
    """An app's export read into frames: what :func:`write_capture` turns into a scene."""

    format: str
    src: Path
    frames: list[CaptureFrame] = field(default_factory=list)
    skipped: dict = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)

    def skip(self, reason: str) -> None:
        self.skipped[reason] = self.skipped.get(reason, 0) + 1


@dataclass
class _DepthTally:
    frames: int = 0
    measured: int = 0  # depth pixels with a measurement before the confidence filter
    dropped: int = 0  # of those, dropped for low confidence
    without_confidence: int = 0  # frames whose depth was dropped for want of a confidence map


def _checked_depth(source: DepthSource, camera: Camera) -> np.ndarray:
    depth = np.asarray(source.read_depth(), dtype=np.float64)
    if depth.ndim != 2 or min(depth.shape) == 0:
        raise SceneError(source.path, f"depth map must be [H, W], got shape {list(depth.shape)}")
    if np.any(depth < 0):  # NaN compares False
        raise SceneError(source.path, f"negative depth values (min {np.nanmin(depth):.4g} m)")
    h, w = depth.shape
    if abs((w / h) / (camera.w / camera.h) - 1.0) > ASPECT_TOLERANCE:
        raise SceneError(source.path, f"depth map is {w}x{h}, not the aspect ratio of its {camera.w}x{camera.h} "
                                      "colour image: it cannot be registered by scaling the intrinsics")
    return depth


def _filtered_depth(source: DepthSource, depth: np.ndarray, min_level: int, tally: _DepthTally) -> np.ndarray | None:
    """``depth`` with pixels below ``min_level`` set to no measurement; None when it cannot be filtered."""
    measured = np.isfinite(depth) & (depth > 0)
    if min_level == 0:
        tally.measured += int(measured.sum())
        return depth
    if source.read_confidence is None:
        tally.without_confidence += 1
        return None
    confidence = np.asarray(source.read_confidence())
    where = source.confidence_path or source.path
    if confidence.shape != depth.shape:
        raise SceneError(where, f"confidence map is {list(confidence.shape)}, its depth map {list(depth.shape)}")
    low = measured & (confidence < min_level)
    tally.measured += int(measured.sum())
    tally.dropped += int(low.sum())
    return np.where(low, 0.0, depth)


def _write_frame(root: Path, frame: CaptureFrame, top: Camera, min_level: int, tally: _DepthTally) -> dict:
    name = f"images/{frame.stem}{frame.image_suffix}"
    (root / "images").mkdir(exist_ok=True)
    frame.write_image(root / name)
    try:
        got = image_size(root / name)
    except SceneError as err:  # it names the copy being built; the fault is the app's file
        message = err.message.replace(str(root / name), frame.origin.name)
        raise SceneError(frame.origin, f"frame {frame.stem}: {message}") from None
    if got != (frame.camera.w, frame.camera.h):
        raise SceneError(frame.origin, f"frame {frame.stem}: image is {got[0]}x{got[1]} but its camera says "
                                       f"{frame.camera.w}x{frame.camera.h}")
    entry: dict = {"file_path": name, "transform_matrix": writer.pose_list(frame.c2w)}
    if frame.camera != top:
        entry.update(frame.camera.as_keys())
    if frame.depth is None:
        return entry
    depth = _checked_depth(frame.depth, frame.depth_camera or frame.camera)
    depth = _filtered_depth(frame.depth, depth, min_level, tally)
    if depth is None:
        return entry
    h, w = depth.shape
    (root / "depth").mkdir(exist_ok=True)
    entry["depth_file_path"] = f"depth/{frame.stem}.png"
    write_atomic(root / entry["depth_file_path"], encode_depth_png16(depth, DEPTH_UNIT_SCALE))
    entry["depth_intrinsics"] = (frame.depth_camera or frame.camera).scaled_to(w, h).as_keys()
    tally.frames += 1
    return entry


def _fill(root: Path, capture: Capture, splits: PaperSplitRule | None, min_confidence: str) -> dict:
    min_level = confidence_threshold(min_confidence)
    top = capture.frames[0].camera
    meta: dict = {"camera_model": "PINHOLE", **top.as_keys(), "depth_unit_scale_factor": DEPTH_UNIT_SCALE}
    tally = _DepthTally()
    meta["frames"] = [_write_frame(root, frame, top, min_level, tally) for frame in capture.frames]
    split_summary = None
    if splits is not None:
        try:
            keys, split_summary = split_keys([f["file_path"] for f in meta["frames"]], splits)
        except SplitError as err:
            raise SceneError(capture.src, str(err), key="--splits paper") from None
        meta.update(keys)
    writer.write_transforms(root, meta)
    notes = list(capture.notes)
    if tally.frames:
        share = tally.dropped / tally.measured if tally.measured else 0.0
        kept = (f"all {tally.measured} measured depth pixels kept (no confidence filter)" if min_level == 0 else
                f"{tally.dropped} of {tally.measured} measured depth pixels ({share:.1%}) below {min_confidence} "
                "confidence dropped")
        notes.append(f"depth kept at its own resolution, registered through the scaled colour intrinsics; {kept}")
        notes.append("no prior file: the engine fuses one from the training frames' depth maps")
    if tally.without_confidence:
        notes.append(f"{tally.without_confidence} frame(s) have a depth map but no confidence map: their depth is "
                     f"not kept (min_confidence low keeps it unfiltered)")
    if not tally.frames:
        notes.append("no depth kept: the scene has no sensor depth")
    return {
        "format": capture.format,
        "frames": len(capture.frames),
        "skipped": dict(capture.skipped),
        "camera_models": ["PINHOLE"],
        "depth_frames": tally.frames,
        "prior": None,
        "splits": split_summary,
        "notes": notes,
    }


def write_capture(out: Path, capture: Capture, splits: PaperSplitRule | None = None,
                  min_confidence: str = DEFAULT_MIN_CONFIDENCE) -> dict:
    """Write ``capture`` as a scene at ``out`` (absent or empty; built beside it and renamed); the summary.

    SceneError naming ``capture.src`` when no frame is left; on any error nothing is left at ``out``.
    """
    confidence_threshold(min_confidence)
    if not capture.frames:
        raise SceneError(capture.src, f"no usable frame: all are skipped ({capture.skipped})")
    return writer.build_scene(Path(out), lambda root: _fill(root, capture, splits, min_confidence))


def select_every(n: int, every: int) -> range:
    """Indices 0, every, 2 every, ... below ``n``; ValueError unless ``every`` >= 1."""
    if every < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    return range(0, n, every)


def copier(src: Path) -> Callable[[Path], None]:
    """A ``write_image`` that copies the app's own image file."""
    return lambda dst: writer.copy_file(src, dst)
