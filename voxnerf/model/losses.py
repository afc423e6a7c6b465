"""Losses (paper III-D): colour MSE, the robust log-Huber depth term and multi-scale depth smoothness, and
mip-NeRF 360's distortion loss.

``L = L_c + lambda_d * (L_d + L_reg) + lambda_dist * L_dist``. Depths are ray distances in normalised units;
``beta`` must be given in the same units (the trainer scales the paper's 0.1 scene units by the normalisation).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

PAPER_BETA = 0.1  # the paper's log-Huber beta, metres; the depth terms compare depths in units of beta / PAPER_BETA

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


def distortion_loss(weights: Tensor, t_starts: Tensor, t_ends: Tensor) -> Tensor:
    """mip-NeRF 360's distortion loss (its eq. 15) in O(S) per ray, averaged over rays.

    Args:
        weights: [R, S] rendering weights; t_starts, t_ends: [R, S] sorted intervals tiling each ray's
            ``[near, far]`` (``t_starts[:, 0]`` to ``t_ends[:, -1]``).
    Returns:
        scalar ``mean_r( sum_ij w_i w_j |m_i - m_j| + 1/3 sum_i w_i^2 d_i )`` with midpoints ``m`` and lengths ``d``
        as fractions of the ray's span, so the value does not depend on the scene's scale: 0 for a single
        infinitely thin surface, larger for weight spread along the ray (floaters, fog).
    The pairwise sum uses exclusive cumulative sums over the sorted midpoints: ``2 sum_i w_i (m_i W_<i - (wm)_<i)``.
    """
    near, span = t_starts[:, :1], (t_ends[:, -1:] - t_starts[:, :1]).clamp_min(1e-9)
    s0, s1 = (t_starts - near) / span, (t_ends - near) / span
    mid, length = 0.5 * (s0 + s1), (s1 - s0).clamp_min(0.0)
    w = weights
    zero = torch.zeros_like(w[:, :1])
    w_before = torch.cat([zero, torch.cumsum(w, -1)[:, :-1]], -1)
    wm_before = torch.cat([zero, torch.cumsum(w * mid, -1)[:, :-1]], -1)
    pairwise = 2.0 * (w * (mid * w_before - wm_before)).sum(-1)
    own = (w * w * length).sum(-1) / 3.0
    return (pairwise + own).mean()


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
