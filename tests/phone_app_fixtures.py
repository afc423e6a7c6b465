"""The shared redkitchen scene re-expressed as LiDAR phone-app exports (Record3D, Polycam, Stray Scanner).

Each writer takes redkitchen frame entries and writes the app's layout as the app does: poses converted into the
app's convention (quaternions ``qx qy qz qw`` for Record3D and Stray, OpenCV camera axes for Stray), depth
resampled to the LiDAR's 256 x 192 grid, and confidence maps with low and medium regions. The checks compare an
imported scene with the source frames.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from voxnerf.data.image_io import encode_exr

REDKITCHEN = Path(__file__).resolve().parents[2] / "shared" / "data" / "redkitchen"
needs_redkitchen = pytest.mark.skipif(
    not (REDKITCHEN / "transforms.json").is_file(), reason="shared redkitchen data not present"
)
FLIP = np.diag([1.0, -1.0, -1.0, 1.0])  # OpenGL <-> OpenCV camera axes
K_7SCENES = np.array([[585.0, 0.0, 320.0], [0.0, 585.0, 240.0], [0.0, 0.0, 1.0]])
WIDTH, HEIGHT = 640, 480
DEPTH_W, DEPTH_H = 256, 192
LOW, MEDIUM, HIGH = 0, 1, 2


def redkitchen_frames(n: int, start: int = 0) -> list[dict]:
    return json.loads((REDKITCHEN / "transforms.json").read_text())["frames"][start:start + n]


def rotation_to_quaternion(rot: np.ndarray) -> list[float]:
    """``[qx, qy, qz, qw]`` of a rotation matrix (the largest of the four terms picks the formula)."""
    m = np.asarray(rot, dtype=np.float64)
    trace = np.trace(m)
    candidates = [trace, m[0, 0], m[1, 1], m[2, 2]]
    k = int(np.argmax(candidates))
    if k == 0:
        s = 2.0 * np.sqrt(1.0 + trace)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4]
    elif k == 1:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [s / 4, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif k == 2:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 1] + m[1, 0]) / s, s / 4, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, s / 4, (m[1, 0] - m[0, 1]) / s]
    return [float(v) for v in q]


def nearest_rigid(pose: np.ndarray) -> np.ndarray:
    """``pose`` with its rotation replaced by the nearest rotation (redkitchen's are float32-rounded)."""
    u, _, vt = np.linalg.svd(pose[:3, :3])
    out = np.array(pose, dtype=np.float64)
    out[:3, :3] = u @ vt
    return out


def depth_pixel_sources(size: tuple[int, int] = (DEPTH_W, DEPTH_H)) -> tuple[np.ndarray, np.ndarray]:
    """For each LiDAR-grid pixel, the 640 x 480 source row and column whose area holds its centre."""
    w, h = size
    rows = np.floor((np.arange(h) + 0.5) * HEIGHT / h).astype(int)
    cols = np.floor((np.arange(w) + 0.5) * WIDTH / w).astype(int)
    return rows, cols


def lidar_depth_mm(frame: dict) -> np.ndarray | None:
    """The frame's 16-bit millimetre depth resampled to 256 x 192 (nearest: every value is a source value)."""
    if "depth_file_path" not in frame:
        return None
    full = iio.imread(REDKITCHEN / frame["depth_file_path"])
    rows, cols = depth_pixel_sources()
    return full[np.ix_(rows, cols)].astype(np.uint16)


def lidar_confidence() -> np.ndarray:
    """ARKit levels on the 256 x 192 grid: low on the left 40 columns, medium on the bottom 42 rows, else high."""
    conf = np.full((DEPTH_H, DEPTH_W), HIGH, dtype=np.uint8)
    conf[150:, :] = MEDIUM
    conf[:, :40] = LOW
    return conf


def expected_depth_on_image(depth_mm: np.ndarray, confidence: np.ndarray | None, min_level: int,
                            before: tuple[bool, bool] = (False, False)) -> np.ndarray:
    """What the engine must see on the 640 x 480 image: each pixel takes the LiDAR pixel its centre falls in;
    NaN where there is no measurement or the confidence is below ``min_level``. ``before`` (rows, columns): a
    centre exactly on the edge between two LiDAR pixels (every 5th row and column at this 2.5 ratio) takes the one
    before instead, since rounding may put it on either side."""
    metres = depth_mm.astype(np.float64) * 0.001
    metres[depth_mm == 0] = np.nan
    if confidence is not None:
        metres[confidence < min_level] = np.nan

    def cells(n: int, n_depth: int, edge_before: bool) -> np.ndarray:
        twice = (2 * np.arange(n) + 1) * n_depth  # the centre's depth-grid coordinate times 2n, exactly
        index = twice // (2 * n)
        return np.where(twice % (2 * n) == 0, np.maximum(index - 1, 0), index) if edge_before else index

    rows, cols = cells(HEIGHT, DEPTH_H, before[0]), cells(WIDTH, DEPTH_W, before[1])
    return metres[np.ix_(rows, cols)]


def write_record3d(dst: Path, frames: list[dict]) -> Path:
    """Record3D's EXR + JPG export: ``EXR_RGBD/metadata.json``, ``rgb/N.jpg``, ``depth/N.exr`` (float metres)."""
    root = dst / "EXR_RGBD"
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    poses = []
    for i, frame in enumerate(frames):
        c2w = nearest_rigid(np.asarray(frame["transform_matrix"]))
        poses.append(rotation_to_quaternion(c2w[:3, :3]) + [float(v) for v in c2w[:3, 3]])
        shutil.copyfile(REDKITCHEN / frame["file_path"], root / "rgb" / f"{i}.jpg")
        depth = lidar_depth_mm(frame)
        if depth is not None:
            (root / "depth" / f"{i}.exr").write_bytes(encode_exr({"R": depth.astype(np.float32) * 0.001}))
    meta = {"w": WIDTH, "h": HEIGHT, "fps": 30, "dw": DEPTH_W, "dh": DEPTH_H,
            "K": [float(v) for v in K_7SCENES.T.reshape(-1)], "poses": poses}
    (root / "metadata.json").write_text(json.dumps(meta))
    return dst


def polycam_camera(frame: dict, k: np.ndarray = K_7SCENES) -> dict:
    c2w = np.asarray(frame["transform_matrix"], dtype=np.float64)
    camera = {"fx": k[0, 0], "fy": k[1, 1], "cx": k[0, 2], "cy": k[1, 2], "width": WIDTH, "height": HEIGHT,
              "blur_score": 100.0, "timestamp": 0, "manual_keyframe": False}
    camera.update({f"t_{r}{c}": float(c2w[r, c]) for r in range(3) for c in range(4)})
    return camera


def polycam_stem(i: int) -> str:
    return str(1_700_000_000_000 + 33 * i)


def write_polycam(dst: Path, frames: list[dict]) -> Path:
    """Polycam's raw export: ``keyframes/{images,cameras,depth,confidence}/<timestamp>.*``; confidence as 0/54/255."""
    root = dst / "keyframes"
    for sub in ("images", "cameras", "depth", "confidence"):
        (root / sub).mkdir(parents=True)
    polycam_values = np.array([0, 54, 255], dtype=np.uint8)
    for i, frame in enumerate(frames):
        stem = polycam_stem(i)
        shutil.copyfile(REDKITCHEN / frame["file_path"], root / "images" / f"{stem}.jpg")
        (root / "cameras" / f"{stem}.json").write_text(json.dumps(polycam_camera(frame)))
        depth = lidar_depth_mm(frame)
        if depth is not None:
            iio.imwrite(root / "depth" / f"{stem}.png", depth)
            iio.imwrite(root / "confidence" / f"{stem}.png", polycam_values[lidar_confidence()])
    return dst


def encode_video(path: Path, images: list[Path], fps: int = 30) -> None:
    """An H.264 MP4 of ``images`` (all 640 x 480) through imageio-ffmpeg's ffmpeg."""
    import imageio_ffmpeg

    writer = imageio_ffmpeg.write_frames(str(path), (WIDTH, HEIGHT), fps=fps, codec="libx264", quality=9,
                                         macro_block_size=16, output_params=["-g", "10"])
    writer.send(None)
    for image in images:
        writer.send(np.ascontiguousarray(iio.imread(image)))
    writer.close()


def write_stray(dst: Path, frames: list[dict]) -> Path:
    """A Stray Scanner recording: ``rgb.mp4``, ``odometry.csv`` (OpenCV camera axes, as the app writes it),
    ``camera_matrix.csv``, ``depth/NNNNNN.png`` (16-bit mm) and ``confidence/NNNNNN.png`` (levels 0/1/2)."""
    (dst / "depth").mkdir(parents=True)
    (dst / "confidence").mkdir()
    encode_video(dst / "rgb.mp4", [REDKITCHEN / f["file_path"] for f in frames])
    lines = ["timestamp, frame, x, y, z, qx, qy, qz, qw"]
    for i, frame in enumerate(frames):
        c2w_cv = nearest_rigid(np.asarray(frame["transform_matrix"])) @ FLIP
        q = rotation_to_quaternion(c2w_cv[:3, :3])
        t = c2w_cv[:3, 3]
        lines.append(", ".join([f"{1000 + i / 30:.6f}", f"{i:06d}"] + [repr(float(v)) for v in (*t, *q)]))
        depth = lidar_depth_mm(frame)
        if depth is not None:
            iio.imwrite(dst / "depth" / f"{i:06d}.png", depth)
            iio.imwrite(dst / "confidence" / f"{i:06d}.png", lidar_confidence())
    (dst / "odometry.csv").write_text("\n".join(lines) + "\n")
    (dst / "camera_matrix.csv").write_text("\n".join(", ".join(repr(float(v)) for v in row) for row in K_7SCENES))
    return dst


def check_poses(scene: Path, source: list[dict], quaternions: bool) -> dict:
    """transforms.json of ``scene`` has ``source``'s frames in order, each pose within 1e-6; returns it.

    ``quaternions``: the export stored rotations as quaternions, which hold only rotations: redkitchen's matrices
    are orthonormal to about 5e-5 (KinectFusion's, printed to 8 digits), so the reference is then the nearest
    rotation to each (and the raw matrix is within 1e-4).
    """
    meta = json.loads((scene / "transforms.json").read_text())
    assert len(meta["frames"]) == len(source)
    for got, want in zip(meta["frames"], source, strict=True):
        reference = np.asarray(want["transform_matrix"])
        if quaternions:
            np.testing.assert_allclose(got["transform_matrix"], reference, atol=1e-4)
            reference = nearest_rigid(reference)
        np.testing.assert_allclose(got["transform_matrix"], reference, atol=1e-6)
    assert (meta["fl_x"], meta["fl_y"], meta["cx"], meta["cy"], meta["w"], meta["h"]) == (585, 585, 320, 240,
                                                                                          WIDTH, HEIGHT)
    return meta


def check_depth_registration(scene: Path, source: list[dict], confidence: np.ndarray | None, min_level: int) -> int:
    """Every imported depth map, registered by the engine onto its image, equals the source LiDAR-grid depth
    looked up at each image pixel's centre (NaN where dropped); returns how many frames were checked."""
    from voxnerf.data.scene import depth_on_image, load_scene

    loaded = load_scene(scene, load_images=False)
    checked = 0
    for frame, want in zip(loaded.frames, source, strict=True):
        depth_mm = lidar_depth_mm(want)
        assert (frame.depth_path is not None) == (depth_mm is not None)
        if depth_mm is None:
            continue
        got = depth_on_image(frame, loaded.depth_unit_scale, 1)
        matches = [(np.isnan(got) & np.isnan(want)) | (np.abs(got - want) <= 1e-6)
                   for want in (expected_depth_on_image(depth_mm, confidence, min_level, (r, c))
                                for r in (False, True) for c in (False, True))]
        assert np.all(np.any(matches, axis=0))
        assert np.all(matches[0][1:-1:5, 1:-1:5])  # a pixel off every edge has one answer
        checked += 1
    return checked
