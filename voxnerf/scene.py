"""Scene loading and validation per SCENE_FORMAT.md (nerfstudio transforms.json plus VoxNeRF's prior keys).

Every problem raises :class:`SceneError` naming the file and the key. Poses stay in scene units here;
:class:`SceneTransform` maps them into the canonical box the engine trains in.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from voxnerf.cameras import Intrinsics
from voxnerf.errors import SceneError
from voxnerf.image_io import image_size, read_depth, read_rgb

TRANSFORMS = "transforms.json"
INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h")
DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
SPLIT_KEYS = ("train_filenames", "val_filenames", "test_filenames")
DEFAULT_PRIOR_NAME = "prior.ply"
# A rotation whose columns deviate from orthonormal by less than this is re-orthonormalised with a warning;
# more is refused.
ROTATION_TOLERANCE = 0.05
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
    downscale: int = 1
    images: list[np.ndarray | None] | None = None
    depths: list[np.ndarray | None] | None = None
    warnings: list[str] = field(default_factory=list)

    @property
    def train_indices(self) -> list[int]:
        return self.splits["train"]

    @property
    def eval_split_names(self) -> list[str]:
        """Evaluation splits: the named ``eval_splits`` first, then ``test`` (the default split)."""
        names = [name for name in self.splits if name not in ("train", "val", "test") and self.splits[name]]
        return names + (["test"] if self.splits.get("test") else [])

    def intrinsics(self, index: int) -> Intrinsics:
        """Intrinsics of frame ``index`` at the loaded resolution."""
        intr = self.frames[index].intrinsics
        if self.downscale == 1:
            return intr
        w, h = intr.width // self.downscale, intr.height // self.downscale
        return Intrinsics(
            intr.fl_x * w / intr.width, intr.fl_y * h / intr.height,
            intr.cx * w / intr.width, intr.cy * h / intr.height, w, h,
        )

    def summary(self) -> dict:
        """JSON-able description (frames, split sizes, image size, prior file and stated sigma, depth)."""
        first = self.frames[0].intrinsics
        return {
            "frames": len(self.frames),
            "splits": {name: len(idx) for name, idx in self.splits.items()},
            "image_size": [first.width, first.height],
            "prior": None if self.prior_path is None else {
                "file": self.prior_path.name, "sigma": self.prior_sigma,
            },
            "depth": any(f.depth_path is not None for f in self.frames),
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


def _as_finite(value) -> float | None:
    """``value`` as a finite float, or None for non-numbers, NaN, inf and integers too large for a float."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    try:
        number = float(value)
    except OverflowError:  # a JSON integer literal of hundreds of digits
        return None
    return number if math.isfinite(number) else None


def _clip(text: str) -> str:
    """``text`` on one line, at most about 80 characters, and encodable as UTF-8 (hostile input can hold
    anything, lone surrogates from ``\\udc80`` JSON escapes included: those become ``\\udc80`` again)."""
    text = text.replace("\n", " ").replace("\r", " ").encode("utf-8", "backslashreplace").decode("utf-8")
    return text if len(text) <= 80 else f"{text[:60]}... ({len(text)} characters)"


def _short_repr(value) -> str:
    return _clip(repr(value))


def _positive_number(value, path: Path, key: str) -> float:
    number = _as_finite(value)
    if number is None or number <= 0:
        raise _fail(path, f"must be a positive finite number, got {_short_repr(value)}", key)
    return number


def _finite_number(value, path: Path, key: str) -> float:
    number = _as_finite(value)
    if number is None:
        raise _fail(path, f"must be a finite number, got {_short_repr(value)}", key)
    return number


