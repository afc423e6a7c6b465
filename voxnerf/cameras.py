"""Pinhole cameras and ray generation (OpenGL / nerfstudio convention: camera looks along -Z, +Y up).

:class:`Intrinsics` lives in the torch-free :mod:`voxnerf.camera_rules` with the pose and intrinsics rules;
it is re-exported here.
"""

from __future__ import annotations

import torch
from torch import Tensor

from voxnerf.camera_rules import Intrinsics

__all__ = ["Intrinsics", "camera_rays", "image_rays"]


def camera_rays(
    c2w: Tensor, fl_x: Tensor, fl_y: Tensor, cx: Tensor, cy: Tensor, px: Tensor, py: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """Rays through pixel centres.

    Args:
        c2w: [N, 3, 4] or [N, 4, 4] camera-to-world (OpenGL axes), or one [3|4, 4] shared by all rays.
        fl_x, fl_y, cx, cy: [N] or scalars, pixels.
        px, py: [N] integer (or float) pixel indices; the ray passes through (px + 0.5, py + 0.5).
    Returns:
        origins [N, 3], unit directions [N, 3], and ``z_per_t`` [N]: the z-depth (along the camera's -Z
        axis) per unit of ray distance, so ``z = t * z_per_t``.
    """
    u = (px.to(torch.float32) + 0.5 - cx) / fl_x
    v = (py.to(torch.float32) + 0.5 - cy) / fl_y
    d_cam = torch.stack([u, -v, -torch.ones_like(u)], dim=-1)
    norm = torch.linalg.vector_norm(d_cam, dim=-1, keepdim=True)
    d_cam = d_cam / norm
    rot = c2w[..., :3, :3].to(torch.float32)
    if rot.dim() == 2:
        dirs = d_cam @ rot.T
        origins = c2w[:3, 3].to(torch.float32).expand_as(dirs)
    else:
        dirs = torch.einsum("nij,nj->ni", rot, d_cam)
        origins = c2w[:, :3, 3].to(torch.float32)
    dirs = dirs / torch.linalg.vector_norm(dirs, dim=-1, keepdim=True)
    return origins.contiguous(), dirs.contiguous(), (1.0 / norm.squeeze(-1))


def image_rays(c2w: Tensor, intr: Intrinsics) -> tuple[Tensor, Tensor, Tensor]:
    """All rays of one image, row-major: origins, dirs [H*W, 3] and z_per_t [H*W]."""
    py, px = torch.meshgrid(
        torch.arange(intr.height, device=c2w.device),
        torch.arange(intr.width, device=c2w.device),
        indexing="ij",
    )
    return camera_rays(c2w, intr.fl_x, intr.fl_y, intr.cx, intr.cy, px.reshape(-1), py.reshape(-1))
