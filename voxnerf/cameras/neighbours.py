"""The training cameras nearest a pose: what a rendered view borrows from the training images it lies among.

A scan's per-image errors (pose drift, auto-exposure) change slowly along its path, so a view the scan did not
train on carries about the error of the training cameras near it. :func:`nearest_cameras` finds them and
weighs them by inverse distance; pose refinement and per-image appearance blend their learnt corrections with
these weights (:mod:`voxnerf.cameras.pose_refinement`, :mod:`voxnerf.model.appearance`).
"""

from __future__ import annotations

import torch
from torch import Tensor

NEIGHBOURS = 4  # training cameras a view blends
RADIAN_DISTANCE = 0.5  # the distance (normalised units) one radian between viewing directions counts as


def nearest_cameras(cameras: Tensor, c2w: Tensor, k: int = NEIGHBOURS) -> tuple[Tensor, Tensor]:
    """(index [M, k'] int64, weight [M, k'] summing to 1) of the ``k' = min(k, N)`` training cameras ``cameras``
    [N, 4, 4] nearest each pose ``c2w`` [M, 4, 4] (both normalised units). The distance is that between the
    centres plus :data:`RADIAN_DISTANCE` per radian between the viewing directions; the weight is its inverse,
    so a training camera's own pose takes (all but) all its weight."""
    cameras = cameras.to(c2w.dtype)
    gap = torch.cdist(c2w[:, :3, 3], cameras[:, :3, 3])
    cos = (c2w[:, None, :3, 2] * cameras[None, :, :3, 2]).sum(-1).clamp(-1.0, 1.0)
    distance = gap + RADIAN_DISTANCE * torch.arccos(cos)
    near, index = distance.topk(min(k, cameras.shape[0]), dim=1, largest=False)
    weight = 1.0 / near.clamp_min(1e-6)
    return index, weight / weight.sum(1, keepdim=True)


def blend(values: Tensor, index: Tensor, weight: Tensor) -> Tensor:
    """[M, D] the weighted means of rows ``values`` [N, D] at ``index`` [M, k] with ``weight`` [M, k]."""
    return (weight[..., None] * values.to(weight.dtype)[index]).sum(1)


def identity_cameras(images: int) -> Tensor:
    """[images, 4, 4] identity poses: every camera at the same distance from any view (an even blend)."""
    return torch.eye(4).repeat(images, 1, 1)


def checked_cameras(images: int, cameras: Tensor | None, owner: str) -> Tensor:
    """``cameras`` as a float32 copy, or :func:`identity_cameras` when None; ValueError unless [images, 4, 4]."""
    if cameras is None:
        return identity_cameras(images)
    if tuple(cameras.shape) != (images, 4, 4):
        raise ValueError(f"{owner}: cameras must be [{images}, 4, 4], got {list(cameras.shape)}")
    return cameras.detach().float().clone()