def _read_intrinsics(source: dict, fallback: dict, path: Path, where: str) -> Intrinsics:
    values = {}
    for key in INTRINSIC_KEYS:
        value = source.get(key, fallback.get(key))
        if value is None:
            raise _fail(path, "missing (give it at the top level or in the frame)", f"{where}{key}")
        values[key] = value
    for key in ("w", "h"):
        v = _as_finite(values[key])
        if v is None or v != int(v) or not 0 < v <= 65536:
            raise _fail(path, f"must be a positive integer pixel count, got {_short_repr(values[key])}",
                        f"{where}{key}")
        values[key] = v
    return Intrinsics(
        _positive_number(values["fl_x"], path, f"{where}fl_x"),
        _positive_number(values["fl_y"], path, f"{where}fl_y"),
        _finite_number(values["cx"], path, f"{where}cx"),
        _finite_number(values["cy"], path, f"{where}cy"),
        int(values["w"]),
        int(values["h"]),
    )


def _check_camera_model(meta: dict, frame: dict, path: Path, where: str) -> None:
    model = frame.get("camera_model", meta.get("camera_model", "PINHOLE"))
    if model not in ("PINHOLE", "OPENCV"):
        raise _fail(path, f"unsupported camera model {_short_repr(model)} (PINHOLE or OPENCV)",
                    f"{where}camera_model")
    for key in DISTORTION_KEYS:
        value = frame.get(key, meta.get(key, 0.0))
        if value is None:
            continue
        if model == "PINHOLE" and key in frame and value != 0:
            raise _fail(path, "distortion given with camera_model PINHOLE", f"{where}{key}")
        value = _finite_number(value, path, f"{where}{key}")
        if value != 0:
            raise _fail(
                path,
                f"lens distortion ({key}={value}) is not supported: undistort the images first "
                "(e.g. with COLMAP's image_undistorter) and give camera_model PINHOLE",
                f"{where}{key}",
            )


def _read_pose(value, path: Path, key: str, reorthonormalised: list[tuple[str, float]]) -> np.ndarray:
    try:
        mat = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as exc:
        raise _fail(path, f"must be a 4x4 list of numbers ({_clip(str(exc))})", key) from None
    if mat.shape == (3, 4):
        mat = np.vstack([mat, [0.0, 0.0, 0.0, 1.0]])
    if mat.shape != (4, 4):
        raise _fail(path, f"must be 4x4, got shape {list(mat.shape)}", key)
    if not np.isfinite(mat).all():
        raise _fail(path, "contains NaN or inf", key)
    if not np.allclose(mat[3], [0, 0, 0, 1], atol=1e-6):
        raise _fail(path, f"last row must be [0, 0, 0, 1], got {mat[3].tolist()}", key)
    rot = mat[:3, :3]
    deviation = float(np.abs(rot.T @ rot - np.eye(3)).max())
    if deviation > ROTATION_TOLERANCE or np.linalg.det(rot) <= 0:
        raise _fail(
            path,
            f"rotation is not a proper orthonormal matrix (max |R^T R - I| = {deviation:.3g}, "
            f"det = {np.linalg.det(rot):.3g})",
            key,
        )
    if deviation > 1e-5:
        u, _, vt = np.linalg.svd(rot)
        mat[:3, :3] = u @ vt
        reorthonormalised.append((key, deviation))
    return mat


def _reorthonormalised_warning(fixed: list[tuple[str, float]]) -> str:
    """One warning for every pose whose rotation was re-orthonormalised (a scan can have thousands)."""
    keys = ", ".join(key for key, _ in fixed[:3]) + (f" and {len(fixed) - 3} more" if len(fixed) > 3 else "")
    return f"{keys}: rotation re-orthonormalised (max |R^T R - I| was {max(d for _, d in fixed):.2g})"


def _resolve_inside(root: Path, rel, path: Path, key: str) -> Path:
    if not isinstance(rel, str) or not rel:
        raise _fail(path, f"must be a non-empty relative path string, got {_short_repr(rel)}", key)
    try:
        target = (root / rel).resolve()
        inside = target.is_relative_to(root.resolve())
        found = inside and target.is_file()
    except (OSError, ValueError, RuntimeError) as exc:  # NUL byte, name too long, symlink loop (3.11)
        raise _fail(path, f"unusable path {_short_repr(rel)} ({type(exc).__name__})", key) from None
    if not inside:
        raise _fail(path, f"{_short_repr(rel)} points outside the scene directory", key)
    if not found:
        raise _fail(path, f"file not found: {_clip(rel)}", key)
    return target


