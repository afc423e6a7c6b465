"""``voxnerf import stray``: a Stray Scanner recording (iOS), LiDAR depth and confidence kept.

Layout, as the app's ``docs/format.md`` and its encoders (``OdometryEncoder.swift``, ``DepthEncoder.swift``,
``ConfidenceEncoder.swift``) write it:

- ``rgb.mp4``: the colour video (HEVC on the phone; any codec ffmpeg decodes), one video frame per odometry row,
  decoded in the sensor's orientation (rotation metadata is not applied: the intrinsics and depth maps are in
  the sensor's orientation too);
- ``camera_matrix.csv``: the 3x3 K of the colour camera at the video's resolution (comma-separated rows);
- ``odometry.csv``: a header ``timestamp, frame, x, y, z, qx, qy, qz, qw``, then one row per frame: the camera
  position in ARKit's world (metres) and the rotation ``q_WA * q_AC`` with ``q_AC`` a half turn about X, i.e.
  the camera-to-world pose with OpenCV camera axes; it is turned back to OpenGL axes here;
- ``depth/NNNNNN.png``: 16-bit millimetres, 256 x 192 (older versions: ``.npy`` of integer millimetres);
- ``confidence/NNNNNN.png``: ARKit's levels 0 / 1 / 2 as 8-bit values.

``every``: keep every n-th odometry row (the app records at up to 60 frames per second). Rows without a video
frame and video frames without a row are counted; a frame without its depth map keeps its colour image.
Colour frames are written as JPEG (quality 95).
"""

from __future__ import annotations

import csv
import itertools
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from PIL import Image

from voxnerf.data.image_io import read_depth
from voxnerf.data.importers import arkit, writer
from voxnerf.data.importers.splits import PaperSplitRule
from voxnerf.errors import SceneError

ODOMETRY_COLUMNS = ("timestamp", "frame", "x", "y", "z", "qx", "qy", "qz", "qw")
JPEG_QUALITY = 95


def _check_layout(src: Path) -> None:
    if not src.is_dir():
        raise SceneError(src, "not a directory")
    for name in ("rgb.mp4", "odometry.csv", "camera_matrix.csv"):
        if not (src / name).is_file():
            raise SceneError(src / name, "file not found (a Stray Scanner recording has rgb.mp4, odometry.csv, "
                                         "camera_matrix.csv, depth/, confidence/)")


def read_camera_matrix(path: Path) -> np.ndarray:
    """The 3x3 K of ``camera_matrix.csv``; SceneError naming it when unusable."""
    try:
        rows = [[float(v) for v in line.split(",")] for line in path.read_text().splitlines() if line.strip()]
        k = np.array(rows, dtype=np.float64)
    except (OSError, UnicodeDecodeError, ValueError) as err:
        raise SceneError(path, f"cannot read a 3x3 matrix: {writer.one_line(err)}") from None
    if k.shape != (3, 3):
        raise SceneError(path, f"expected 3 rows of 3 comma-separated numbers, got shape {list(k.shape)}")
    return k


def read_odometry(path: Path) -> list[tuple[int, list[float]]]:
    """``(frame number, [x y z qx qy qz qw])`` per row of ``odometry.csv``; SceneError naming file and line."""
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as err:
        raise SceneError(path, f"cannot read: {writer.one_line(err)}") from None
    reader = csv.reader(lines)
    header = [name.strip() for name in next(reader, [])]
    missing = [name for name in ODOMETRY_COLUMNS[1:] if name not in header]
    if missing:
        raise SceneError(path, f"line 1: header lacks {', '.join(missing)} (expected "
                               f"'{', '.join(ODOMETRY_COLUMNS)}')")
    at = {name: header.index(name) for name in ODOMETRY_COLUMNS[1:]}
    rows = []
    for number, row in enumerate(reader, start=2):
        if not any(cell.strip() for cell in row):
            continue
        try:
            frame = int(float(row[at["frame"]]))
            values = [float(row[at[name]]) for name in ODOMETRY_COLUMNS[2:]]
        except (IndexError, ValueError):
            raise SceneError(path, f"line {number}: expected {len(header)} numbers, got "
                                   f"{writer.one_line(','.join(row), 80)!r}") from None
        rows.append((frame, values))
    if not rows:
        raise SceneError(path, "no odometry rows after the header")
    return rows


class _Video:
    """The frames of ``rgb.mp4`` decoded in order, one at a time (the caller asks for ascending indices)."""

    def __init__(self, path: Path) -> None:
        import imageio_ffmpeg

        self.path = path
        try:
            self._frames: Iterator = imageio_ffmpeg.read_frames(str(path), input_params=["-noautorotate"])
            meta = next(self._frames)
        except (OSError, RuntimeError, StopIteration) as err:
            raise SceneError(path, f"cannot decode video: {writer.one_line(err)}") from None
        self.size = tuple(int(v) for v in meta["size"])
        self._next = 0

    def close(self) -> None:
        """Stop the decoder (its ffmpeg process) before the end of the video."""
        self._frames.close()

    def frame(self, index: int) -> np.ndarray | None:
        """Frame ``index`` as uint8 ``[H, W, 3]``, or None past the end of the video."""
        if index < self._next:
            raise ValueError(f"video frames are read in order: {index} after {self._next - 1}")
        w, h = self.size
        data = None
        try:
            while self._next <= index:
                data = next(self._frames, None)
                self._next += 1
                if data is None:
                    self._next = index + 1
                    return None
        except (OSError, RuntimeError) as err:
            raise SceneError(self.path, f"cannot decode video frame {self._next - 1}: {writer.one_line(err)}") from None
        return np.frombuffer(data, dtype=np.uint8).reshape(h, w, 3)



