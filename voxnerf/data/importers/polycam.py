"""``voxnerf import polycam``: Polycam's raw-data export (LiDAR / "developer mode"), depth and confidence kept.

Layout (``keyframes/`` at the top of the export, or the ``keyframes`` folder itself), one entry per keyframe
named by its timestamp N:

- ``images/N.jpg`` and ``cameras/N.json``: the colour image and its camera as ARKit tracked it;
- ``corrected_images/N.jpg`` and ``corrected_cameras/N.json`` (when Polycam's own optimisation ran): refined
  poses and the images they belong to; used when both folders exist, as nerfstudio's ``ns-process-data polycam``
  does;
- ``depth/N.png``: 16-bit millimetres at the LiDAR's resolution (256 x 192); ``confidence/N.png``: 8-bit, ARKit's
  low / medium / high written as 0 / 54 / 255 (read here as level 0 below 27, 1 below 155, else 2).

A camera JSON holds ``fx fy cx cy`` and ``width height`` (the image's), and ``t_00 .. t_23``: the top three rows
of the camera-to-world pose with OpenGL camera axes in Polycam's (ARKit's gravity-aligned) world frame, taken as
is (nerfstudio additionally permutes the world axes to make +Z up; a scene needs no particular up axis).
``blur_score`` is ignored. The depth map is registered through the camera it was measured with,
``cameras/N.json`` scaled to its size, beside the corrected colour camera. Keyframes without a camera file are
skipped and counted; one without its depth map keeps its colour image.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from voxnerf.data.image_io import read_depth
from voxnerf.data.importers import arkit, writer
from voxnerf.data.importers.splits import PaperSplitRule
from voxnerf.errors import SceneError

COLOR_SUFFIXES = (".jpg", ".jpeg", ".png")
POSE_KEYS = tuple(f"t_{r}{c}" for r in range(3) for c in range(4))
CONFIDENCE_BOUNDS = (27, 155)
"""8-bit confidence values below the first are ARKit's low, below the second medium, else high."""


def keyframes_dir(src: Path) -> Path:
    """The ``keyframes`` folder of the export at ``src``; SceneError naming what is missing."""
    if not src.is_dir():
        raise SceneError(src, "not a directory")
    for root in (src / "keyframes", src):
        if (root / "cameras").is_dir() or (root / "corrected_cameras").is_dir():
            return root
    raise SceneError(src / "keyframes" / "cameras", "folder not found (a Polycam raw export has keyframes/ with "
                                                     "images/, cameras/, depth/, confidence/)")


def _order(path: Path) -> tuple:
    return (0, int(path.stem), "") if path.stem.isdigit() else (1, 0, path.stem)


def read_camera(path: Path) -> tuple[np.ndarray, arkit.Camera]:
    """The OpenGL camera-to-world pose and the camera of a Polycam camera JSON (SceneError naming it)."""
    try:
        raw = json.loads(path.read_text())
        values = [float(raw[key]) for key in POSE_KEYS]
        k = np.array([[float(raw["fx"]), 0, float(raw["cx"])], [0, float(raw["fy"]), float(raw["cy"])], [0, 0, 1]])
        width, height = int(raw["width"]), int(raw["height"])
    except KeyError as err:
        raise SceneError(path, f"key {err.args[0]!r} missing (a Polycam camera has fx fy cx cy width height "
                               "t_00..t_23)") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, TypeError, ValueError) as err:
        raise SceneError(path, f"cannot read a Polycam camera: {writer.one_line(err)}") from None
    pose = np.eye(4)
    pose[:3, :] = np.array(values).reshape(3, 4)
    return pose, arkit.camera_from_k(k, width, height, path)


def confidence_levels(path: Path) -> np.ndarray:
    """ARKit levels (0 / 1 / 2) of a Polycam 8-bit confidence PNG."""
    import imageio.v3 as iio

    try:
        raw = np.asarray(iio.imread(path))
    except (OSError, ValueError) as err:
        raise SceneError(path, f"cannot read confidence PNG: {writer.one_line(err)}") from None
    if raw.ndim != 2:
        raise SceneError(path, f"confidence must be a single-channel image, got shape {list(raw.shape)}")
    return np.digitize(raw, CONFIDENCE_BOUNDS)


def _image_of(folder: Path, stem: str) -> Path | None:
    for suffix in COLOR_SUFFIXES:
        if (folder / f"{stem}{suffix}").is_file():
            return folder / f"{stem}{suffix}"
    return None


def _depth_of(root: Path, stem: str) -> arkit.DepthSource | None:
    path = root / "depth" / f"{stem}.png"
    if not path.is_file():
        return None
    conf = root / "confidence" / f"{stem}.png"
    # read_depth: 16-bit PNG x 0.001 -> metres, NaN where 0 or 65535; the writer takes NaN as no measurement.
    return arkit.DepthSource(path, lambda: read_depth(path, arkit.DEPTH_UNIT_SCALE),
                             (lambda: confidence_levels(conf)) if conf.is_file() else None,
                             conf if conf.is_file() else None)


def read_polycam(src: str | Path) -> arkit.Capture:
    """The keyframes of the Polycam export at ``src`` in timestamp order (SceneError naming the file at fault)."""
    root = keyframes_dir(Path(src))
    corrected = (root / "corrected_cameras").is_dir() and (root / "corrected_images").is_dir()
    images_dir = root / ("corrected_images" if corrected else "images")
    cameras_dir = root / ("corrected_cameras" if corrected else "cameras")
    if not images_dir.is_dir():
        raise SceneError(images_dir, "folder not found")
    images = sorted((p for p in images_dir.iterdir() if p.suffix.lower() in COLOR_SUFFIXES), key=_order)
    if not images:
        raise SceneError(images_dir, "no images (.jpg or .png) in the folder")
    capture = arkit.Capture("polycam", root)
    capture.notes.append(f"poses and images from {cameras_dir.name}/ and {images_dir.name}/")
    for image in images:
        camera_path = cameras_dir / f"{image.stem}.json"
        if not camera_path.is_file():
            capture.skip("no camera file")
            continue
        c2w, camera = read_camera(camera_path)
        problem = writer.rigid_problem(c2w)
        if problem is not None:
            capture.skip(f"invalid pose ({problem})")
            continue
        depth = _depth_of(root, image.stem)
        depth_camera = None
        if depth is not None and corrected:
            original = root / "cameras" / f"{image.stem}.json"
            if not original.is_file():
                raise SceneError(original, "file not found: the camera its depth map was measured with")
            depth_camera = read_camera(original)[1]
        capture.frames.append(arkit.CaptureFrame(image.stem, c2w, camera, arkit.copier(image),
                                                 image.suffix.lower(), image, depth, depth_camera))
    return capture


def import_polycam(src: str | Path, out: str | Path, splits: PaperSplitRule | None = None,
                   min_confidence: str = arkit.DEFAULT_MIN_CONFIDENCE) -> dict:
    """Write the Polycam export under ``src`` as a scene at ``out`` (absent or empty); returns the summary.

    ``min_confidence``: ``low``, ``medium`` (default) or ``high``; depth below it is dropped. Raises SceneError
    naming the file at fault; on any error nothing is left at ``out``.
    """
    out = Path(out)
    writer.check_out_dir(out)
    arkit.confidence_threshold(min_confidence)
    return arkit.write_capture(out, read_polycam(src), splits, min_confidence)
