"""Writing an imported scene: built in a temporary directory beside the output and renamed into place.

Shared by every importer: the output-directory rule (must not exist or be empty), copying frames, the
OpenCV -> OpenGL camera-axes flip, the point-cloud PLY, image-header checks and the atomic transforms.json.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path, PurePosixPath

import numpy as np

from voxnerf.data.image_io import build_dir_atomic, image_size, write_atomic
from voxnerf.errors import SceneError
from voxnerf.files import TRANSFORMS

OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])
"""Right-multiplying a camera-to-world pose by this flips the camera's Y and Z axes: OpenCV (x right, y down,
z forward) to OpenGL / nerfstudio (x right, y up, looking along -z). It is its own inverse."""
POSE_TOLERANCE = 0.05
"""Largest |R^T R - I| entry of a pose still taken as rigid (the scene loader's rotation tolerance)."""


def check_out_dir(out: Path) -> None:
    """SceneError unless ``out`` is absent or an empty directory."""
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise SceneError(out, "the output must not exist or be an empty directory")


def build_scene(out: Path, fill: Callable[[Path], dict]) -> dict:
    """Run ``fill(tmp) -> summary`` on a fresh directory beside ``out`` and rename it to ``out``.

    Nothing is left behind when ``fill`` raises: the temporary directory is removed and ``out`` untouched.
    """
    return build_dir_atomic(Path(out), fill, check_out_dir)


def safe_name(name: str, listed_in: Path) -> PurePosixPath:
    """A relative file name read from a model (``listed_in``), or SceneError if it could leave its folder."""
    path = PurePosixPath(name)
    if not name or "\\" in name or "\x00" in name or path.is_absolute() or ".." in path.parts:
        raise SceneError(listed_in, f"image name {name!r} is not a plain relative path")
    return path


def copy_file(src: Path, dst: Path) -> None:
    """Copy ``src`` to ``dst`` (folders made); SceneError naming ``src`` when it cannot be read."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    try:
        shutil.copyfile(src, dst)
    except OSError as err:
        raise SceneError(src, f"cannot copy: {err.strerror or err}") from None


def check_image(path: Path, width: int, height: int, what: str) -> None:
    """SceneError naming ``path`` unless its header declares ``width`` x ``height`` (nothing is decoded)."""
    got = image_size(path)
    if got != (width, height):
        raise SceneError(path, f"image is {got[0]}x{got[1]} but {what} says {width}x{height}")


def rigid_problem(pose: np.ndarray) -> str | None:
    """Why a 4x4 pose is not a rigid transform (non-finite, scaled / sheared rotation, bad last row)."""
    if pose.shape != (4, 4):
        return f"shape {list(pose.shape)}, expected 4x4"
    if not np.isfinite(pose).all():
        return "non-finite values"
    rot = pose[:3, :3]
    if np.abs(rot.T @ rot - np.eye(3)).max() > POSE_TOLERANCE or np.linalg.det(rot) <= 0:
        return "not a rotation"
    if np.abs(pose[3] - [0.0, 0.0, 0.0, 1.0]).max() > 1e-6:
        return "last row is not 0 0 0 1"
    return None


def write_points_ply(path: Path, xyz: np.ndarray, rgb: np.ndarray) -> None:
    """A binary little-endian PLY point cloud: float32 ``x y z`` and uint8 ``red green blue`` per vertex."""
    vertex = np.empty(
        len(xyz), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")]
    )
    for i, axis in enumerate("xyz"):
        vertex[axis] = xyz[:, i]
    for i, channel in enumerate(("red", "green", "blue")):
        vertex[channel] = rgb[:, i]
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(xyz)}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    )
    path.write_bytes(header.encode("ascii") + vertex.tobytes())


def write_transforms(root: Path, meta: dict) -> None:
    """``root/transforms.json``, written atomically."""
    write_atomic(root / TRANSFORMS, (json.dumps(meta, indent=2) + "\n").encode())


def pose_list(c2w: np.ndarray) -> list[list[float]]:
    """A 4x4 pose as transforms.json writes it (full float precision)."""
    return [[float(v) for v in row] for row in c2w]


def one_line(text: str, limit: int = 200) -> str:
    """``text`` (e.g. a library's error) on one line, clipped to about ``limit`` characters."""
    text = " ".join(str(text).split()).encode("utf-8", "backslashreplace").decode("utf-8")
    return text if len(text) <= limit else f"{text[: limit - 20]}... ({len(text)} characters)"
