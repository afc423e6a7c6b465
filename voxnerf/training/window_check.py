"""How well the VoxNeRF sampler's window around the octree's first hit holds the surface a ray sees (issue #46).

The sampler (paper III-C, :class:`voxnerf.model.samplers.VoxNeRFSampler`) puts its importance samples within
``3 sqrt(3) v`` of the first occupied leaf a ray meets and spreads the rest uniformly. It pays only where that
first hit lies within the window of the true surface; these functions measure, against a depth (a synthetic
room's exact depth, a sensor's), how often it does and what the window is worth next to the prior's real noise:

- :func:`first_hit_check`: of the rays with a depth, the share whose ray hits no leaf (they fall back to the
  occupancy grid), stops short (first hit more than the half-width before the depth: a noisy or stray leaf in
  front) or passes through (first hit more than the half-width beyond it: the surface's leaves are missing);
  the first hit's offset from the depth; the half-width against the prior's noise measured along the rays.
- :func:`samples_near` / :func:`share_outside`: the share of a sampler's samples within a band of the depth,
  and of the VoxNeRF sampler's samples outside its own window.
- :func:`choose_sampler`: sampler ``auto``'s choice from the first check, the VoxNeRF sampler unless its window
  misses the surface on too many rays.

Plain numpy (no torch): the set-up stage ``window_check`` (:mod:`voxnerf.training.stages.window_check`) hands
its tensors over as arrays. Distances are normalised ray distances (NaN where there is none) and come back in
metres through ``scale`` (normalised units per metre).
"""

from __future__ import annotations

import numpy as np

MAD_TO_SIGMA = 1.4826
"""A normal distribution's standard deviation over its median absolute deviation."""


def robust_spread(values: np.ndarray) -> float | None:
    """``MAD_TO_SIGMA`` x the median absolute deviation of the finite ``values`` (the standard deviation of
    normal noise, unmoved by a few outliers); None when there are none."""
    values = np.asarray(values, np.float64)
    values = values[np.isfinite(values)]
    if not values.size:
        return None
    return float(MAD_TO_SIGMA * np.median(np.abs(values - np.median(values))))


def first_hit_check(hit_t: np.ndarray, hit: np.ndarray, true_t: np.ndarray, half_window: float, scale: float,
                    prior_t: np.ndarray | None = None, prior_sigma: float | None = None) -> dict:
    """The octree's first hits ``hit_t`` (with ``hit``: whether the ray met a leaf) against the depth ``true_t``,
    all normalised ray distances of the same rays (any shape; NaN in ``true_t`` where there is no depth, such rays
    are left out). ``half_window`` is the sampler's half-width and ``prior_sigma`` the prior's stated sigma
    (normalised); ``prior_t`` the prior's own depth along the rays (NaN where the prior is not seen), whose offset
    from ``true_t`` gives the prior's real noise. ValueError when the shapes differ or a length is not positive.

    Returns (fractions of the rays with a depth, lengths in metres): ``rays``, ``miss``, ``stop_short``,
    ``pass_through``, ``wrong_first_hit`` (the last two together), ``half_window_m``, ``first_hit_offset_m``
    (``p10``, ``p50``, ``p90`` of first hit minus depth over the rays that hit; None without one), ``prior_sigma_m``,
    ``prior_noise_m`` (robust spread of the prior's depth minus the depth) and ``window_over_noise``
    (``half_window_m / prior_noise_m``); each None where it cannot be measured.
    """
    hit_t, true_t = np.asarray(hit_t, np.float64).ravel(), np.asarray(true_t, np.float64).ravel()
    hit = np.asarray(hit, bool).ravel()
    if not hit_t.shape == hit.shape == true_t.shape or (prior_t is not None and np.size(prior_t) != true_t.size):
        raise ValueError(f"first hits, hit flags, depths (and prior depths) must have one shape, got "
                         f"{hit_t.shape}, {hit.shape}, {true_t.shape}"
                         + ("" if prior_t is None else f", {np.shape(prior_t)}"))
    if not (np.isfinite(half_window) and half_window > 0 and np.isfinite(scale) and scale > 0):
        raise ValueError(f"half_window and scale must be positive numbers, got {half_window!r}, {scale!r}")
    half_window, scale = float(half_window), float(scale)  # plain floats: the result goes into report.json
    with_depth = np.isfinite(true_t)
    n = int(with_depth.sum())
    hits = with_depth & hit & np.isfinite(hit_t)
    offset = (hit_t - true_t)[hits] / scale
    half_m = half_window / scale
    out: dict = {"rays": n, "half_window_m": half_m,
                 "prior_sigma_m": None if prior_sigma is None else float(prior_sigma) / scale}
    out["miss"] = _share(int((with_depth & ~hits).sum()), n)
    out["stop_short"] = _share(int((offset < -half_m).sum()), n)
    out["pass_through"] = _share(int((offset > half_m).sum()), n)
    out["wrong_first_hit"] = (None if n == 0 else out["stop_short"] + out["pass_through"])
    out["first_hit_offset_m"] = (None if not offset.size else
                                 dict(zip(("p10", "p50", "p90"), np.percentile(offset, [10, 50, 90]).tolist(),
                                          strict=True)))
    noise = None
    if prior_t is not None:
        prior_t = np.asarray(prior_t, np.float64).ravel()
        noise = robust_spread(((prior_t - true_t) / scale)[with_depth & np.isfinite(prior_t)])
    out["prior_noise_m"] = noise
    out["window_over_noise"] = half_m / noise if noise else None
    return out


