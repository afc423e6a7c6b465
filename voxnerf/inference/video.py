"""Rendering a camera path to an MP4 video or to a directory of frames.

- MP4: H.264 (libx264, yuv420p, CRF 18) through the ffmpeg binary that the ``imageio-ffmpeg`` wheel carries, so
  no system ffmpeg is needed. yuv420p stores colour at half resolution, so width and height must be even: odd
  sizes are refused (not padded or resized, so every pixel of the video is a rendered one). Only ``rgb`` goes
  into a video. The video is written to a temporary name beside ``out`` and renamed when complete.
- Frames directory: ``frame_00000.png`` (rgb), ``frame_00000_depth.png`` (16-bit, the run's depth unit) and
  ``frame_00000_opacity.png`` (8-bit) as :mod:`voxnerf.inference.encoding` encodes a single render; or with
  ``fmt="exr"``
  one ``frame_00000.exr`` per frame holding channels R G B (Z, A). The directory is built beside ``out`` and
  renamed when complete; ``out`` must be absent or empty.

The path is saved beside what it rendered, in nerfstudio's camera-path JSON (scene units):
``<out>.camera_path.json`` for a video, ``<out>/camera_path.json`` for frames.

A render stopped by ``should_stop`` (or by an exception, Ctrl-C included) leaves nothing at ``out`` and no
temporary file.
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from voxnerf.cameras.paths import CameraPath
from voxnerf.data.image_io import build_dir_atomic, write_atomic
from voxnerf.errors import RunError
from voxnerf.inference.encoding import OUTPUT_NAMES, encode_files
from voxnerf.inference.render import TrainedModel, render

VIDEO_SUFFIX = ".mp4"
FORMATS = ("mp4", "png", "exr")
FRAME_NAME = "frame_{:05d}"
PATH_FILE = "camera_path.json"
# libx264's constant rate factor: 18 is visually lossless for most content (0 lossless, 51 worst).
H264_CRF = 18


@dataclass
class PathRender:
    """What :func:`render_path` did: ``frames`` rendered (all of the path unless ``stopped``), the video or frames
    directory ``out``, the saved camera path ``path_file`` and the wall-clock ``seconds`` it took.

    When ``stopped`` is True, nothing was written: neither ``out`` nor ``path_file`` exists.
    """

    frames: int
    out: Path
    path_file: Path
    seconds: float
    stopped: bool = False


class _Stopped(Exception):
    """``should_stop`` asked to end the render after ``frames`` frames."""

    def __init__(self, frames: int) -> None:
        super().__init__(frames)
        self.frames = frames


def format_of(out: Path, fmt: str | None) -> str:
    """``fmt`` checked against ``out``: ``mp4`` for a ``.mp4`` file, ``png`` (default) or ``exr`` for a frames
    directory. RunError for an unknown format or one that contradicts ``out``."""
    is_video = Path(out).suffix.lower() == VIDEO_SUFFIX
    fmt = fmt or ("mp4" if is_video else "png")
    if fmt not in FORMATS:
        raise RunError(f"{out}: unknown format {fmt!r}; choose from {list(FORMATS)}")
    if (fmt == "mp4") != is_video:
        raise RunError(f"{out}: an MP4 video must end in .mp4 and a frames directory must not (format {fmt})")
    return fmt


def path_file_of(out: Path, fmt: str) -> Path:
    """Where the camera path of a render to ``out`` is saved."""
    out = Path(out)
    return out.with_name(f"{out.name}.camera_path.json") if fmt == "mp4" else out / PATH_FILE


def check_request(path: CameraPath, out: Path, outputs: Sequence[str], fmt: str | None = None) -> str:
    """The checks :func:`render_path` makes before rendering anything; the format (see :func:`format_of`).

    RunError for an unknown format or output, outputs without rgb, anything but rgb in a video, odd video sizes,
    a video over a directory, a frames directory that is not empty.
    """
    out = Path(out)
    fmt = format_of(out, fmt)
    _check_outputs(out, fmt, outputs, path)
    if fmt != "mp4":
        _empty_or_absent(out)
    return fmt


def _check_outputs(out: Path, fmt: str, outputs: Sequence[str], path: CameraPath) -> None:
    unknown = [name for name in outputs if name not in OUTPUT_NAMES]
    if unknown or "rgb" not in outputs:
        raise RunError(f"outputs must hold rgb and any of {list(OUTPUT_NAMES)}, got {list(outputs)}")
    width, height = path.size
    if fmt == "mp4" and list(outputs) != ["rgb"]:
        raise RunError(f"{out}: a video holds rgb only; render {', '.join(outputs[1:])} to a frames directory")
    if fmt == "mp4" and out.is_dir():
        raise RunError(f"{out}: is a directory; a video must be a file")
    if fmt == "mp4" and (width % 2 or height % 2):
        raise RunError(f"{out}: width, height: H.264 (yuv420p) needs even sizes, got {width}x{height}")


def _frames(trained: TrainedModel, path: CameraPath, outputs: Sequence[str], on_frame, should_stop,
            antialias: bool | None):
    """Yield each frame's images (render's dict) in order; _Stopped when ``should_stop`` says so."""
    for i, (pose, intrinsics) in enumerate(zip(path.poses, path.intrinsics, strict=True)):
        if should_stop is not None and should_stop():
            raise _Stopped(i)
        yield render(trained, pose, intrinsics, outputs, antialias=antialias)
        if on_frame is not None:
            on_frame(i + 1, len(path))


def _path_json(path: CameraPath) -> bytes:
    return json.dumps(path.to_nerfstudio(), indent=1).encode()


def _write_video(tmp: Path, frames, path: CameraPath) -> int:
    """Encode ``frames`` (dicts with rgb float [H, W, 3] in [0, 1]) as H.264 into ``tmp``; frames written."""
    import imageio_ffmpeg

    writer = imageio_ffmpeg.write_frames(
        str(tmp), path.size, fps=path.fps, codec="libx264", pix_fmt_out="yuv420p", quality=None,
        macro_block_size=1, ffmpeg_log_level="error",
        output_params=["-crf", str(H264_CRF), "-movflags", "+faststart", "-f", "mp4"],
    )
    writer.send(None)  # start ffmpeg
    count = 0
    try:
        for images in frames:
            rgb = np.round(np.clip(np.nan_to_num(images["rgb"], nan=0.0), 0.0, 1.0) * 255.0).astype(np.uint8)
            writer.send(np.ascontiguousarray(rgb))
            count += 1
    finally:
        writer.close()  # waits for ffmpeg to finish the file
    return count


def _render_video(out: Path, frames, path: CameraPath) -> int:
    """Write the video to a temporary file beside ``out`` and rename it; nothing is left behind on failure."""
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(dir=out.parent, prefix=f".{out.name}.", suffix=f".tmp{VIDEO_SUFFIX}")
    os.close(fd)
    tmp = Path(name)
    try:
        count = _write_video(tmp, frames, path)
        os.chmod(tmp, 0o644)
        os.replace(tmp, out)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    write_atomic(path_file_of(out, "mp4"), _path_json(path))
    return count


def _empty_or_absent(out: Path) -> None:
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise RunError(f"{out}: exists and is not an empty directory (a frames directory is written whole)")


def _render_frames(out: Path, frames, path: CameraPath, fmt: str, outputs: Sequence[str],
                   depth_unit_scale: float) -> int:
    """Write each frame's files into a directory built beside ``out``, renamed to ``out`` when complete."""

    def fill(tmp: Path) -> int:
        count = 0
        for i, images in enumerate(frames):
            name = tmp / f"{FRAME_NAME.format(i)}.{fmt}"
            for file, data in encode_files(name, images, outputs, depth_unit_scale).items():
                file.write_bytes(data)
            count += 1
        (tmp / PATH_FILE).write_bytes(_path_json(path))
        return count

    return build_dir_atomic(out, fill, _empty_or_absent)


