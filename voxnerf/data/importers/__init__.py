"""Importers: other capture layouts written as docs/scene-format.md scenes (``voxnerf import``, and uploads).

- :func:`import_colmap`: a COLMAP sparse model and its images (:mod:`voxnerf.data.importers.colmap`);
- :func:`import_scannet`: ScanNet's exported frames (:mod:`voxnerf.data.importers.scannet`);
- :func:`import_images`: photos without poses, posed by structure from motion (:mod:`voxnerf.data.importers.sfm`);
- :func:`import_video`: a video's sharpest frames, then the same (:mod:`voxnerf.data.importers.video`);
- :func:`import_rosbag`: a robot's ROS 1 / ROS 2 bag (:mod:`voxnerf.data.importers.rosbag`);
- :func:`import_record3d`, :func:`import_polycam`, :func:`import_stray`: LiDAR phone apps' exports with their
  depth (:mod:`voxnerf.data.importers.record3d`, ``.polycam``, ``.stray``; ARKit's conventions in ``.arkit``);
- ``splits=PaperSplitRule()``: the paper's train / interpolation / extrapolation splits
  (:mod:`voxnerf.data.importers.splits`), the same rule for every importer.

Each returns a JSON-able summary: ``format``, ``frames``, ``skipped`` (count per reason), ``camera_models``,
``depth_frames``, ``prior`` (file, points, sigma and its rule; None without one), ``splits`` (the rule's
parameters and the frame counts; None without ``splits``) and ``notes``; the SfM importers add ``sfm`` (and a
video ``video``). Torch-free: the API imports this
package on upload.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path, PurePosixPath

from voxnerf.data.importers.colmap import import_colmap
from voxnerf.data.importers.monitor import ImportCancelled, ImportMonitor
from voxnerf.data.importers.polycam import import_polycam
from voxnerf.data.importers.record3d import import_record3d
from voxnerf.data.importers.rosbag import RosbagOptions, import_rosbag
from voxnerf.data.importers.scannet import import_scannet
from voxnerf.data.importers.sfm import import_images
from voxnerf.data.importers.splits import PaperSplitRule, paper_splits
from voxnerf.data.importers.stray import import_stray
from voxnerf.data.importers.video import import_video

__all__ = ["LAYOUTS", "MONITORED_LAYOUTS", "QUEUED_LAYOUTS", "ImportCancelled", "ImportMonitor", "PaperSplitRule",
           "RosbagOptions", "capture_file_layout", "describe",
           "detect_layout", "import_colmap", "import_images", "import_polycam", "import_record3d", "import_rosbag",
           "import_scannet", "import_stray", "import_video", "paper_splits", "run_import"]

# Each layout's importer with its default options, called as ``importer(src, out, splits)``; those of
# MONITORED_LAYOUTS also take ``monitor=`` (an ImportMonitor: progress within the import, and a stop request).
IMPORTERS = {
    "colmap": import_colmap,
    "scannet": import_scannet,
    "record3d": import_record3d,
    "polycam": import_polycam,
    "stray": import_stray,
    "rosbag": import_rosbag,
    "images": import_images,
    "video": lambda src, out, splits, monitor=None: import_video(src, out, splits=splits, monitor=monitor),
}
LAYOUTS = tuple(IMPORTERS)
MONITORED_LAYOUTS = ("images", "video")
# Layouts whose import reads a whole capture (a phone's video, a robot's log) or solves for poses: the service
# queues them as import jobs instead of importing them while the upload's request waits.
QUEUED_LAYOUTS = ("stray", "rosbag", "images", "video")
PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png")  # a folder of only these (at its top) is photos to pose
COLMAP_MODEL_DIRS = ("sparse/0", "sparse", "")
SCANNET_FOLDERS = ("color", "pose", "intrinsic")
STRAY_FILES = ("rgb.mp4", "odometry.csv")
ROS2_BAG_METADATA = "metadata.yaml"
ROS2_STORAGE_SUFFIXES = (".db3", ".mcap")
# A capture sent as one file, known by its first bytes: its layout and the file name suffix its reader expects.
# A ROS 1 bag (format 2.0), an MCAP file or an SQLite 3 database (the two storages of a ROS 2 bag).
CAPTURE_FILES = {
    b"#ROSBAG V2.0\n": ("rosbag", ".bag"),
    b"\x89MCAP0\r\n": ("rosbag", ".mcap"),
    b"SQLite format 3\x00": ("rosbag", ".db3"),
}
VIDEO_BOX = b"ftyp"  # an MP4 or QuickTime file: its first box, at byte 4, is ``ftyp`` with the brand after it
QUICKTIME_BRAND = b"qt  "
CAPTURE_MAGIC_BYTES = max(12, *(len(magic) for magic in CAPTURE_FILES))


def detect_layout(paths: Iterable[PurePosixPath | str]) -> str | None:
    """One of LAYOUTS, or None, for the relative file paths of a folder or archive.

    A COLMAP model has ``cameras.bin`` or ``cameras.txt`` in ``sparse/0``, ``sparse`` or at the top; a ScanNet
    export has files under ``color/``, ``pose/`` and ``intrinsic/``; a Record3D export ``metadata.json`` beside
    ``rgb/`` (at the top or in ``EXR_RGBD/``); a Polycam export camera files in ``cameras/`` or
    ``corrected_cameras/`` (at the top or in ``keyframes/``); a Stray Scanner recording ``rgb.mp4`` and
    ``odometry.csv`` at the top; a ROS 2 bag folder ``metadata.yaml`` and its ``.db3`` or ``.mcap`` storage at
    the top; photos to pose (``images``) JPEG or PNG files alone, all at the top. (A ``transforms.json`` at the
    top is a scene already; the caller checks that first.)
    """
    paths = {PurePosixPath(p) for p in paths}
    cameras = {PurePosixPath(d) / f"cameras.{ext}" for d in COLMAP_MODEL_DIRS for ext in ("bin", "txt")}
    if paths & cameras:
        return "colmap"
    tops = {p.parts[0] for p in paths if len(p.parts) > 1}
    if all(folder in tops for folder in SCANNET_FOLDERS):
        return "scannet"
    if all(PurePosixPath(name) in paths for name in STRAY_FILES):
        return "stray"
    folders = {p.parent for p in paths}
    for base in (PurePosixPath("."), PurePosixPath("EXR_RGBD")):
        if base / "metadata.json" in paths and any(f.parts[: len(base.parts) + 1] == (*base.parts, "rgb")
                                                   for f in folders):
            return "record3d"
    for base in (PurePosixPath("."), PurePosixPath("keyframes")):
        if {base / "cameras", base / "corrected_cameras"} & folders:
            return "polycam"
    top_files = {p for p in paths if len(p.parts) == 1}
    if PurePosixPath(ROS2_BAG_METADATA) in top_files and any(p.suffix in ROS2_STORAGE_SUFFIXES for p in top_files):
        return "rosbag"
    if paths and paths == top_files and all(p.suffix.lower() in PHOTO_SUFFIXES for p in paths):
        return "images"
    return None


def capture_file_layout(head: bytes) -> tuple[str, str] | None:
    """The layout of a capture sent as one file and the suffix its file needs, from its first
    :data:`CAPTURE_MAGIC_BYTES` bytes (nothing else is read): ``("rosbag", ".bag")`` for a ROS 1 bag, ``.mcap``
    or ``.db3`` for a ROS 2 bag's storage, ``("video", ".mp4")`` or ``".mov"`` for an MP4 or QuickTime video (as
    phones write them); None for anything else (a zip, say)."""
    if head[4:8] == VIDEO_BOX:
        return ("video", ".mov" if head[8:12] == QUICKTIME_BRAND else ".mp4")
    return next((kind for magic, kind in CAPTURE_FILES.items() if head.startswith(magic)), None)


def run_import(layout: str, src: str | Path, out: str | Path, splits: PaperSplitRule | None = None,
               monitor: ImportMonitor | None = None) -> dict:
    """Run the importer of ``layout`` (one of LAYOUTS) from ``src`` into ``out``, with each importer's default
    options (a bag's topics found automatically); its summary. ``monitor`` follows the importers of
    MONITORED_LAYOUTS as they run (the others report nothing until they end)."""
    importer = IMPORTERS.get(layout)
    if importer is None:
        raise ValueError(f"unknown layout {layout!r} (one of {', '.join(LAYOUTS)})")
    if monitor is not None and layout in MONITORED_LAYOUTS:
        return importer(src, out, splits, monitor=monitor)
    return importer(src, out, splits)


def describe(summary: dict) -> list[str]:
    """An importer's summary in a few lines for people."""
    skipped = summary.get("skipped") or {}
    skip_text = ", ".join(f"{n} {why}" for why, n in skipped.items())
    lines = [f"{summary['format']}: imported {summary['frames']} frames"
             + (f", skipped {sum(skipped.values())} ({skip_text})" if skipped else "")]
    lines.append(f"cameras: {', '.join(summary['camera_models'])}; frames with depth: {summary['depth_frames']}")
    prior = summary.get("prior")
    if prior:
        sigma = f"{prior['sigma']:.4g}" if prior.get("sigma") is not None else "not given"
        lines.append(f"prior: {prior['file']}, {prior['points']} points, sigma {sigma} ({prior['sigma_rule']})")
    splits = summary.get("splits")
    if splits:
        params = ", ".join(f"{k}={v}" for k, v in splits.items() if k not in ("train", "interpolation",
                                                                              "extrapolation"))
        lines.append(f"splits ({params}): train {splits['train']}, interpolation {splits['interpolation']}, "
                     f"extrapolation {splits['extrapolation']}")
    lines += [f"note: {note}" for note in summary.get("notes", [])]
    return lines
