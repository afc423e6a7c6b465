"""Scene loading and validation per docs/scene-format.md (nerfstudio transforms.json plus VoxNeRF's prior keys).

Every problem raises :class:`SceneError` naming the file and the key. Poses stay in scene units here;
:class:`SceneTransform` maps them into the canonical box the engine trains in.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from voxnerf.cameras.lens import undistort
from voxnerf.cameras.rules import (
    COEFFICIENT_KEYS,
    OPENCV,
    OPENCV_FISHEYE,
    REPAIR_WARNING_ABOVE,
    ROTATION_TOLERANCE,
    CameraError,
    Intrinsics,
    Lens,
    finite_number,
    lens_of,
    one_line,
    pixel_count,
    positive_number,
    short_repr,
    validate_pose_deviation,
)
from voxnerf.data.image_io import image_size, read_depth, read_rgb
from voxnerf.errors import SceneError
from voxnerf.files import TRANSFORMS

INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h")
DISTORTION_KEYS = COEFFICIENT_KEYS  # k1 k2 k3 k4 p1 p2, nerfstudio's (OpenCV's) names
SPLIT_KEYS = ("train_filenames", "val_filenames", "test_filenames")
DEFAULT_PRIOR_NAME = "prior.ply"
MAX_IMAGE_SIDE = 65536  # pixels, for w and h
__all__ = [
    "ROTATION_TOLERANCE", "Frame", "Scene", "SceneTransform", "depth_on_image", "inspect_scene", "load_scene",
    "with_focal_scale",
]
# Names of eval_splits: they become folder names of evaluation renders (``eval/<split>/``) and URL segments.
SPLIT_NAME = re.compile(r"[A-Za-z0-9_-][A-Za-z0-9_.-]{0,63}")


@dataclass
class Frame:
    """One posed image. ``c2w`` is camera-to-world (OpenGL axes) in scene units, float64 [4, 4]."""

    file_path: str
    image_path: Path
    c2w: np.ndarray
    intrinsics: Intrinsics
    depth_path: Path | None = None
    depth_intrinsics: Intrinsics | None = None  # the depth camera's, when ``depth_intrinsics`` gives them
    camera_model: str = "PINHOLE (default)"  # the lens model (intrinsics.lens) and how it was decided
    # the camera transforms.json states, when ``intrinsics`` is a corrected one (:func:`with_focal_scale`): a
    # depth map without depth_intrinsics was measured through it
    stated_intrinsics: Intrinsics | None = None


@dataclass
class Scene:
    """A validated scene. Images and depth maps are loaded at ``1/downscale`` resolution when asked, for the
    frames of some split only (``None`` for a frame that no split uses)."""

    root: Path
    frames: list[Frame]
    splits: dict[str, list[int]]
    prior_path: Path | None
    prior_sigma: float | None
    depth_unit_scale: float
    prior_key: str | None = None  # where prior_path came from: prior_file_path, ply_file_path or the default name
    depth_max: float | None = None  # depth beyond this (scene units) is no measurement
    downscale: int = 1
    images: list[np.ndarray | None] | None = None
    depths: list[np.ndarray | None] | None = None  # training frames only: held-out depth is never read
    warnings: list[str] = field(default_factory=list)
    synthetic: bool = False  # transforms.json's ``synthetic``: rendered images with exact poses

    @property
    def train_indices(self) -> list[int]:
        return self.splits["train"]

    @property
    def eval_split_names(self) -> list[str]:
        """Evaluation splits: the named ``eval_splits`` first, then ``test`` (the default split)."""
        names = [name for name in self.splits if name not in ("train", "val", "test") and self.splits[name]]
        return names + (["test"] if self.splits.get("test") else [])

    def intrinsics(self, index: int) -> Intrinsics:
        """Intrinsics of frame ``index`` at the loaded resolution, its lens included (scaling an image leaves
        the distortion coefficients unchanged)."""
        intr = self.frames[index].intrinsics
        if self.downscale == 1:
            return intr
        w, h = intr.width // self.downscale, intr.height // self.downscale
        return Intrinsics(
            intr.fl_x * w / intr.width, intr.fl_y * h / intr.height,
            intr.cx * w / intr.width, intr.cy * h / intr.height, w, h, intr.lens,
        )

    def camera_models(self) -> dict[str, int]:
        """Frames per camera model and how it was decided, e.g. ``{"OPENCV (camera_model)": 40}``."""
        counts: dict[str, int] = {}
        for frame in self.frames:
            counts[frame.camera_model] = counts.get(frame.camera_model, 0) + 1
        return counts

    def image_sizes(self) -> dict[str, int]:
        """Frames per image size, e.g. ``{"1000x657": 12, "1000x659": 11}`` (in the order the sizes first appear)."""
        counts: dict[str, int] = {}
        for frame in self.frames:
            size = f"{frame.intrinsics.width}x{frame.intrinsics.height}"
            counts[size] = counts.get(size, 0) + 1
        return counts

    def summary(self) -> dict:
        """JSON-able description (frames, split sizes, image sizes, prior file and stated sigma, depth).
        ``image_size`` is the first training frame's: the camera a run renders with when asked for no other."""
        first = self.frames[self.train_indices[0]].intrinsics
        return {
            "frames": len(self.frames),
            "splits": {name: len(idx) for name, idx in self.splits.items()},
            "image_size": [first.width, first.height],
            "image_sizes": self.image_sizes(),
            "prior": None if self.prior_path is None else {
                "file": self.prior_path.name, "sigma": self.prior_sigma, "source": self.prior_key,
            },
            "depth": any(f.depth_path is not None for f in self.frames),
            "camera_models": self.camera_models(),
            "depth_frames": {"all": sum(f.depth_path is not None for f in self.frames),
                             "train": sum(self.frames[i].depth_path is not None for i in self.train_indices)},
            "synthetic": self.synthetic,
            "warnings": list(self.warnings),
        }


