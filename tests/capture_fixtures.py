"""Captures as users hold them, made from the shared redkitchen scene and the synthetic room: photos without
poses (scaled to 320 x 240 so structure from motion takes seconds) and videos encoded with imageio-ffmpeg's
ffmpeg; and the comparison of an imported scene's poses with the source's after a similarity fit."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from voxnerf.data.importers.alignment import PoseErrors, pose_errors

REDKITCHEN = Path(__file__).resolve().parents[2] / "shared" / "data" / "redkitchen"
needs_redkitchen = pytest.mark.skipif(
    not (REDKITCHEN / "transforms.json").is_file(), reason="shared redkitchen data not present"
)
SIZE = (320, 240)


def redkitchen_frames() -> list[dict]:
    return json.loads((REDKITCHEN / "transforms.json").read_text())["frames"]


def redkitchen_rgb(index: int, size: tuple[int, int] = SIZE) -> np.ndarray:
    """Redkitchen colour frame ``index`` scaled to ``size`` (uint8 [H, W, 3])."""
    with Image.open(REDKITCHEN / "images" / f"frame-{index:06d}.jpg") as im:
        return np.array(im.convert("RGB").resize(size, Image.LANCZOS))


def write_redkitchen_photos(dst: Path, indices, size: tuple[int, int] = SIZE) -> Path:
    """Redkitchen frames ``indices`` as JPEG photos named as in the source (``frame-000000.jpg``)."""
    dst.mkdir(parents=True, exist_ok=True)
    for index in indices:
        Image.fromarray(redkitchen_rgb(index, size)).save(dst / f"frame-{index:06d}.jpg", quality=95)
    return dst


def write_video(path: Path, frames: list[np.ndarray], fps: float = 15, codec: str = "libx264") -> Path:
    """``frames`` (uint8 [H, W, 3], one size) encoded with imageio-ffmpeg's bundled ffmpeg."""
    import imageio_ffmpeg

    height, width = frames[0].shape[:2]
    writer = imageio_ffmpeg.write_frames(str(path), (width, height), fps=fps, codec=codec, quality=8,
                                         macro_block_size=1, ffmpeg_log_level="error")
    writer.send(None)
    for frame in frames:
        writer.send(np.ascontiguousarray(frame))
    writer.close()
    return path


def ffmpeg(*args: str) -> None:
    """Run the bundled ffmpeg (overwriting, errors only)."""
    import imageio_ffmpeg

    subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-y", "-loglevel", "error", *args], check=True)


def with_rotation(src: Path, dst: Path, degrees: int) -> Path:
    """``src`` remuxed (no re-encoding) with a display-matrix rotation of ``degrees`` counter-clockwise, as a
    phone held upright writes it."""
    ffmpeg("-display_rotation", str(degrees), "-i", str(src), "-c", "copy", str(dst))
    return dst


def scene_pose_errors(scene: Path, source_pose_of) -> PoseErrors:
    """Errors of ``scene``'s poses against ``source_pose_of(file_path)`` after the similarity fit."""
    meta = json.loads((scene / "transforms.json").read_text())
    estimated = np.array([f["transform_matrix"] for f in meta["frames"]])
    given = np.array([source_pose_of(f["file_path"]) for f in meta["frames"]])
    return pose_errors(estimated, given)
