"""``voxnerf import record3d``: Record3D's "EXR + JPG sequence" export, LiDAR depth kept.

Layout (the export's ``EXR_RGBD`` folder, or a folder holding it): ``metadata.json``, ``rgb/N.jpg`` and
``depth/N.exr`` for frame N = 0, 1, ... (the index into ``poses``). ``metadata.json``:

- ``w``, ``h``: the colour images' size; ``K``: the 3x3 intrinsic matrix as 9 numbers in column-major order
  (``fx 0 0  0 fy 0  cx cy 1``, as nerfstudio's ``record3d_utils`` reads it); ``perFrameIntrinsicCoeffs``
  (newer exports, optional): ``fx fy cx cy`` per frame, used instead of ``K`` when it has one entry per pose;
- ``poses``: per frame ``qx qy qz qw tx ty tz``, the camera-to-world pose in ARKit's axes
  (:mod:`voxnerf.data.importers.arkit`).

Depth EXR: float32 metres in channel ``R`` (or the file's only channel), at the LiDAR's resolution (e.g.
192 x 256 beside 720 x 960 colour). The export holds no confidence maps, so the depth is kept as exported (0,
NaN and inf: no measurement). Frames without an image or with an invalid pose
are skipped and counted; a frame without its EXR keeps its colour image. ``every``: keep every n-th frame.

Record3D's own ``.r3d`` file (a zip of the same metadata with LZFSE-compressed depth) is refused with a message
asking for the EXR + JPG export: its layout is documented only by ad-hoc scripts, and the EXR export carries the
same poses, intrinsics and depth.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from voxnerf.data.image_io import decode_exr
from voxnerf.data.importers import arkit, writer
from voxnerf.data.importers.splits import PaperSplitRule
from voxnerf.errors import SceneError

METADATA = "metadata.json"
EXPORT_FOLDER = "EXR_RGBD"
COLOR_SUFFIXES = (".jpg", ".jpeg", ".png")


def export_root(src: Path) -> Path:
    """``src`` or its ``EXR_RGBD`` folder, whichever holds ``metadata.json``; SceneError naming what is missing."""
    if src.suffix.lower() == ".r3d" and src.is_file():
        raise SceneError(src, "Record3D's .r3d files are not read: export the recording as 'EXR + JPG sequence' "
                              "and import its folder")
    if not src.is_dir():
        raise SceneError(src, "not a directory")
    for root in (src, src / EXPORT_FOLDER):
        if (root / METADATA).is_file():
            return root
    raise SceneError(src / METADATA, f"file not found (a Record3D EXR + JPG export has {METADATA}, rgb/, depth/)")


def _read_metadata(path: Path) -> dict:
    try:
        meta = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise SceneError(path, f"cannot read JSON: {writer.one_line(err)}") from None
    if not isinstance(meta, dict):
        raise SceneError(path, "expected a JSON object")
    for key in ("w", "h", "K", "poses"):
        if key not in meta:
            raise SceneError(path, "missing (a Record3D export's metadata has w, h, K, poses)", key=key)
    if not isinstance(meta["poses"], list) or not meta["poses"]:
        raise SceneError(path, "must be a non-empty list of [qx, qy, qz, qw, tx, ty, tz]", key="poses")
    return meta


def _cameras(meta: dict, path: Path) -> list[arkit.Camera]:
    """One camera per pose: ``perFrameIntrinsicCoeffs`` when it covers every pose, else ``K`` for all."""
    try:
        w, h = int(meta["w"]), int(meta["h"])
        coeffs = meta.get("perFrameIntrinsicCoeffs")
        if isinstance(coeffs, list) and len(coeffs) == len(meta["poses"]):
            return [arkit.camera_from_k(np.array([[c[0], 0, c[2]], [0, c[1], c[3]], [0, 0, 1]], dtype=float), w, h,
                                        path) for c in coeffs]
        k = np.array(meta["K"], dtype=np.float64).reshape(3, 3).T  # stored column-major
    except (TypeError, ValueError, IndexError) as err:
        raise SceneError(path, f"intrinsics unreadable: {writer.one_line(err)}", key="K") from None
    return [arkit.camera_from_k(k, w, h, path)] * len(meta["poses"])


def read_depth_exr(path: Path) -> np.ndarray:
    """A Record3D depth EXR as float metres ``[H, W]``: channel ``R``, or the only channel."""
    try:
        channels = decode_exr(path.read_bytes())
    except (OSError, ValueError) as err:
        raise SceneError(path, f"cannot read depth EXR: {writer.one_line(err)}") from None
    if "R" in channels:
        return channels["R"].astype(np.float64)
    if len(channels) == 1:
        return next(iter(channels.values())).astype(np.float64)
    raise SceneError(path, f"no depth channel: expected R or a single channel, got {sorted(channels)}")


def _image_of(root: Path, index: int) -> Path | None:
    for suffix in COLOR_SUFFIXES:
        path = root / "rgb" / f"{index}{suffix}"
        if path.is_file():
            return path
    return None


def read_record3d(src: str | Path, every: int = 1) -> arkit.Capture:
    """The frames of the Record3D export at ``src`` (SceneError naming the file at fault)."""
    root = export_root(Path(src))
    meta_path = root / METADATA
    meta = _read_metadata(meta_path)
    if not (root / "rgb").is_dir():
        raise SceneError(root / "rgb", "folder not found (a Record3D EXR + JPG export has rgb/ and depth/)")
    cameras = _cameras(meta, meta_path)
    capture = arkit.Capture("record3d", root)
    capture.notes.append("Record3D's EXR export has no confidence maps: its depth is kept as exported")
    width = max(5, len(str(len(meta["poses"]) - 1)))
    for index in arkit.select_every(len(meta["poses"]), every):
        image = _image_of(root, index)
        if image is None:
            capture.skip("no image file")
            continue
        try:
            values = [float(v) for v in meta["poses"][index]]
            if len(values) != 7:
                raise ValueError(f"{len(values)} numbers, expected 7")
            c2w = arkit.pose_from_quaternion(values[:4], values[4:])
        except (TypeError, ValueError) as err:
            capture.skip(f"invalid pose ({writer.one_line(err, 60)})")
            continue
        camera = cameras[index]
        depth_path = root / "depth" / f"{index}.exr"
        depth = None
        if depth_path.is_file():
            depth = arkit.DepthSource(depth_path, lambda p=depth_path: read_depth_exr(p), None)
        capture.frames.append(arkit.CaptureFrame(f"{index:0{width}d}", c2w, camera, arkit.copier(image),
                                                 image.suffix.lower(), image, depth))
    return capture


def import_record3d(src: str | Path, out: str | Path, splits: PaperSplitRule | None = None, every: int = 1) -> dict:
    """Write the Record3D export under ``src`` as a scene at ``out`` (absent or empty); returns the summary.

    Raises SceneError naming the file at fault; on any error nothing is left at ``out``.
    """
    out = Path(out)
    writer.check_out_dir(out)
    capture = read_record3d(src, every)
    # No confidence maps exist in this export: nothing to filter by, whatever is asked.
    return arkit.write_capture(out, capture, splits, "low")