@dataclass(frozen=True)
class SceneTransform:
    """Similarity from scene units to the canonical box: ``x_n = (x - center) * scale``.

    The box is ``[-1, 1]^3`` around the prior and the cameras; distances in normalised units divide by
    ``scale`` to come back to scene units.
    """

    center: tuple[float, float, float]
    scale: float

    def points_to_normalized(self, points: np.ndarray) -> np.ndarray:
        return (points - np.asarray(self.center)) * self.scale

    def c2w_to_normalized(self, c2w: np.ndarray) -> np.ndarray:
        """[..., 4, 4] camera-to-world in scene units -> normalised units (rotation unchanged)."""
        out = np.array(c2w, dtype=np.float64, copy=True)
        out[..., :3, 3] = (out[..., :3, 3] - np.asarray(self.center)) * self.scale
        return out

    def c2w_to_scene(self, c2w: np.ndarray) -> np.ndarray:
        """[..., 4, 4] camera-to-world in normalised units -> scene units (the inverse of
        :meth:`c2w_to_normalized`)."""
        out = np.array(c2w, dtype=np.float64, copy=True)
        out[..., :3, 3] = out[..., :3, 3] / self.scale + np.asarray(self.center)
        return out

    @staticmethod
    def fit(points: np.ndarray, margin: float = 0.05) -> SceneTransform:
        """The transform that puts ``points`` [N, 3] inside ``[-1+margin, 1-margin]^3``."""
        lo, hi = points.min(axis=0), points.max(axis=0)
        center = (lo + hi) / 2
        half = float(np.max(hi - lo)) / 2
        half = max(half, 1e-9 * max(1.0, float(np.abs(center).max())))
        return SceneTransform(tuple(float(c) for c in center), (1.0 - margin) / half)


def _fail(path: Path, message: str, key: str | None = None) -> SceneError:
    return SceneError(path, message, key=key)


def _checked(rule: Callable, value, path: Path, key: str):
    """``rule(value, key)`` of :mod:`voxnerf.cameras.rules`, its CameraError as a SceneError naming ``path``."""
    try:
        return rule(value, key)
    except CameraError as err:
        raise _fail(path, err.message, key) from None


def _positive_number(value, path: Path, key: str) -> float:
    return _checked(positive_number, value, path, key)


def _finite_number(value, path: Path, key: str) -> float:
    return _checked(finite_number, value, path, key)


def _boolean(value, path: Path, key: str) -> bool:
    if not isinstance(value, bool):
        raise _fail(path, f"must be true or false, got {short_repr(value)}", key)
    return value


