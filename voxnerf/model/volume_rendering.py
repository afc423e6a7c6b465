"""Volume rendering (paper eq. 1-3), stable by construction.

Tensor contract (nerfacc style, dense packing): every ray carries ``S`` samples, as intervals
``[t_starts, t_ends]`` along unit-length directions, shapes ``[R, S]``, sorted and non-overlapping.

- ``alpha = -expm1(-sigma * delta)``: exact for tiny optical depth, saturates to 1 for huge ones;
- ``T_i = exp(-sum_{j<i} sigma_j delta_j)`` from an exclusive cumulative sum (no product of many alphas);
- optical depth clamped to ``[0, MAX_OPTICAL_DEPTH]``: densities up to inf and steps down to 0 stay finite.
"""

from __future__ import annotations

import torch
from torch import Tensor

# exp(-1e4) is 0 in float32 and float64: clamping here loses nothing and keeps cumsums finite.
MAX_OPTICAL_DEPTH = 1.0e4


def render_weights(densities: Tensor, t_starts: Tensor, t_ends: Tensor) -> tuple[Tensor, Tensor]:
    """Per-sample weights and transmittance.

    Args:
        densities: [R, S] non-negative densities (per unit length); NaN is treated as an error upstream.
        t_starts, t_ends: [R, S] interval bounds along the ray.
    Returns:
        weights [R, S] in [0, 1] with ``weights.sum(-1) = 1 - exp(-sum tau) <= 1``, and transmittance [R, S]
        (the probability of reaching each interval's start).
    """
    deltas = (t_ends - t_starts).clamp_min(0.0)
    tau = torch.nan_to_num(densities * deltas, nan=0.0, posinf=MAX_OPTICAL_DEPTH).clamp(0.0, MAX_OPTICAL_DEPTH)
    alphas = -torch.expm1(-tau)
    # Exclusive sum by shifting, not ``cumsum(tau) - tau``: that cancels catastrophically after an opaque
    # interval (1e4 + 1e-3 - 1e4 keeps only float32's 1e-3 resolution at 1e4) and let weights sum above 1.
    optical_before = torch.cat([torch.zeros_like(tau[..., :1]), torch.cumsum(tau[..., :-1], dim=-1)], dim=-1)
    transmittance = torch.exp(-optical_before)
    return transmittance * alphas, transmittance


def volume_render(
    densities: Tensor,
    rgbs: Tensor,
    t_starts: Tensor,
    t_ends: Tensor,
    background: Tensor | None = None,
) -> dict[str, Tensor]:
    """Composite samples into pixels.

    Args:
        densities: [R, S]; rgbs: [R, S, 3] in [0, 1]; t_starts, t_ends: [R, S] ray distances.
        background: [3] or [R, 3] colour behind the last interval (default black).
    Returns:
        ``rgb`` [R, 3]; ``opacity`` [R] in [0, 1]; ``depth`` [R] expected ray distance with the residual
        transmittance placed at the ray's far bound (so always within [t_starts[:, 0], t_ends[:, -1]]);
        ``weights`` [R, S].
    """
    weights, _ = render_weights(densities, t_starts, t_ends)
    opacity = weights.sum(-1).clamp(0.0, 1.0)
    residual = 1.0 - opacity
    rgb = (weights[..., None] * rgbs).sum(-2)
    if background is not None:
        rgb = rgb + residual[:, None] * background
    mids = 0.5 * (t_starts + t_ends)
    depth = (weights * mids).sum(-1) + residual * t_ends[:, -1]
    depth = torch.minimum(torch.maximum(depth, t_starts[:, 0]), t_ends[:, -1])
    return {"rgb": rgb, "opacity": opacity, "depth": depth, "weights": weights}