def render_path(
    trained: TrainedModel,
    path: CameraPath,
    out: Path,
    *,
    outputs: Sequence[str] = ("rgb",),
    fmt: str | None = None,
    on_frame: Callable[[int, int], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
    antialias: bool | None = None,
) -> PathRender:
    """Render every frame of ``path`` (poses in scene units) with ``trained`` into ``out``.

    Args:
        out: ``VIDEO.mp4`` (format ``mp4``) or a frames directory (``png``, the default, or ``exr``).
        outputs: ``rgb`` plus, for frames directories, ``depth`` (z-depth, scene units) and ``opacity``.
        fmt: ``mp4``, ``png`` or ``exr``; default from ``out`` (see :func:`format_of`).
        on_frame: called as ``on_frame(done, total)`` after each frame.
        should_stop: asked before each frame; True ends the render, leaving nothing at ``out``.
        antialias: see :func:`voxnerf.inference.render.render_normalized` (None: the model's setting).
    Raises:
        RunError: what :func:`check_request` refuses, before anything is rendered.
    """
    out = Path(out)
    fmt = check_request(path, out, outputs, fmt)
    frames = _frames(trained, path, outputs, on_frame, should_stop, antialias)
    start = time.perf_counter()
    try:
        if fmt == "mp4":
            count = _render_video(out, frames, path)
        else:
            count = _render_frames(out, frames, path, fmt, outputs, trained.depth_unit_scale)
    except _Stopped as stop:
        return PathRender(stop.frames, out, path_file_of(out, fmt), time.perf_counter() - start, stopped=True)
    return PathRender(count, out, path_file_of(out, fmt), time.perf_counter() - start)
