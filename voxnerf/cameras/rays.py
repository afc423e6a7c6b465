"""Cameras and ray generation (OpenGL / nerfstudio convention: camera looks along -Z, +Y up).

A camera is a pinhole, or a pinhole behind an OpenCV lens (:mod:`voxnerf.cameras.lens`): a pixel's ray then goes
through the lens's inverse distortion. :class:`Intrinsics` lives in the torch-free
:mod:`voxnerf.cameras.rules` with the pose and intrinsics rules; it is re-exported here.
"""

from __future__ import annotations

import torch
from torch import Tensor

from voxnerf.cameras.lens import LensBatch, lens_directions
from voxnerf.cameras.rules import Intrinsics

__all__ = ["Intrinsics", "camera_rays", "image_rays"]


def camera_rays(
    c2w: Tensor, fl_x: Tensor, fl_y: Tensor, cx: Tensor, cy: Tensor, px: Tensor, py: Tensor,
    lens: LensBatch | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Rays through pixel centres, through the lens when there is one.

    Args:
        c2w: [N, 3, 4] or [N, 4, 4] camera-to-world (OpenGL axes), or one [3|4, 4] shared by all rays.
        fl_x, fl_y, cx, cy: [N] or scalars, pixels.
        px, py: [N] integer (or float) pixel indices; the ray passes through (px + 0.5, py + 0.5).
        lens: None (pinhole), or the lenses of the rays' cameras (coefficients [N, 6], or [1, 6] shared):
            the pixel's distorted normalised coordinates go through the inverse distortion.
    Returns:
        origins [N, 3], unit directions [N, 3], and ``z_per_t`` [N]: the z-depth (along the camera's -Z
        axis) per unit of ray distance, so ``z = t * z_per_t``.
    """
    u = (px.to(torch.float32) + 0.5 - cx) / fl_x
    v = (py.to(torch.float32) + 0.5 - cy) / fl_y
    if lens is None:
        d_cam = torch.stack([u, -v, -torch.ones_like(u)], dim=-1)
        norm = torch.linalg.vector_norm(d_cam, dim=-1, keepdim=True)
        d_cam, z_per_t = d_cam / norm, 1.0 / norm.squeeze(-1)
    else:  # OpenCV axes (x right, y down, z forward) -> OpenGL (x right, y up, z back)
        d_cv = lens_directions(torch.stack([u, v], dim=-1), lens)
        d_cam, z_per_t = d_cv * d_cv.new_tensor([1.0, -1.0, -1.0]), d_cv[:, 2]
    rot = c2w[..., :3, :3].to(torch.float32)
    if rot.dim() == 2:
        dirs = d_cam @ rot.T
        origins = c2w[:3, 3].to(torch.float32).expand_as(dirs)
    else:
        dirs = torch.einsum("nij,nj->ni", rot, d_cam)
        origins = c2w[:, :3, 3].to(torch.float32)
    dirs = dirs / torch.linalg.vector_norm(dirs, dim=-1, keepdim=True)
    return origins.contiguous(), dirs.contiguous(), z_per_t


def image_rays(c2w: Tensor, intr: Intrinsics) -> tuple[Tensor, Tensor, Tensor]:
    """All rays of one image, row-major, through ``intr.lens`` when it has one: origins, dirs [H*W, 3] and
    z_per_t [H*W]."""
    py, px = torch.meshgrid(
        torch.arange(intr.height, device=c2w.device),
        torch.arange(intr.width, device=c2w.device),
        indexing="ij",
    )
    lens = None if intr.lens is None else LensBatch.of([intr.lens], c2w.device)
    return camera_rays(c2w, intr.fl_x, intr.fl_y, intr.cx, intr.cy, px.reshape(-1), py.reshape(-1), lens)
