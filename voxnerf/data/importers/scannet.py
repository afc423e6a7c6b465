"""``voxnerf import scannet``: ScanNet's exported frames (the SensReader layout) as a docs/scene-format.md scene.

Layout: ``color/N.jpg``, ``depth/N.png`` (16-bit millimetres), ``pose/N.txt`` (4x4 camera-to-world, OpenCV
camera axes), ``intrinsic/intrinsic_color.txt`` and ``intrinsic/intrinsic_depth.txt`` (4x4, K in the top-left).

- Frames are ordered by their number N. A frame whose pose is invalid (ScanNet writes rows of ``-inf`` where
  tracking was lost; also NaN, a scaled or sheared rotation) or whose pose file is missing or unreadable is
  skipped, and the skips are counted by reason. A frame without a depth map keeps its colour image.
- Poses are converted to OpenGL camera axes (camera Y and Z flipped); ScanNet's world frame is kept.
- Intrinsics: ScanNet's K is taken as given, i.e. its principal point is assumed to be in this project's
  continuous pixel coordinates (the centre of a W x H image at W/2), as nerfstudio's and MonoSDF's ScanNet
  loaders take it; were it in OpenCV's pixel-index convention the true centre would be 0.5 px further, below
  ScanNet's calibration accuracy. The colour camera gives the top-level ``fl_x fl_y cx cy`` (``w h`` from the
  colour images); the depth camera gives ``depth_intrinsics`` (``w h`` from the depth maps), by which the
  loader registers each depth map (640x480) to its colour image (1296x968): same pose, other intrinsics.
- Depth: copied to ``depth/N.png`` with ``depth_file_path`` per frame and ``depth_unit_scale_factor`` 0.001.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from voxnerf.data.image_io import image_size, read_png_header
from voxnerf.data.importers import writer
from voxnerf.data.importers.splits import PaperSplitRule, SplitError, split_keys
from voxnerf.errors import SceneError

DEPTH_UNIT_SCALE = 0.001
COLOR_SUFFIXES = (".jpg", ".jpeg", ".png")


@dataclass
class _Frame:
    stem: str
    color: Path
    c2w: np.ndarray
    depth: Path | None


@dataclass
class _Export:
    src: Path
    frames: list[_Frame] = field(default_factory=list)
    skipped: dict = field(default_factory=dict)

    def skip(self, reason: str) -> None:
        self.skipped[reason] = self.skipped.get(reason, 0) + 1


def _order(path: Path) -> tuple:
    return (0, int(path.stem), "") if path.stem.isdigit() else (1, 0, path.stem)


def read_intrinsic(path: Path) -> np.ndarray:
    """The 3x3 K of a ScanNet intrinsic file (4x4 or 3x3 text); SceneError naming the file when unusable."""
    try:
        values = [float(v) for v in path.read_text().split()]
    except (OSError, ValueError, UnicodeDecodeError) as err:
        raise SceneError(path, f"cannot read a 4x4 intrinsic matrix: {writer.one_line(err)}") from None
    if len(values) not in (9, 16):
        raise SceneError(path, f"expected a 4x4 (or 3x3) matrix, got {len(values)} numbers")
    side = 4 if len(values) == 16 else 3
    k = np.array(values).reshape(side, side)[:3, :3]
    if not np.isfinite(k).all() or k[0, 0] <= 0 or k[1, 1] <= 0:
        raise SceneError(path, "focal lengths must be positive and every entry finite")
    return k


def _intrinsics(k: np.ndarray, size: tuple[int, int]) -> dict:
    return {"fl_x": float(k[0, 0]), "fl_y": float(k[1, 1]), "cx": float(k[0, 2]), "cy": float(k[1, 2]),
            "w": int(size[0]), "h": int(size[1])}


def _read_pose(path: Path) -> tuple[np.ndarray | None, str | None]:
    """The OpenGL camera-to-world pose in a ScanNet pose file, or None and why it is skipped."""
    try:
        values = [float(v) for v in path.read_text().split()]
    except (OSError, ValueError, UnicodeDecodeError):
        return None, "unreadable pose file"
    if len(values) != 16:
        return None, "unreadable pose file"
    pose = np.array(values).reshape(4, 4)
    problem = writer.rigid_problem(pose)
    if problem is not None:
        return None, f"invalid pose ({problem})"
    return pose @ writer.OPENCV_TO_OPENGL, None


def _check_depth(path: Path, size: tuple[int, int] | None) -> tuple[int, int]:
    """SceneError naming ``path`` unless it is a 16-bit single-channel PNG of ``size`` (when given)."""
    header = read_png_header(path)
    if header is None or header.bit_depth != 16 or header.color_type != 0:
        raise SceneError(path, "ScanNet depth must be a 16-bit single-channel PNG (millimetres)")
    if size is not None and (header.width, header.height) != size:
        raise SceneError(path, f"depth map is {header.width}x{header.height}, the first one {size[0]}x{size[1]}")
    return header.width, header.height


def _collect(export: _Export) -> None:
    src = export.src
    colors = sorted((p for p in (src / "color").iterdir() if p.suffix.lower() in COLOR_SUFFIXES), key=_order)
    if not colors:
        raise SceneError(src / "color", "no colour images (.jpg or .png) in the folder")
    for color in colors:
        pose_path = src / "pose" / f"{color.stem}.txt"
        if not pose_path.is_file():
            export.skip("no pose file")
            continue
        c2w, why = _read_pose(pose_path)
        if c2w is None:
            export.skip(why)
            continue
        depth = src / "depth" / f"{color.stem}.png"
        export.frames.append(_Frame(color.stem, color, c2w, depth if depth.is_file() else None))
    if not export.frames:
        raise SceneError(src / "pose", f"no usable frame: all {len(colors)} are skipped ({export.skipped})")


def _check_layout(src: Path) -> None:
    if not src.is_dir():
        raise SceneError(src, "not a directory")
    for need in ("color", "pose"):
        if not (src / need).is_dir():
            raise SceneError(src / need, "folder not found (a ScanNet export has color/, depth/, pose/, intrinsic/)")
    if not (src / "intrinsic" / "intrinsic_color.txt").is_file():
        raise SceneError(src / "intrinsic" / "intrinsic_color.txt", "file not found")


def _depth_keys(export: _Export) -> tuple[dict, list[str]]:
    """``depth_unit_scale_factor`` and ``depth_intrinsics`` (when any frame has depth), and notes."""
    with_depth = [f for f in export.frames if f.depth is not None]
    if not with_depth:
        return {}, ["no depth maps: the scene has no sensor depth"]
    size = None
    for frame in with_depth:
        size = _check_depth(frame.depth, size)
    keys: dict = {"depth_unit_scale_factor": DEPTH_UNIT_SCALE}
    depth_k = export.src / "intrinsic" / "intrinsic_depth.txt"
    if depth_k.is_file():
        keys["depth_intrinsics"] = _intrinsics(read_intrinsic(depth_k), size)
        return keys, []
    return keys, ["intrinsic/intrinsic_depth.txt missing: depth maps are taken to cover the colour field of view"]


def _fill(root: Path, export: _Export, color_k: np.ndarray, splits: PaperSplitRule | None) -> dict:
    size = image_size(export.frames[0].color)
    meta: dict = {"camera_model": "PINHOLE", **_intrinsics(color_k, size)}
    depth_keys, notes = _depth_keys(export)
    meta.update(depth_keys)
    meta["frames"] = [_write_frame(root, frame, size) for frame in export.frames]
    split_summary = None
    if splits is not None:
        try:
            keys, split_summary = split_keys([f["file_path"] for f in meta["frames"]], splits)
        except SplitError as err:
            raise SceneError(export.src, str(err), key="--splits paper") from None
        meta.update(keys)
    writer.write_transforms(root, meta)
    depth_frames = sum(f.depth is not None for f in export.frames)
    if depth_frames:
        notes.append("no prior file: the engine fuses one from the training frames' depth maps")
    if 0 < depth_frames < len(export.frames):
        notes.append(f"{len(export.frames) - depth_frames} frame(s) without a depth map")
    return {
        "format": "scannet",
        "frames": len(export.frames),
        "skipped": dict(export.skipped),
        "camera_models": ["PINHOLE"],
        "depth_frames": depth_frames,
        "prior": None,
        "splits": split_summary,
        "notes": notes,
    }


def _write_frame(root: Path, frame: _Frame, size: tuple[int, int]) -> dict:
    writer.check_image(frame.color, size[0], size[1], "the first colour image")
    name = f"images/{frame.color.name}"
    writer.copy_file(frame.color, root / name)
    entry = {"file_path": name, "transform_matrix": writer.pose_list(frame.c2w)}
    if frame.depth is not None:
        entry["depth_file_path"] = f"depth/{frame.stem}.png"
        writer.copy_file(frame.depth, root / entry["depth_file_path"])
    return entry


def import_scannet(src: str | Path, out: str | Path, splits: PaperSplitRule | None = None) -> dict:
    """Write the ScanNet export under ``src`` as a scene at ``out`` (absent or empty); returns the summary.

    ``splits``: write the paper's splits (:mod:`voxnerf.data.importers.splits`), else no split keys. Raises
    SceneError naming the file at fault; on any error nothing is left at ``out``.
    """
    src, out = Path(src), Path(out)
    writer.check_out_dir(out)
    _check_layout(src)
    color_k = read_intrinsic(src / "intrinsic" / "intrinsic_color.txt")
    export = _Export(src)
    _collect(export)
    return writer.build_scene(out, lambda root: _fill(root, export, color_k, splits))
