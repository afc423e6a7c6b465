"""Importers: other capture layouts written as docs/scene-format.md scenes (``voxnerf import``, and uploads).

- :func:`import_colmap`: a COLMAP sparse model and its images (:mod:`voxnerf.data.importers.colmap`);
- :func:`import_scannet`: ScanNet's exported frames (:mod:`voxnerf.data.importers.scannet`);
- :func:`import_images`: photos without poses, posed by structure from motion (:mod:`voxnerf.data.importers.sfm`);
- :func:`import_video`: a video's sharpest frames, then the same (:mod:`voxnerf.data.importers.video`);
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
from voxnerf.data.importers.scannet import import_scannet
from voxnerf.data.importers.sfm import import_images
from voxnerf.data.importers.splits import PaperSplitRule, paper_splits
from voxnerf.data.importers.video import import_video

__all__ = ["LAYOUTS", "PaperSplitRule", "describe", "detect_layout", "import_colmap", "import_images",
           "import_scannet", "import_video", "paper_splits", "run_import"]

LAYOUTS = ("colmap", "scannet")
COLMAP_MODEL_DIRS = ("sparse/0", "sparse", "")
SCANNET_FOLDERS = ("color", "pose", "intrinsic")


def detect_layout(paths: Iterable[PurePosixPath | str]) -> str | None:
    """``"colmap"``, ``"scannet"`` or None for the relative file paths of a folder or archive.

    A COLMAP model has ``cameras.bin`` or ``cameras.txt`` in ``sparse/0``, ``sparse`` or at the top; a ScanNet
    export has files under ``color/``, ``pose/`` and ``intrinsic/``. (A ``transforms.json`` at the top is a
    scene already; the caller checks that first.)
    """
    paths = {PurePosixPath(p) for p in paths}
    cameras = {PurePosixPath(d) / f"cameras.{ext}" for d in COLMAP_MODEL_DIRS for ext in ("bin", "txt")}
    if paths & cameras:
        return "colmap"
    tops = {p.parts[0] for p in paths if len(p.parts) > 1}
    if all(folder in tops for folder in SCANNET_FOLDERS):
        return "scannet"
    return None


def run_import(layout: str, src: str | Path, out: str | Path, splits: PaperSplitRule | None = None) -> dict:
    """Run the importer of ``layout`` (one of LAYOUTS) from ``src`` into ``out``; its summary."""
    if layout == "colmap":
        return import_colmap(src, out, splits)
    if layout == "scannet":
        return import_scannet(src, out, splits)
    raise ValueError(f"unknown layout {layout!r} (one of {', '.join(LAYOUTS)})")


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
