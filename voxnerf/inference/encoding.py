"""Encoding a render's outputs as PNG or EXR: one rule for ``voxnerf render`` and ``POST /render``.

numpy only (no torch): the service imports it.

PNG holds one output: ``rgb`` as 8-bit colour, ``depth`` as 16-bit in ``depth_unit_scale`` units (scene
units per stored unit, the scene's ``depth_unit_scale_factor``), ``opacity`` as 8-bit gray (one channel).
EXR holds any of them as float32 channels ``R G B`` (rgb as *linear* light: the model's sRGB-encoded colour,
decoded with the sRGB transfer function, as EXR readers expect), ``Z`` (z-depth, scene units) and ``A`` (opacity).
The CLI writes a PNG render as one file per output: ``IMG.png`` (rgb), ``IMG_depth.png``, ``IMG_opacity.png``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from voxnerf.data.image_io import (
    encode_depth_png16,
    encode_exr,
    encode_gray_png8,
    encode_png,
    srgb_to_linear,
    write_atomic,
)

OUTPUT_NAMES = ("rgb", "depth", "opacity")
MEDIA_TYPES = {"png": "image/png", "exr": "image/x-exr"}
FORMATS = tuple(MEDIA_TYPES)


def _check_outputs(fmt: str, outputs: Sequence[str], images: Mapping[str, np.ndarray]) -> None:
    if fmt not in MEDIA_TYPES:
        raise ValueError(f"unknown format {fmt!r}; choose from {list(FORMATS)}")
    unknown = [name for name in outputs if name not in OUTPUT_NAMES]
    if unknown or not outputs:
        raise ValueError(f"outputs must name at least one of {list(OUTPUT_NAMES)}, got {list(outputs)}")
    if fmt == "png" and len(outputs) != 1:
        raise ValueError(f"a PNG holds one output, got {list(outputs)}: ask for one or use exr")
    missing = [name for name in outputs if name not in images]
    if missing:
        raise ValueError(f"no image for output(s) {missing}")


def encode_outputs(
    images: Mapping[str, np.ndarray], fmt: str, outputs: Sequence[str], depth_unit_scale: float
) -> bytes:
    """PNG or EXR bytes of ``images`` (rgb float [H, W, 3] in [0, 1], depth and opacity float [H, W]).

    ``fmt`` is ``"png"`` (exactly one output) or ``"exr"`` (any of them, channels in the order R G B Z A).
    ``depth_unit_scale``: scene units per stored unit of a depth PNG. Raises ValueError for an unknown
    format or output, a PNG asked for more than one output, or an output missing from ``images``.
    """
    _check_outputs(fmt, outputs, images)
    if fmt == "png":
        (name,) = outputs
        if name == "rgb":
            return encode_png(images["rgb"])
        if name == "depth":
            return encode_depth_png16(images["depth"], depth_unit_scale)
        return encode_gray_png8(images["opacity"])
    channels: dict[str, np.ndarray] = {}
    if "rgb" in outputs:
        rgb = srgb_to_linear(images["rgb"])
        channels.update(R=rgb[..., 0], G=rgb[..., 1], B=rgb[..., 2])
    if "depth" in outputs:
        channels["Z"] = images["depth"]
    if "opacity" in outputs:
        channels["A"] = images["opacity"]
    return encode_exr(channels)


def format_of(path: str | Path) -> str:
    """``"png"`` or ``"exr"`` from a file name's suffix; ValueError for any other."""
    fmt = Path(path).suffix.lower().lstrip(".")
    if fmt not in MEDIA_TYPES:
        raise ValueError(f"output must end in .png or .exr, got {Path(path).name!r}")
    return fmt


def output_path(out: str | Path, name: str) -> Path:
    """Where the CLI writes output ``name`` of a PNG render ``out``: ``IMG.png`` for rgb, else ``IMG_<name>.png``."""
    out = Path(out)
    return out if name == "rgb" else out.with_name(f"{out.stem}_{name}.png")


def encode_files(
    out: str | Path, images: Mapping[str, np.ndarray], outputs: Sequence[str], depth_unit_scale: float
) -> dict[Path, bytes]:
    """The files of a render saved as ``out`` (``.png`` or ``.exr``), each path with its bytes.

    EXR: one file holding every output. PNG: one file per output (see :func:`output_path`).
    """
    fmt = format_of(out)
    if fmt == "exr":
        return {Path(out): encode_outputs(images, "exr", outputs, depth_unit_scale)}
    return {output_path(out, name): encode_outputs(images, "png", [name], depth_unit_scale) for name in outputs}


def write_files(files: Mapping[Path, bytes]) -> list[Path]:
    """Write each file atomically (see :func:`voxnerf.data.image_io.write_atomic`); the paths, in order."""
    for path, data in files.items():
        write_atomic(path, data)
    return list(files)
