"""voxnerf.cameras.rays: pinhole rays in the OpenGL convention (camera looks along -Z, +Y up, +X right)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from voxnerf.cameras.rays import Intrinsics, camera_rays, image_rays


def _c2w(rot: np.ndarray | None = None, t=(0.0, 0.0, 0.0)) -> torch.Tensor:
    pose = np.eye(4)
    if rot is not None:
        pose[:3, :3] = rot
    pose[:3, 3] = t
    return torch.tensor(pose, dtype=torch.float32)


def _rot_y(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def test_centre_pixel_looks_along_minus_z():
    # a 1x1 image whose principal point is the centre of its only pixel
    intr = Intrinsics(fl_x=1.0, fl_y=1.0, cx=0.5, cy=0.5, width=1, height=1)
    origins, dirs, z_per_t = image_rays(_c2w(t=(1.0, 2.0, 3.0)), intr)
    torch.testing.assert_close(dirs, torch.tensor([[0.0, 0.0, -1.0]]))
    torch.testing.assert_close(origins, torch.tensor([[1.0, 2.0, 3.0]]))
    torch.testing.assert_close(z_per_t, torch.tensor([1.0]))


def test_right_and_down_pixels_go_to_plus_x_and_minus_y():
    px, py = torch.tensor([9, 0]), torch.tensor([0, 9])
    _, dirs, _ = camera_rays(_c2w(), 10.0, 10.0, 5.0, 5.0, px, py)
    # pixel (9, 0): right of and above the centre; pixel (0, 9): left of and below it
    assert dirs[0, 0] > 0 and dirs[0, 1] > 0 and dirs[0, 2] < 0
    assert dirs[1, 0] < 0 and dirs[1, 1] < 0 and dirs[1, 2] < 0


def test_directions_follow_the_pinhole_formula_and_are_unit():
    fl_x, fl_y, cx, cy = 20.0, 30.0, 7.0, 4.0
    px, py = torch.arange(12), torch.arange(12).flip(0)
    _, dirs, z_per_t = camera_rays(_c2w(), fl_x, fl_y, cx, cy, px, py)
    u = (px.double() + 0.5 - cx) / fl_x
    v = (py.double() + 0.5 - cy) / fl_y
    expected = torch.stack([u, -v, -torch.ones_like(u)], -1)
    expected = expected / expected.norm(dim=-1, keepdim=True)
    torch.testing.assert_close(dirs.double(), expected, atol=1e-6, rtol=0)
    torch.testing.assert_close(dirs.norm(dim=-1), torch.ones(12), atol=1e-6, rtol=0)
    # z-depth per unit distance is the cosine between the ray and the view axis
    torch.testing.assert_close(z_per_t.double(), -expected[:, 2], atol=1e-6, rtol=0)


def test_rotation_and_translation_are_applied():
    rot = _rot_y(math.pi / 2)  # turns -Z into -X
    origins, dirs, _ = camera_rays(_c2w(rot, (1.0, 0.0, -2.0)), 1.0, 1.0, 0.5, 0.5, torch.tensor([0]),
                                   torch.tensor([0]))
    torch.testing.assert_close(dirs, torch.tensor([[-1.0, 0.0, 0.0]]), atol=1e-6, rtol=0)
    torch.testing.assert_close(origins, torch.tensor([[1.0, 0.0, -2.0]]))


def test_one_pose_per_ray_equals_a_shared_pose():
    rng = np.random.default_rng(0)
    rot = _rot_y(0.7)
    shared = _c2w(rot, (0.3, -0.2, 1.0))
    n = 16
    px = torch.from_numpy(rng.integers(0, 32, n))
    py = torch.from_numpy(rng.integers(0, 24, n))
    a = camera_rays(shared, 25.0, 25.0, 16.0, 12.0, px, py)
    b = camera_rays(shared.expand(n, 4, 4), torch.full((n,), 25.0), torch.full((n,), 25.0),
                    torch.full((n,), 16.0), torch.full((n,), 12.0), px, py)
    c = camera_rays(shared[:3].expand(n, 3, 4), 25.0, 25.0, 16.0, 12.0, px, py)  # [N, 3, 4] poses
    for x, y, z in zip(a, b, c, strict=True):
        torch.testing.assert_close(x, y)
        torch.testing.assert_close(x, z)


def test_image_rays_are_row_major_and_contiguous():
    intr = Intrinsics(fl_x=8.0, fl_y=8.0, cx=2.5, cy=1.5, width=5, height=3)
    origins, dirs, z_per_t = image_rays(_c2w(), intr)
    assert origins.shape == dirs.shape == (15, 3) and z_per_t.shape == (15,)
    assert origins.is_contiguous() and dirs.is_contiguous()
    assert origins.dtype == dirs.dtype == torch.float32
    grid = dirs.view(3, 5, 3)
    assert (grid[:, 1:, 0] > grid[:, :-1, 0]).all()  # x grows along a row
    assert (grid[1:, :, 1] < grid[:-1, :, 1]).all()  # y falls down the image
    torch.testing.assert_close(grid[1, 2], torch.tensor([0.0, 0.0, -1.0]))  # the centre pixel


@pytest.mark.parametrize("factor", [0.5, 2.0])
def test_scaled_intrinsics_give_the_same_rays_through_the_same_points(factor):
    intr = Intrinsics(fl_x=10.0, fl_y=12.0, cx=4.0, cy=3.0, width=8, height=6)
    scaled = intr.scaled(factor)
    # the ray through a continuous image point (x, y) keeps its direction when the image is resized
    x, y = 4.0, 3.0  # the principal point
    _, d1, _ = camera_rays(_c2w(), intr.fl_x, intr.fl_y, intr.cx, intr.cy, torch.tensor([x - 0.5]),
                           torch.tensor([y - 0.5]))
    _, d2, _ = camera_rays(_c2w(), scaled.fl_x, scaled.fl_y, scaled.cx, scaled.cy,
                           torch.tensor([x * factor - 0.5]), torch.tensor([y * factor - 0.5]))
    torch.testing.assert_close(d1, d2)