def _pixel_count(value, path: Path, key: str) -> int:
    count = _checked(pixel_count, value, path, key)
    if count > MAX_IMAGE_SIDE:
        raise _fail(path, f"must be a positive integer pixel count, got {short_repr(value)}", key)
    return count


def _focal_length(source: dict, fallback: dict, axis: str, size: int, path: Path, where: str) -> float | None:
    """``fl_<axis>``, else the focal length of instant-ngp's ``camera_angle_<axis>`` (the field of view over
    ``size`` pixels, radians), else None."""
    value = source.get(f"fl_{axis}", fallback.get(f"fl_{axis}"))
    if value is not None:
        return _positive_number(value, path, f"{where}fl_{axis}")
    key = f"camera_angle_{axis}"
    angle = source.get(key, fallback.get(key))
    if angle is None:
        return None
    if _positive_number(angle, path, f"{where}{key}") >= math.pi:
        raise _fail(path, f"must be a field of view in radians below pi, got {short_repr(angle)}", f"{where}{key}")
    return 0.5 * size / math.tan(0.5 * float(angle))


def _focal_lengths(source: dict, fallback: dict, width: int, height: int, path: Path,
                   where: str) -> tuple[float, float]:
    """``(fl_x, fl_y)``. Both are needed, except that an instant-ngp ``camera_angle_x`` (or ``_y``) alone
    gives both (square pixels)."""
    fx = _focal_length(source, fallback, "x", width, path, where)
    fy = _focal_length(source, fallback, "y", height, path, where)
    angle_only = source.get("fl_x", fallback.get("fl_x")) is None and source.get("fl_y", fallback.get("fl_y")) is None
    if fx is None and (fy is None or not angle_only):
        raise _fail(path, "missing (give it, or camera_angle_x, at the top level or in the frame)", f"{where}fl_x")
    if fy is None and not angle_only:
        raise _fail(path, "missing (give it at the top level or in the frame)", f"{where}fl_y")
    return (fx or fy), (fy or fx)


def _read_intrinsics(source: dict, fallback: dict, path: Path, where: str) -> Intrinsics:
    """The pinhole intrinsics of ``source`` (a frame), each key missing there taken from ``fallback``."""
    values = {}
    for key in ("cx", "cy", "w", "h"):
        value = source.get(key, fallback.get(key))
        if value is None:
            raise _fail(path, "missing (give it at the top level or in the frame)", f"{where}{key}")
        values[key] = value
    width = _pixel_count(values["w"], path, f"{where}w")
    height = _pixel_count(values["h"], path, f"{where}h")
    fl_x, fl_y = _focal_lengths(source, fallback, width, height, path, where)
    return Intrinsics(
        fl_x,
        fl_y,
        _finite_number(values["cx"], path, f"{where}cx"),
        _finite_number(values["cy"], path, f"{where}cy"),
        width,
        height,
    )


def _lens_checked(model: str, coefficients: dict, path: Path, where: str, context: str = "") -> Lens | None:
    """:func:`voxnerf.cameras.rules.lens_of`, its CameraError as a SceneError naming the key."""
    try:
        return lens_of(model, coefficients)
    except CameraError as err:
        raise _fail(path, f"{context}{err.message}", f"{where}{err.field}") from None


def _instant_ngp_lens(meta: dict, frame: dict, path: Path, where: str) -> tuple[Lens | None, str]:
    """Coefficients without ``camera_model``, read as instant-ngp reads them: any non-zero coefficient makes
    the camera ``OPENCV``, or ``OPENCV_FISHEYE`` when ``is_fisheye`` is true; all zero (or none) is a pinhole."""
    fisheye = _boolean(frame.get("is_fisheye", meta.get("is_fisheye", False)), path, f"{where}is_fisheye")
    values = {key: frame.get(key, meta.get(key)) for key in DISTORTION_KEYS}
    numbers = {key: _finite_number(v, path, f"{where}{key}") for key, v in values.items() if v is not None}
    if not any(numbers.values()):
        return None, "PINHOLE (default)"
    model = OPENCV_FISHEYE if fisheye else OPENCV
    context = f"no camera_model, so read as {model} (is_fisheye {str(fisheye).lower()}): "
    lens = _lens_checked(model, numbers, path, where, context)
    return lens, f"{model} (coefficients without camera_model, as instant-ngp)"