def count_video_frames(path: Path) -> int:
    """The number of frames ffmpeg decodes from ``path`` (0 when none); SceneError naming it when unreadable."""
    import imageio_ffmpeg

    try:
        return int(imageio_ffmpeg.count_frames_and_secs(str(path))[0])
    except (OSError, RuntimeError, ValueError) as err:
        raise SceneError(path, f"cannot decode video: {writer.one_line(err)}") from None


def _depth_source(src: Path, frame: int) -> arkit.DepthSource | None:
    name = f"{frame:06d}"
    png, npy = src / "depth" / f"{name}.png", src / "depth" / f"{name}.npy"
    conf = src / "confidence" / f"{name}.png"
    if png.is_file():
        path, read = png, (lambda: read_depth(png, arkit.DEPTH_UNIT_SCALE))
    elif npy.is_file():
        path, read = npy, (lambda: _read_npy_millimetres(npy))
    else:
        return None
    return arkit.DepthSource(path, read, (lambda: _read_confidence(conf)) if conf.is_file() else None,
                             conf if conf.is_file() else None)


def _read_npy_millimetres(path: Path) -> np.ndarray:
    try:
        raw = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as err:
        raise SceneError(path, f"cannot read .npy depth: {writer.one_line(err)}") from None
    if raw.dtype.kind not in "ui" or raw.ndim != 2:
        raise SceneError(path, f"expected [H, W] integer millimetres, got {raw.dtype} {list(raw.shape)}")
    return raw.astype(np.float64) * arkit.DEPTH_UNIT_SCALE


def _read_confidence(path: Path) -> np.ndarray:
    import imageio.v3 as iio

    try:
        raw = np.asarray(iio.imread(path))
    except (OSError, ValueError) as err:
        raise SceneError(path, f"cannot read confidence PNG: {writer.one_line(err)}") from None
    if raw.ndim != 2 or raw.max(initial=0) > 2:
        raise SceneError(path, f"expected a single-channel map of levels 0, 1, 2, got {raw.dtype} "
                               f"{list(raw.shape)} up to {raw.max(initial=0)}")
    return raw


def _writer(video: _Video, index: int):
    def write(dst: Path) -> None:
        rgb = video.frame(index)
        if rgb is None:  # counted before writing; the video ended sooner than its first pass said
            raise SceneError(video.path, f"video frame {index} could not be decoded")
        Image.fromarray(rgb).save(dst, format="JPEG", quality=JPEG_QUALITY)
    return write


def read_stray(src: str | Path, every: int = 1) -> tuple[arkit.Capture, _Video]:
    """The frames of the Stray Scanner recording at ``src``, and the video their images are decoded from as
    they are written (close it after); SceneError naming the file at fault."""
    src = Path(src)
    _check_layout(src)
    k = read_camera_matrix(src / "camera_matrix.csv")
    rows = read_odometry(src / "odometry.csv")
    n_video = count_video_frames(src / "rgb.mp4")
    if n_video == 0:
        raise SceneError(src / "rgb.mp4", "no decodable video frames")
    video = _Video(src / "rgb.mp4")
    camera = arkit.camera_from_k(k, video.size[0], video.size[1], src / "camera_matrix.csv")
    capture = arkit.Capture("stray", src)
    unmatched = n_video - len({frame for frame, _ in rows if 0 <= frame < n_video})
    if unmatched > 0:
        capture.notes.append(f"{unmatched} video frame(s) have no odometry row")
    for i in arkit.select_every(len(rows), every):
        frame, values = rows[i]
        if not 0 <= frame < n_video:
            capture.skip("no video frame")
            continue
        try:
            c2w_opencv = arkit.pose_from_quaternion(values[3:], values[:3])
        except ValueError as err:
            capture.skip(f"invalid pose ({writer.one_line(err, 60)})")
            continue
        capture.frames.append(arkit.CaptureFrame(f"{frame:06d}", c2w_opencv @ writer.OPENCV_TO_OPENGL, camera,
                                                 _writer(video, frame), ".jpg", src / "rgb.mp4",
                                                 _depth_source(src, frame)))
    numbers = [int(f.stem) for f in capture.frames]
    if any(b <= a for a, b in itertools.pairwise(numbers)):
        video.close()
        raise SceneError(src / "odometry.csv", "frame numbers must increase from row to row")
    return capture, video


def import_stray(src: str | Path, out: str | Path, splits: PaperSplitRule | None = None,
                 min_confidence: str = arkit.DEFAULT_MIN_CONFIDENCE, every: int = 1) -> dict:
    """Write the Stray Scanner recording under ``src`` as a scene at ``out`` (absent or empty); the summary.

    ``min_confidence``: ``low``, ``medium`` (default) or ``high``; depth below it is dropped. Raises SceneError
    naming the file at fault; on any error nothing is left at ``out``.
    """
    out = Path(out)
    writer.check_out_dir(out)
    arkit.confidence_threshold(min_confidence)
    capture, video = read_stray(src, every)
    try:
        return arkit.write_capture(out, capture, splits, min_confidence)
    finally:
        video.close()