def samples_near(mid_t: np.ndarray, true_t: np.ndarray, band: float) -> float | None:
    """The share of samples (interval midpoints ``mid_t`` [R, S], normalised) within ``band`` of their ray's depth
    ``true_t`` [R] (rays without a depth, NaN, left out); None when no ray has one."""
    mid_t, true_t = np.asarray(mid_t, np.float64), np.asarray(true_t, np.float64)
    if mid_t.ndim != 2 or true_t.shape != mid_t.shape[:1]:
        raise ValueError(f"samples must be [R, S] and depths [R], got {mid_t.shape} and {true_t.shape}")
    rows = np.isfinite(true_t)
    if not rows.any():
        return None
    return float((np.abs(mid_t[rows] - true_t[rows, None]) <= band).mean())


def share_outside(mid_t: np.ndarray, hit_t: np.ndarray, hit: np.ndarray, half_window: float) -> float | None:
    """The share of the VoxNeRF sampler's samples (midpoints ``mid_t`` [R, S]) outside its window
    ``hit_t +- half_window`` [R]; every sample of a ray without a hit (``hit`` False: the grid places them) counts
    as outside. None for no rays."""
    mid_t, hit_t, hit = np.asarray(mid_t, np.float64), np.asarray(hit_t, np.float64), np.asarray(hit, bool)
    if mid_t.ndim != 2 or hit_t.shape != mid_t.shape[:1] or hit.shape != hit_t.shape:
        raise ValueError(f"samples must be [R, S] and first hits [R], got {mid_t.shape}, {hit_t.shape}, {hit.shape}")
    if not mid_t.size:
        return None
    inside = hit[:, None] & (np.abs(mid_t - hit_t[:, None]) <= half_window)
    return float(1.0 - inside.mean())


MAX_WRONG_FIRST_HITS = 0.06
"""Sampler ``auto`` keeps the VoxNeRF sampler while at most this share of the checked rays has a wrong first hit
(stops short or passes through); above it the prior-seeded occupancy grid samples instead. Chosen between the
tuning suite's scenes, 1.4-4.7 % (the window sampler leads or ties on each), and den with its prior moved by 15 cm,
7.3 % (the grid leads by 0.4 / 0.1 dB) and by 40 cm, 49 % (by 2.5 / 0.7 dB): docs/benchmarks.md, 'A prior in
the wrong place'."""


def choose_sampler(check: dict | None, has_octree: bool) -> tuple[str, str]:
    """Sampler ``auto``'s choice, ``(name, why)``: ``'occgrid'`` without an octree (no prior to place a window) or
    when more than :data:`MAX_WRONG_FIRST_HITS` of the rays of ``check`` (:func:`first_hit_check`'s result) have a
    wrong first hit, else ``'voxnerf'`` (also when nothing could be checked: no depth, ``check`` None)."""
    if not has_octree:
        return "occgrid", "no octree (no prior) to place a window: the occupancy grid samples"
    wrong = None if check is None else check.get("wrong_first_hit")
    if wrong is None:
        return "voxnerf", "no depth to check the window against: the VoxNeRF sampler, as the paper"
    if wrong > MAX_WRONG_FIRST_HITS:
        return "occgrid", (f"the first hit is wrong on {wrong:.1%} of the rays with depth (more than "
                           f"{MAX_WRONG_FIRST_HITS:.0%}): the window would miss their surface, so the occupancy grid "
                           "seeded from the prior samples")
    return "voxnerf", (f"the first hit is wrong on {wrong:.1%} of the rays with depth (at most "
                       f"{MAX_WRONG_FIRST_HITS:.0%}): the VoxNeRF sampler")


def _share(count: int, total: int) -> float | None:
    return None if total == 0 else count / total