def _read_splits(meta: dict, names: list[str], path: Path) -> dict[str, list[int]]:
    index = {name: i for i, name in enumerate(names)}

    def lookup(key: str, files) -> list[int]:
        if not isinstance(files, list) or not all(isinstance(f, str) for f in files):
            raise _fail(path, "must be a list of file_path strings", key)
        missing = [f for f in files if f not in index]
        if missing:
            raise _fail(path, f"{len(missing)} file(s) not in frames, e.g. {missing[0]!r}", key)
        return [index[f] for f in files]

    splits: dict[str, list[int]] = {}
    named = {k: lookup(k, meta[k]) for k in SPLIT_KEYS if k in meta}
    eval_splits = meta.get("eval_splits")
    if eval_splits is not None and not isinstance(eval_splits, dict):
        raise _fail(path, "must be an object mapping split names to lists of file_path", "eval_splits")
    for name in eval_splits or {}:
        if name in ("train", "val", "test"):
            raise _fail(path, f"split name {name!r} is reserved", f"eval_splits.{name}")
        if not SPLIT_NAME.fullmatch(name):  # it names a folder of evaluation renders
            raise _fail(
                path,
                f"split name {_short_repr(name)}: use 1 to 64 letters, digits, '_', '-' or '.', not starting "
                "with '.'",
                "eval_splits",
            )
    extra = {name: lookup(f"eval_splits.{name}", files) for name, files in (eval_splits or {}).items()}
    if not named and not extra:
        test = list(range(0, len(names), 8))
        splits["train"] = [i for i in range(len(names)) if i % 8 != 0]
        splits["test"] = test
        return splits
    if "train_filenames" in named:
        splits["train"] = named["train_filenames"]
    else:
        used = {i for key, idx in named.items() for i in idx} | {i for idx in extra.values() for i in idx}
        splits["train"] = [i for i in range(len(names)) if i not in used]
    if "val_filenames" in named:
        splits["val"] = named["val_filenames"]
    if "test_filenames" in named:
        splits["test"] = named["test_filenames"]
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
        raise SceneError(path, f"invalid JSON: {_clip(str(exc))}") from None
    if not isinstance(meta, dict):
        raise SceneError(path, "top level must be a JSON object")
    return path, meta


def load_scene(path: str | Path, *, downscale: int = 1, load_images: bool = True) -> Scene:
    """Read and validate a scene directory.

    Args:
        path: scene directory holding ``transforms.json``.
        downscale: integer factor; images (area-averaged) and intrinsics are reduced by it.
        load_images: read the images (uint8 [H/d, W/d, 3]) and depth maps (float32 metres, NaN invalid) of
            every frame that a split uses (``None`` for the rest: a 1000-frame scan with 125 frames in its
            splits decodes 125); otherwise only the image headers are checked.
    Raises:
        SceneError: one per problem, naming the file and the key.
    """
    root = Path(path)
    json_path, meta = _read_meta(root)
    if not isinstance(downscale, int) or downscale < 1:
        raise SceneError(json_path, f"downscale must be a positive integer, got {downscale!r}")
    raw_frames = meta.get("frames")
    if not isinstance(raw_frames, list) or not raw_frames:
        raise SceneError(json_path, "must be a non-empty list", key="frames")
    warnings: list[str] = []
    reorthonormalised: list[tuple[str, float]] = []
    frames: list[Frame] = []
    seen: set[str] = set()
    for i, raw in enumerate(raw_frames):
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
        _check_camera_model(meta, raw, json_path, where)
        depth_path = None
        if raw.get("depth_file_path") is not None:
            depth_path = _resolve_inside(root, raw["depth_file_path"], json_path, f"{where}depth_file_path")
        frames.append(Frame(file_path, image_path, c2w, intr, depth_path))
    if reorthonormalised:
        warnings.append(_reorthonormalised_warning(reorthonormalised))

    splits = _read_splits(meta, [f.file_path for f in frames], json_path)
    depth_scale = meta.get("depth_unit_scale_factor", 0.001)
    depth_scale = _positive_number(depth_scale, json_path, "depth_unit_scale_factor")

    prior_path = None
    if meta.get("prior_file_path") is not None:
        prior_path = _resolve_inside(root, meta["prior_file_path"], json_path, "prior_file_path")
    elif (root / DEFAULT_PRIOR_NAME).is_file():
        prior_path = (root / DEFAULT_PRIOR_NAME).resolve()
        warnings.append(f"prior_file_path absent: using {DEFAULT_PRIOR_NAME} found in the scene directory")
    prior_sigma = None
    if meta.get("prior_sigma") is not None:
        prior_sigma = _positive_number(meta["prior_sigma"], json_path, "prior_sigma")

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

    scene = Scene(root.resolve(), frames, splits, prior_path, prior_sigma, depth_scale, downscale,
                  warnings=warnings)
    if load_images:
        used = {i for idx in splits.values() for i in idx}
        scene.images = [_downscale_rgb(read_rgb(f.image_path), downscale) if i in used else None
                        for i, f in enumerate(frames)]
        scene.depths = [
            None if f.depth_path is None or i not in used else _read_depth_at(f, depth_scale, downscale)
            for i, f in enumerate(frames)
        ]
    return scene