def _check_camera_model(meta: dict, frame: dict, path: Path, where: str) -> tuple[Lens | None, str]:
    """The frame's lens (None: a pinhole) and its summary line, e.g. ``"OPENCV (camera_model)"``.

    ``camera_model`` and the coefficients ``k1 k2 k3 k4 p1 p2`` may be given at the top level or in the frame
    (the frame's keys win); a frame whose ``camera_model`` differs from the top level's does not inherit the
    top level's coefficients. Without ``camera_model`` the coefficients are read as instant-ngp does
    (:func:`_instant_ngp_lens`). Keys are named ``frames[i].<key>`` wherever they were given.
    """
    own = frame.get("camera_model")
    model = own if own is not None else meta.get("camera_model")
    if model is None:
        return _instant_ngp_lens(meta, frame, path, where)
    inherit = own is None or own == meta.get("camera_model")
    values = {key: frame.get(key, meta.get(key) if inherit else None) for key in DISTORTION_KEYS}
    return _lens_checked(model, values, path, where), f"{model} (camera_model)"


def _read_pose(value, path: Path, key: str, reorthonormalised: list[tuple[str, float]]) -> np.ndarray:
    """The pose rule of :func:`voxnerf.cameras.rules.validate_pose`; a 3x4 matrix gets its last row added.

    Appends ``(key, deviation)`` to ``reorthonormalised`` when the repair is large enough to warn about.
    """
    if isinstance(value, list) and len(value) == 3 and all(isinstance(r, list) and len(r) == 4 for r in value):
        value = [*value, [0.0, 0.0, 0.0, 1.0]]
    try:
        mat, deviation = validate_pose_deviation(value)
    except CameraError as err:
        raise _fail(path, err.message, key) from None  # bounded: values inside are already shortened
    if deviation > REPAIR_WARNING_ABOVE:
        reorthonormalised.append((key, deviation))
    return mat


def _reorthonormalised_warning(fixed: list[tuple[str, float]]) -> str:
    """One warning for every pose whose rotation was re-orthonormalised (a scan can have thousands)."""
    keys = ", ".join(key for key, _ in fixed[:3]) + (f" and {len(fixed) - 3} more" if len(fixed) > 3 else "")
    return f"{keys}: rotation re-orthonormalised (max |R^T R - I| was {max(d for _, d in fixed):.2g})"


def _resolve_inside(root: Path, rel, path: Path, key: str) -> Path:
    if not isinstance(rel, str) or not rel:
        raise _fail(path, f"must be a non-empty relative path string, got {short_repr(rel)}", key)
    try:
        target = (root / rel).resolve()
        inside = target.is_relative_to(root.resolve())
        found = inside and target.is_file()
    except (OSError, ValueError, RuntimeError) as exc:  # NUL byte, name too long, symlink loop (3.11)
        raise _fail(path, f"unusable path {short_repr(rel)} ({type(exc).__name__})", key) from None
    if not inside:
        raise _fail(path, f"{short_repr(rel)} points outside the scene directory", key)
    if not found:
        raise _fail(path, f"file not found: {one_line(rel)}", key)
    return target


def _split_indices(index: dict[str, int], files, path: Path, key: str) -> list[int]:
    """Frame indices of the ``file_path`` list ``files`` given under ``key``."""
    if not isinstance(files, list) or not all(isinstance(f, str) for f in files):
        raise _fail(path, "must be a list of file_path strings", key)
    missing = [f for f in files if f not in index]
    if missing:
        raise _fail(path, f"{len(missing)} file(s) not in frames, e.g. {missing[0]!r}", key)
    return [index[f] for f in files]


