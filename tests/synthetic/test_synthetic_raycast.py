"""voxnerf.synthetic.raycast: rendered views match the written PNGs and follow the OpenGL camera axes."""

from __future__ import annotations

from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
from synthetic_fixtures import TINY, make_tiny_scene, meta_of

from voxnerf.synthetic import build_room, render_view


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory) -> Path:
    return make_tiny_scene(tmp_path_factory)


def test_depth_png_matches_rendered_z_depth(tiny_scene: Path):
    meta = meta_of(tiny_scene)
    geom = build_room(TINY.seed)
    for frame in meta["frames"][::7]:
        rgb, depth = render_view(
            geom,
            np.asarray(frame["transform_matrix"]),
            meta["fl_x"],
            meta["cx"],
            meta["cy"],
            meta["w"],
            meta["h"],
            TINY.supersample,
        )
        assert rgb.dtype == np.float32 and depth.dtype == np.float32
        assert np.isfinite(depth).all() and rgb.min() >= 0.0 and rgb.max() <= 1.0
        png_depth = iio.imread(tiny_scene / frame["depth_file_path"]).astype(np.float64) * 0.001
        assert np.abs(png_depth - depth).max() <= 0.001
        png_rgb = iio.imread(tiny_scene / frame["file_path"]).astype(np.float64)
        assert np.abs(png_rgb - rgb * 255).max() <= 0.5 + 1e-3


def test_table_top_projects_to_its_depth(tiny_scene: Path):
    """Project the table top's centre through each camera (OpenGL axes) and intersect the pixel's ray with the
    top's plane analytically: the written depth must equal that z-depth, or be smaller where an object on the
    table occludes it -- never larger (which would mean a flipped axis shows the floor or a wall)."""
    meta = meta_of(tiny_scene)
    lo, hi = (np.asarray(b) for b in meta["voxnerf_synthetic"]["objects"]["table_top"]["bounds"])
    top_z = hi[2]
    centre = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, top_z])
    fl, cx, cy, w, h = meta["fl_x"], meta["cx"], meta["cy"], meta["w"], meta["h"]
    matched = 0
    for frame in meta["frames"]:
        c2w = np.asarray(frame["transform_matrix"])
        x, y, z = np.linalg.inv(c2w)[:3] @ np.append(centre, 1.0)
        if z >= 0:
            continue  # behind the camera (it looks along -Z)
        u, v = cx + fl * x / -z, cy - fl * y / -z
        if not (1 <= u < w - 1 and 1 <= v < h - 1):
            continue
        px, py = int(u), int(v)
        ray_cam = np.array([(px + 0.5 - cx) / fl, -(py + 0.5 - cy) / fl, -1.0])
        ray_world = c2w[:3, :3] @ ray_cam
        t = (top_z - c2w[2, 3]) / ray_world[2]  # z-depth, as the camera z-component of ray_cam is -1
        hit = c2w[:3, 3] + t * ray_world
        assert lo[0] <= hit[0] <= hi[0] and lo[1] <= hit[1] <= hi[1], "the pixel ray should meet the top"
        depth = iio.imread(tiny_scene / frame["depth_file_path"])[py, px] * 0.001
        assert depth <= t + 0.002, frame["file_path"]
        matched += abs(depth - t) <= 0.002
    assert matched >= 2