def _downscale_rgb(rgb: np.ndarray, factor: int) -> np.ndarray:
    """uint8 [H, W, 3] -> uint8 [H // f, W // f, 3] by area averaging."""
    if factor == 1:
        return rgb
    h, w = rgb.shape[0] // factor, rgb.shape[1] // factor
    x = torch.from_numpy(rgb[: h * factor, : w * factor]).permute(2, 0, 1)[None].float()
    x = F.avg_pool2d(x, factor)
    return x[0].permute(1, 2, 0).round().clamp(0, 255).to(torch.uint8).numpy()


def _read_depth_at(frame: Frame, unit_scale: float, factor: int) -> np.ndarray:
    """float32 [H // f, W // f] metres; NaN where invalid (a block with no valid pixel)."""
    depth = read_depth(frame.depth_path, unit_scale)
    if depth.shape != (frame.intrinsics.height, frame.intrinsics.width):
        raise SceneError(
            frame.depth_path,
            f"depth map is {depth.shape[1]}x{depth.shape[0]}, image is "
            f"{frame.intrinsics.width}x{frame.intrinsics.height}",
            key="size",
        )
    if factor == 1:
        return depth
    h, w = depth.shape[0] // factor, depth.shape[1] // factor
    d = torch.from_numpy(depth[: h * factor, : w * factor])[None, None]
    valid = torch.isfinite(d)
    total = F.avg_pool2d(torch.where(valid, d, torch.zeros_like(d)), factor)
    count = F.avg_pool2d(valid.float(), factor)
    out = torch.where(count > 0, total / count.clamp_min(1e-12), torch.full_like(total, float("nan")))
    return out[0, 0].numpy()


def inspect_scene(path: str | Path) -> dict:
    """Full validation for upload: the transforms, every image header, the depth maps and the prior.

    Returns :meth:`Scene.summary` with the prior's kind and (given or estimated) sigma filled in.
    """
    from voxnerf.prior import load_prior

    scene = load_scene(path, load_images=False)
    for frame in scene.frames:
        read_rgb(frame.image_path)
        if frame.depth_path is not None:
            _read_depth_at(frame, scene.depth_unit_scale, 1)
    summary = scene.summary()
    if scene.prior_path is not None:
        prior = load_prior(scene.prior_path, scene.prior_sigma)
        summary["prior"] = {
            "file": scene.prior_path.name,
            "kind": prior.kind,
            "sigma": prior.sigma,
            "sigma_estimated": prior.sigma_estimated,
        }
    return summary
