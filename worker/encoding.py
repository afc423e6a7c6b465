"""Encoding a render's outputs as the bytes ``POST /render`` answers (the rule is in RenderRequest's doc)."""

from __future__ import annotations

import imageio.v3 as iio
import numpy as np

from voxnerf.image_io import encode_depth_png16, encode_exr, encode_png


def encode_render(
    images: dict[str, np.ndarray], fmt: str, outputs: list[str], depth_unit_scale: float
) -> bytes:
    """PNG or EXR bytes of ``images`` (rgb float32 [H, W, 3] in [0, 1], depth and opacity float32 [H, W]).

    PNG: exactly one output; rgb as 8-bit colour, depth as 16-bit in ``depth_unit_scale`` units (metres per
    unit), opacity as 8-bit gray. EXR: float32 channels R, G, B (rgb), Z (depth, scene units), A (opacity).
    """
    if fmt == "png":
        (name,) = outputs
        if name == "rgb":
            return encode_png(images["rgb"])
        if name == "depth":
            return encode_depth_png16(images["depth"], depth_unit_scale)
        alpha = np.round(np.clip(np.nan_to_num(images["opacity"], nan=0.0), 0.0, 1.0) * 255.0).astype(
            np.uint8
        )
        return iio.imwrite("<bytes>", alpha, extension=".png")
    if fmt != "exr":
        raise ValueError(f"unknown format {fmt!r}")
    channels: dict[str, np.ndarray] = {}
    if "rgb" in outputs:
        channels.update(R=images["rgb"][..., 0], G=images["rgb"][..., 1], B=images["rgb"][..., 2])
    if "depth" in outputs:
        channels["Z"] = images["depth"]
    if "opacity" in outputs:
        channels["A"] = images["opacity"]
    return encode_exr(channels)