def _eval_splits(meta: dict, index: dict[str, int], path: Path) -> dict[str, list[int]]:
    """The named evaluation splits of ``eval_splits``, their names checked (they name folders)."""
    eval_splits = meta.get("eval_splits")
    if eval_splits is not None and not isinstance(eval_splits, dict):
        raise _fail(path, "must be an object mapping split names to lists of file_path", "eval_splits")
    for name in eval_splits or {}:
        if name in ("train", "val", "test"):
            raise _fail(path, f"split name {name!r} is reserved", f"eval_splits.{name}")
        if not SPLIT_NAME.fullmatch(name):  # it names a folder of evaluation renders
            raise _fail(
                path,
                f"split name {short_repr(name)}: use 1 to 64 letters, digits, '_', '-' or '.', not starting "
                "with '.'",
                "eval_splits",
            )
    return {name: _split_indices(index, files, path, f"eval_splits.{name}")
            for name, files in (eval_splits or {}).items()}


def _read_splits(meta: dict, names: list[str], path: Path) -> dict[str, list[int]]:
    index = {name: i for i, name in enumerate(names)}
    named = {k: _split_indices(index, meta[k], path, k) for k in SPLIT_KEYS if k in meta}
    extra = _eval_splits(meta, index, path)
    if not named and not extra:  # every 8th frame is a test frame
        return {
            "train": [i for i in range(len(names)) if i % 8 != 0],
            "test": list(range(0, len(names), 8)),
        }
    splits: dict[str, list[int]] = {}
    if "train_filenames" in named:
        splits["train"] = named["train_filenames"]
    else:  # the frames no other split names
        used = {i for idx in named.values() for i in idx} | {i for idx in extra.values() for i in idx}
        splits["train"] = [i for i in range(len(names)) if i not in used]
    for key, name in (("val_filenames", "val"), ("test_filenames", "test")):
        if key in named:
            splits[name] = named[key]
    splits.update(extra)
    if not splits["train"]:
        raise _fail(path, "no training frames", "train_filenames")
    return splits


def _read_meta(root: Path) -> tuple[Path, dict]:
    root = Path(root)
    path = root / TRANSFORMS
    if not root.is_dir():
        raise SceneError(root, "scene directory not found")
    if not path.is_file():
        raise SceneError(path, "file not found")
    try:
        meta = json.loads(path.read_text(encoding="utf-8"))
    except (ValueError, RecursionError) as exc:  # bad UTF-8 or JSON, 4300+ digit integers, deep nesting
        raise SceneError(path, f"invalid JSON: {one_line(str(exc))}") from None
    if not isinstance(meta, dict):
        raise SceneError(path, "top level must be a JSON object")
    return path, meta


def _read_frame(root: Path, meta: dict, i: int, raw, json_path: Path, seen: set[str],
                reorthonormalised: list[tuple[str, float]]) -> Frame:
    """Frame ``i`` of ``frames``: its image path (unique, inside the scene), pose, camera and depth path."""
    where = f"frames[{i}]."
    if not isinstance(raw, dict):
        raise SceneError(json_path, "must be an object", key=f"frames[{i}]")
    file_path = raw.get("file_path")
    image_path = _resolve_inside(root, file_path, json_path, f"{where}file_path")
    if file_path in seen:
        raise SceneError(json_path, f"duplicate file_path {file_path!r}", key=f"{where}file_path")
    seen.add(file_path)
    if "transform_matrix" not in raw:
        raise SceneError(json_path, "missing", key=f"{where}transform_matrix")
    c2w = _read_pose(raw["transform_matrix"], json_path, f"{where}transform_matrix", reorthonormalised)
    intr = _read_intrinsics(raw, meta, json_path, where)
    lens, camera_model = _check_camera_model(meta, raw, json_path, where)
    intr = replace(intr, lens=lens)
    depth_path = depth_intr = None
    if raw.get("depth_file_path") is not None:
        depth_path = _resolve_inside(root, raw["depth_file_path"], json_path, f"{where}depth_file_path")
        depth_intr = _read_depth_intrinsics(raw, meta, json_path, where)
    return Frame(file_path, image_path, c2w, intr, depth_path, depth_intr, camera_model)


def _read_depth_intrinsics(raw: dict, meta: dict, path: Path, where: str) -> Intrinsics | None:
    """``depth_intrinsics`` of the frame, else of the top level: the depth camera's fl_x fl_y cx cy w h."""
    if raw.get("depth_intrinsics") is not None:
        value, key = raw["depth_intrinsics"], f"{where}depth_intrinsics"
    elif meta.get("depth_intrinsics") is not None:
        value, key = meta["depth_intrinsics"], "depth_intrinsics"
    else:
        return None
    if not isinstance(value, dict):
        raise _fail(path, "must be an object with fl_x, fl_y, cx, cy, w, h", key)
    return _read_intrinsics(value, {}, path, f"{key}.")


