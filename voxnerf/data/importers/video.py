"""``voxnerf import video``: a phone video as a scene: frames picked from it, then posed by structure from motion.

- Decoding: imageio-ffmpeg's bundled ffmpeg (MP4 / MOV, H.264 and HEVC as phones write them), frames as 8-bit
  RGB. ffmpeg applies the stream's rotation metadata (its display matrix) while decoding, so a portrait phone
  video gives portrait frames.
- Picking: the video is cut into ``n_frames`` windows of equal duration; from each the sharpest frame is kept,
  sharpness being the variance of the Laplacian of the frame's grey levels (:func:`sharpness`; motion blur
  lowers it). A frame's time is its index over the stream's frame rate (a variable-rate video's times are
  approximate). The frame count comes from the header's duration and rate; frames past it join the last window.
- The picked frames are written as JPEG (quality :data:`voxnerf.data.importers.sfm.JPEG_QUALITY`) named
  ``frame_00000.jpg`` ... in time order, then posed as photos are (:mod:`voxnerf.data.importers.sfm`) with
  sequential matching and one shared camera.
- A file ffmpeg cannot open, one without a video stream, or one whose video stream decodes to no frame is a
  one-line SceneError naming it; nothing is written.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from voxnerf.data.importers import writer
from voxnerf.data.importers.monitor import ImportMonitor
from voxnerf.data.importers.sfm import JPEG_QUALITY, StagedPhotos, reconstruct_and_write, work_dir
from voxnerf.data.importers.splits import PaperSplitRule
from voxnerf.errors import SceneError

DEFAULT_FRAMES = 100
DECODE_SHARE = 0.2
"""The share of a video import's work its decoding takes, as its progress reports it (the rest is structure from
motion); DECODE_REPORT_EVERY frames apart it reports and asks whether to stop."""
DECODE_REPORT_EVERY = 30
MAX_FRAMES = 2000
SHARPNESS_MAX_SIDE = 640
"""Frames are box-averaged down to about this longest side before the Laplacian (same scale for every frame
of a video, so the comparison is fair; fine sensor noise does not count as sharpness)."""


@dataclass(frozen=True)
class PickedFrame:
    """One frame kept from the video."""

    name: str
    index: int
    time: float
    sharpness: float


def sharpness(rgb: np.ndarray) -> float:
    """Variance of the 4-neighbour Laplacian of the grey image (the frame box-averaged to about
    SHARPNESS_MAX_SIDE pixels on its longest side first)."""
    grey = rgb.astype(np.float32).mean(axis=2)
    factor = max(1, int(np.ceil(max(grey.shape) / SHARPNESS_MAX_SIDE)))
    if factor > 1:
        h, w = grey.shape[0] // factor * factor, grey.shape[1] // factor * factor
        grey = grey[:h, :w].reshape(h // factor, factor, w // factor, factor).mean(axis=(1, 3))
    lap = grey[1:-1, :-2] + grey[1:-1, 2:] + grey[:-2, 1:-1] + grey[2:, 1:-1] - 4 * grey[1:-1, 1:-1]
    return float(lap.var()) if lap.size else 0.0


def _open(path: Path):
    """imageio-ffmpeg's frame generator and the stream's metadata; SceneError naming ``path`` when ffmpeg
    finds no video stream in it."""
    import imageio_ffmpeg

    frames = imageio_ffmpeg.read_frames(str(path), pix_fmt="rgb24")
    quiet = logging.getLogger("imageio_ffmpeg")  # it warns when rotation makes the frames' size differ
    level = quiet.level
    quiet.setLevel(logging.ERROR)
    try:
        meta = next(frames)
    except (OSError, RuntimeError, IndexError, ValueError, AttributeError, StopIteration) as err:
        # imageio-ffmpeg raises OSError (with ffmpeg's log) when ffmpeg writes no output stream, IndexError /
        # AttributeError when the log lists no video stream
        frames.close()
        if " Video: " in str(err):  # ffmpeg found a video stream but decoded nothing from it
            raise SceneError(path, "no decodable frames: ffmpeg finds a video stream but cannot decode any frame "
                             "of it (truncated or corrupt file)") from None
        raise SceneError(path, "not a video ffmpeg can decode: no video stream found") from None
    finally:
        quiet.setLevel(level)
    return frames, meta


class _SharpestPerWindow:
    """Frames fed in order; the sharpest of each window written to ``dst`` when the window closes."""

    def __init__(self, dst: Path, n_frames: int, expected: int | None, fps: float) -> None:
        self.dst, self.n_frames, self.expected, self.fps = dst, n_frames, expected, fps
        self.picked: list[PickedFrame] = []
        self.best: tuple[float, int, np.ndarray] | None = None
        self.window = 0

    def window_of(self, index: int) -> int:
        """Frame ``index``'s window: equal shares of the expected frame count (without one, a frame each)."""
        if self.expected:
            return min(self.n_frames - 1, index * self.n_frames // self.expected)
        return min(index, self.n_frames - 1)

    def add(self, index: int, rgb: np.ndarray) -> None:
        window = self.window_of(index)
        if window != self.window:
            self.close()
        self.window = window
        score = sharpness(rgb)
        if self.best is None or score > self.best[0]:
            self.best = (score, index, rgb.copy())

    def close(self) -> None:
        """Write the open window's sharpest frame, if it has one."""
        from PIL import Image

        if self.best is None:
            return
        score, index, rgb = self.best
        name = f"frame_{self.window:05d}.jpg"
        Image.fromarray(rgb).save(self.dst / name, quality=JPEG_QUALITY)
        self.picked.append(PickedFrame(name, index, index / self.fps if self.fps > 0 else float(index), score))
        self.best = None


def _report_decoding(monitor: ImportMonitor, read: int, expected: int | None) -> None:
    monitor.check()
    of = f" of about {expected}" if expected else ""
    monitor.step(f"decoding the video: {read}{of} frames", read / expected if expected else 0.0)


def pick_frames(path: str | Path, n_frames: int, dst: Path,
                monitor: ImportMonitor | None = None) -> tuple[list[PickedFrame], dict]:
    """Write the sharpest frame of each of ``n_frames`` equal time windows of the video at ``path`` into ``dst``
    (``frame_00000.jpg`` ...); the frames kept and the video's facts (codec, size, fps, duration, frames read).
    ``monitor``: frames decoded against the frames the container announces, every DECODE_REPORT_EVERY frames,
    and a stop request (ImportCancelled)."""
    path = Path(path)
    if not path.is_file():
        raise SceneError(path, "video file not found")
    if not 1 <= n_frames <= MAX_FRAMES:
        raise SceneError(path, f"--frames must be between 1 and {MAX_FRAMES}, not {n_frames}", key="--frames")
    frames, meta = _open(path)
    width, height = meta["size"]
    fps = float(meta.get("fps") or 0.0)
    duration = float(meta.get("duration") or 0.0)
    expected = max(1, round(fps * duration)) if fps > 0 and duration > 0 else None
    picker = _SharpestPerWindow(dst, n_frames, expected, fps)
    monitor = monitor or ImportMonitor()
    read = 0
    try:
        for index, data in enumerate(frames):
            picker.add(index, np.frombuffer(data, dtype=np.uint8).reshape(height, width, 3))
            read += 1
            if read % DECODE_REPORT_EVERY == 0:
                _report_decoding(monitor, read, expected)
    except RuntimeError as err:  # the stream breaks off: keep the frames decoded before it
        if not read:
            raise SceneError(path, f"no decodable frames: {writer.one_line(err)}") from None
    finally:
        frames.close()
    picker.close()
    if not picker.picked:
        raise SceneError(path, "no decodable frames in the video stream")
    facts = {"codec": meta.get("codec"), "size": [int(width), int(height)], "fps": fps, "duration_s": duration,
             "frames_read": read, "frames_picked": len(picker.picked)}
    return picker.picked, facts


def import_video(
    src: str | Path, out: str | Path, n_frames: int = DEFAULT_FRAMES, splits: PaperSplitRule | None = None,
    monitor: ImportMonitor | None = None,
) -> dict:
    """Pick ``n_frames`` frames from the video ``src``, pose them by structure from motion and write the scene
    ``out`` (absent or empty). The summary's ``video`` entry gives the stream's facts and, per frame kept, its
    source index, time and sharpness; ``sfm`` what SfM registered. SceneError naming the file at fault,
    ImportCancelled when ``monitor`` asks it to stop; nothing left at ``out`` on error."""
    src, out = Path(src), Path(out)
    writer.check_out_dir(out)
    with work_dir(out) as work:
        staged = StagedPhotos(work / "images")
        staged.dir.mkdir()
        monitor = monitor or ImportMonitor()
        picked, facts = pick_frames(src, n_frames, staged.dir, monitor.within(0.0, DECODE_SHARE))
        staged.names = [frame.name for frame in picked]
        staged.camera_keys = {tuple(facts["size"])}  # one camera: every frame of a stream has its size and lens
        times = {frame.name: frame.time for frame in picked}
        summary = reconstruct_and_write(staged, work, out, splits, "sequential", "video", src,
                                        describe_name=lambda name: f"{name} (t={times[name]:.2f} s)",
                                        monitor=monitor.within(DECODE_SHARE, 1.0))
    video = {**facts, "picked": [{"file": f"images/{f.name}", "frame": f.index, "time_s": round(f.time, 4),
                                  "sharpness": round(f.sharpness, 2)} for f in picked]}
    note = (f"{len(picked)} frames picked from {facts['frames_read']} ({facts['codec']}, "
            f"{facts['size'][0]}x{facts['size'][1]}, {facts['fps']:g} fps): the sharpest of each equal time window")
    return {**summary, "video": video, "notes": [note, *summary["notes"]]}
