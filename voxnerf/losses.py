"""Losses (paper III-D): colour MSE, the robust log-Huber depth term and multi-scale depth smoothness.

``L = L_c + lambda_d * (L_d + L_reg)``. Depths are ray distances in normalised units; ``beta`` must be given in
the same units (the trainer scales the paper's 0.1 scene units by the normalisation).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor


def color_loss(pred: Tensor, target: Tensor) -> Tensor:
    """Mean squared error over rays and channels. pred, target: [R, 3]."""
    return torch.mean((pred - target) ** 2)


def log_huber(residual: Tensor, beta: float | Tensor) -> Tensor:
    """Elementwise robust loss of |residual|: ``r^2 / 2`` below ``beta``, ``beta^2 (1/2 + ln(r / beta))`` above.

    ``beta`` is a positive number or a positive tensor broadcastable to ``residual`` (a beta per ray).
    Continuous with a continuous first derivative at ``beta`` (both branches give ``beta^2 / 2`` and slope
    ``beta``); grows logarithmically, so outliers of any size (1e6) pull with at most ``beta^2 / r``. Finite for
    every finite input and for inf (inf is clamped to the largest float; the log of the ratio is a difference
    of logs, so it cannot overflow).
    """
    r = residual.abs().nan_to_num(nan=0.0, posinf=torch.finfo(residual.dtype).max)
    if isinstance(beta, Tensor):
        small, large, log_beta = torch.minimum(r, beta), torch.maximum(r, beta), torch.log(beta)
    else:
        small, large, log_beta = torch.clamp(r, max=beta), torch.clamp(r, min=beta), math.log(beta)
    quadratic = 0.5 * small * small
    logarithmic = beta * beta * (0.5 + torch.log(large) - log_beta)
    return torch.where(r < beta, quadratic, logarithmic)


def depth_loss(pred: Tensor, target: Tensor, valid: Tensor, beta: float | Tensor) -> Tensor:
    """Mean log-Huber loss over the rays with a valid pseudo depth. pred, target, valid: [R] (target may be NaN
    where invalid); beta a number or [R]. Zero when no ray is valid."""
    residual = torch.where(valid, pred - torch.nan_to_num(target, nan=0.0), torch.zeros_like(pred))
    per_ray = log_huber(residual, beta) * valid
    return per_ray.sum() / valid.sum().clamp_min(1)


def depth_smoothness_loss(depth: Tensor, valid: Tensor, scales: int = 3) -> Tensor:
    """Multi-scale depth-gradient penalty ``sum_s mean(M |G_x(s)| + M |G_y(s)|)`` on image patches.

    Args:
        depth: [P, H, W] rendered depth of P patches; valid: [P, H, W] bool mask M.
        scales: number of scales; scale ``s`` averages 2^s x 2^s blocks (masked mean) before differencing.
    Returns:
        scalar; a gradient counts only where both pixels are valid.
    """
    total = depth.new_zeros(())
    d, m = depth[:, None], valid[:, None].to(depth.dtype)
    for s in range(scales):
        if s > 0:
            if min(d.shape[-2:]) < 2:
                break
            weight = F.avg_pool2d(m, 2)
            d = F.avg_pool2d(d * m, 2) / weight.clamp_min(1e-6)
            m = (weight > 0).to(depth.dtype)
        gx_mask = m[..., :, 1:] * m[..., :, :-1]
        gy_mask = m[..., 1:, :] * m[..., :-1, :]
        gx = (d[..., :, 1:] - d[..., :, :-1]).abs() * gx_mask
        gy = (d[..., 1:, :] - d[..., :-1, :]).abs() * gy_mask
        total = total + gx.sum() / gx_mask.sum().clamp_min(1) + gy.sum() / gy_mask.sum().clamp_min(1)
    return total