def _read_frames(root: Path, meta: dict, json_path: Path, warnings: list[str]) -> list[Frame]:
    """Every frame of ``frames``; one warning for all the poses whose rotation was repaired."""
    raw_frames = meta.get("frames")
    if not isinstance(raw_frames, list) or not raw_frames:
        raise SceneError(json_path, "must be a non-empty list", key="frames")
    reorthonormalised: list[tuple[str, float]] = []
    seen: set[str] = set()
    frames = [_read_frame(root, meta, i, raw, json_path, seen, reorthonormalised) for i, raw in enumerate(raw_frames)]
    if reorthonormalised:
        warnings.append(_reorthonormalised_warning(reorthonormalised))
    return frames


def prior_file(root: Path, meta: dict) -> Path | None:
    """The prior file (resolved) that :func:`load_scene` takes for the scene at ``root`` whose transforms.json
    holds ``meta``, or None; SceneError for a path outside ``root``."""
    return _read_prior_keys(root, meta, root / "transforms.json", [])[0]


def _read_prior_keys(
    root: Path, meta: dict, json_path: Path, warnings: list[str]
) -> tuple[Path | None, float | None, str | None]:
    """The prior's path, its stated sigma and where the path came from: ``prior_file_path``, else nerfstudio's
    ``ply_file_path`` (a COLMAP or capture-app point cloud), else ``prior.ply`` when present."""
    prior_path = key = None
    for name in ("prior_file_path", "ply_file_path"):
        if meta.get(name) is not None:
            prior_path, key = _resolve_inside(root, meta[name], json_path, name), name
            break
    else:
        if (root / DEFAULT_PRIOR_NAME).is_file():
            prior_path, key = (root / DEFAULT_PRIOR_NAME).resolve(), DEFAULT_PRIOR_NAME
            warnings.append(f"prior_file_path absent: using {DEFAULT_PRIOR_NAME} found in the scene directory")
    prior_sigma = None
    if meta.get("prior_sigma") is not None:
        prior_sigma = _positive_number(meta["prior_sigma"], json_path, "prior_sigma")
    return prior_path, prior_sigma, key


def _check_image_sizes(frames: list[Frame], json_path: Path, downscale: int) -> None:
    """Each image header agrees with its frame's ``w h``, and ``downscale`` leaves pixels."""
    for frame in frames:
        w, h = image_size(frame.image_path)
        if (w, h) != (frame.intrinsics.width, frame.intrinsics.height):
            raise SceneError(
                frame.image_path,
                f"image is {w}x{h} but transforms.json says w={frame.intrinsics.width} "
                f"h={frame.intrinsics.height}",
                key="size",
            )
        if frame.intrinsics.width // downscale < 1 or frame.intrinsics.height // downscale < 1:
            raise SceneError(json_path, f"downscale {downscale} leaves no pixels", key="w")


def _load_pixels(scene: Scene) -> None:
    """Decode the images of the frames some split uses and the depth maps of the training frames (registered
    to their images), at the scene's downscale."""
    used = {i for idx in scene.splits.values() for i in idx}
    train = set(scene.train_indices)
    scene.images = [_downscale_rgb(read_rgb(f.image_path), scene.downscale) if i in used else None
                    for i, f in enumerate(scene.frames)]
    scene.depths = [
        None if f.depth_path is None or i not in train else
        depth_on_image(f, scene.depth_unit_scale, scene.downscale, scene.depth_max)
        for i, f in enumerate(scene.frames)
    ]


def load_scene(path: str | Path, *, downscale: int = 1, load_images: bool = True) -> Scene:
    """Read and validate a scene directory.

    Args:
        path: scene directory holding ``transforms.json``.
        downscale: integer factor; images (area-averaged) and intrinsics are reduced by it.
        load_images: read the images (uint8 [H/d, W/d, 3]) of every frame that a split uses and the depth maps
            (float32 metres, NaN invalid, registered to the image) of the training frames (``None`` for the
            rest: a 1000-frame scan with 125 frames in its splits decodes 125 images); otherwise only the image
            headers are checked.
    Raises:
        SceneError: one per problem, naming the file and the key.
    """
    root = Path(path)
    json_path, meta = _read_meta(root)
    if not isinstance(downscale, int) or downscale < 1:
        raise SceneError(json_path, f"downscale must be a positive integer, got {downscale!r}")
    warnings: list[str] = []
    frames = _read_frames(root, meta, json_path, warnings)
    splits = _read_splits(meta, [f.file_path for f in frames], json_path)
    depth_scale = _positive_number(meta.get("depth_unit_scale_factor", 0.001), json_path, "depth_unit_scale_factor")
    depth_max = None
    if meta.get("depth_max") is not None:
        depth_max = _positive_number(meta["depth_max"], json_path, "depth_max")
    prior_path, prior_sigma, prior_key = _read_prior_keys(root, meta, json_path, warnings)
    _check_image_sizes(frames, json_path, downscale)
    synthetic = _boolean(meta.get("synthetic", False), json_path, "synthetic")
    scene = Scene(root.resolve(), frames, splits, prior_path, prior_sigma, depth_scale, prior_key, depth_max,
                  downscale, warnings=warnings, synthetic=synthetic)
    if load_images:
        _load_pixels(scene)
    return scene


def with_focal_scale(scene: Scene, scale: float) -> Scene:
    """``scene`` with every frame's colour focal lengths times ``scale`` (principal point, size and lens kept), as
    a focal check measured them (:mod:`voxnerf.prior.focal_check`); ``scene`` itself when ``scale`` is 1.

    The depth maps keep the camera they were measured through (``depth_intrinsics``, else the stated colour
    camera), so the loaded training depth is registered again to the corrected images.
    """
    if scale == 1.0:
        return scene
    frames = [replace(f, intrinsics=replace(f.intrinsics, fl_x=f.intrinsics.fl_x * scale,
                                            fl_y=f.intrinsics.fl_y * scale),
                      stated_intrinsics=f.stated_intrinsics or f.intrinsics) for f in scene.frames]
    corrected = replace(scene, frames=frames, warnings=list(scene.warnings))
    if scene.depths is not None:
        corrected.depths = [None if d is None else depth_on_image(frames[i], scene.depth_unit_scale, scene.downscale,
                                                                 scene.depth_max)
                            for i, d in enumerate(scene.depths)]
    return corrected


def _downscale_rgb(rgb: np.ndarray, factor: int) -> np.ndarray:
    """uint8 [H, W, 3] -> uint8 [H // f, W // f, 3] by area averaging."""
    if factor == 1:
        return rgb
    h, w = rgb.shape[0] // factor, rgb.shape[1] // factor
    x = torch.from_numpy(rgb[: h * factor, : w * factor]).permute(2, 0, 1)[None].float()
    x = F.avg_pool2d(x, factor)
    return x[0].permute(1, 2, 0).round().clamp(0, 255).to(torch.uint8).numpy()


ASPECT_TOLERANCE = 0.01  # a depth map without depth_intrinsics must have its image's aspect ratio to within 1 %


def read_depth_map(frame: Frame, unit_scale: float, depth_max: float | None) -> tuple[np.ndarray, Intrinsics]:
    """A frame's depth map at its own size and the depth camera's intrinsics.

    Depth: float32 [h, w] scene units, NaN where invalid (0, the 16-bit maximum, NaN, beyond ``depth_max``).
    The camera is ``depth_intrinsics`` when given (the file must have its size, and it is a pinhole); else the
    image's camera (lens included), scaled when the depth map is smaller or larger but covers the same field of
    view (same aspect ratio).
    """
    depth = read_depth(frame.depth_path, unit_scale)
    if depth_max is not None:
        depth[depth > depth_max] = np.nan
    h, w = depth.shape
    colour, given = frame.stated_intrinsics or frame.intrinsics, frame.depth_intrinsics
    if given is not None:
        if (w, h) != (given.width, given.height):
            raise SceneError(frame.depth_path, f"depth map is {w}x{h} but depth_intrinsics say "
                             f"w={given.width} h={given.height}", key="size")
        return depth, given
    if (w, h) == (colour.width, colour.height):
        return depth, colour
    if abs(w * colour.height / (h * colour.width) - 1.0) > ASPECT_TOLERANCE:
        raise SceneError(frame.depth_path, f"depth map is {w}x{h}, image is {colour.width}x{colour.height}: "
                         "a different aspect ratio needs the depth camera's depth_intrinsics", key="size")
    return depth, Intrinsics(colour.fl_x * w / colour.width, colour.fl_y * h / colour.height,
                             colour.cx * w / colour.width, colour.cy * h / colour.height, w, h, colour.lens)


def depth_on_image(frame: Frame, unit_scale: float, factor: int, depth_max: float | None = None) -> np.ndarray:
    """float32 [H // f, W // f] scene units on the image's pixel grid; NaN where invalid.

    A depth map on the image's own camera is area-averaged over its valid pixels (NaN for a block with none);
    one from another camera (another size, or ``depth_intrinsics``) is registered by its intrinsics: each
    pixel takes the depth pixel its centre falls in (nearest, so no depth is invented across an edge).
    """
    depth, camera = read_depth_map(frame, unit_scale, depth_max)
    if camera == frame.intrinsics:
        return _area_average_depth(depth, factor)
    return _register_depth(depth, camera, frame.intrinsics, factor)


def _area_average_depth(depth: np.ndarray, factor: int) -> np.ndarray:
    if factor == 1:
        return depth
    h, w = depth.shape[0] // factor, depth.shape[1] // factor
    d = torch.from_numpy(depth[: h * factor, : w * factor])[None, None]
    valid = torch.isfinite(d)
    total = F.avg_pool2d(torch.where(valid, d, torch.zeros_like(d)), factor)
    count = F.avg_pool2d(valid.float(), factor)
    out = torch.where(count > 0, total / count.clamp_min(1e-12), torch.full_like(total, float("nan")))
    return out[0, 0].numpy()


def _register_depth(depth: np.ndarray, camera: Intrinsics, image: Intrinsics, factor: int) -> np.ndarray:
    """``depth`` (on ``camera``, same pose) sampled at the pixel centres of ``image`` reduced by ``factor``.

    Both cameras share the lens when the depth camera is the image's scaled; a pinhole depth camera
    (``depth_intrinsics``) beside a distorted image is reached through the image's inverse distortion.
    """
    w, h = image.width // factor, image.height // factor
    sx, sy = w / image.width, h / image.height
    y, x = np.meshgrid((np.arange(h) + 0.5 - image.cy * sy) / (image.fl_y * sy),
                       (np.arange(w) + 0.5 - image.cx * sx) / (image.fl_x * sx), indexing="ij")
    if image.lens is not None and camera.lens is None:
        xy = torch.from_numpy(np.stack([x, y], axis=-1))
        xy = undistort(xy, torch.tensor(image.lens.coefficients, dtype=torch.float64), image.lens.model).numpy()
        x, y = xy[..., 0], xy[..., 1]
    cols = np.floor(camera.fl_x * x + camera.cx).astype(np.int64)
    rows = np.floor(camera.fl_y * y + camera.cy).astype(np.int64)
    inside = (rows >= 0) & (rows < camera.height) & (cols >= 0) & (cols < camera.width)
    picked = depth[np.clip(rows, 0, camera.height - 1), np.clip(cols, 0, camera.width - 1)]
    return np.where(inside, picked, np.float32(np.nan)).astype(np.float32)


def inspect_scene(path: str | Path) -> dict:
    """Full validation for upload: the transforms, every image header, the depth maps and the prior.

    Returns :meth:`Scene.summary` with the prior's kind and (given or estimated) sigma filled in.
    """
    from voxnerf.prior.loading import load_prior

    scene = load_scene(path, load_images=False)
    for frame in scene.frames:
        read_rgb(frame.image_path)
        if frame.depth_path is not None:
            read_depth_map(frame, scene.depth_unit_scale, scene.depth_max)
    summary = scene.summary()
    if scene.prior_path is not None:
        prior = load_prior(scene.prior_path, scene.prior_sigma)
        summary["prior"] = {
            "file": scene.prior_path.name,
            "source": scene.prior_key,
            "kind": prior.kind,
            "sigma": prior.sigma,
            "sigma_estimated": prior.sigma_estimated,
        }
    return summary
