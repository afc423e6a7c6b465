"""Property-based tests (hypothesis) of the numerical core on stiff and extreme input (issue 6, item 1).

Every property is checked against an independent reference: float64 closed forms for volume rendering and
the log-Huber loss, and a brute-force slab test of every occupied leaf for octree ray casting.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from voxnerf.model.losses import depth_loss, log_huber
from voxnerf.model.volume_rendering import MAX_OPTICAL_DEPTH, render_weights, volume_render
from voxnerf.prior.octree import MAX_LEVELS, SparseVoxelOctree, morton_decode

PROPERTY = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
TINY_DIR = np.float32(1e-30)  # the octree's documented stand-in for a zero direction component


# ------------------------------------------------------------------------------------------ volume rendering


@st.composite
def stiff_rays(draw) -> dict:
    """Rays with 1..4096 sorted intervals, steps from 1e-9 to 1e6, densities from 0 to 1e10 plus inf.

    Interval lengths are ``step * U(0, 2)`` (some exactly zero), rays start anywhere in [0, 1e3] and a few
    intervals leave gaps. Densities are log-uniform over a drawn range, with some zeros and infinities.
    """
    n_rays = draw(st.integers(1, 4))
    n_samples = draw(st.sampled_from([1, 2, 3, 17, 128, 1000, 4096]))
    step = 10.0 ** draw(st.floats(-9.0, 6.0))
    log_lo = draw(st.floats(-12.0, 10.0))
    log_hi = draw(st.floats(log_lo, 10.0))
    special = draw(st.floats(0.0, 0.3))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    deltas = step * rng.uniform(0.0, 2.0, (n_rays, n_samples))
    deltas[rng.random(deltas.shape) < 0.05] = 0.0
    gaps = np.where(rng.random(deltas.shape) < 0.1, step * rng.random(deltas.shape), 0.0)
    start = rng.uniform(0.0, 1e3, (n_rays, 1)) * (rng.random((n_rays, 1)) < 0.5)
    t_starts = start + np.cumsum(gaps + deltas, axis=1) - deltas
    t_ends = t_starts + deltas
    densities = 10.0 ** rng.uniform(log_lo, log_hi, (n_rays, n_samples))
    pick = rng.random(densities.shape)
    densities[pick < special / 2] = 0.0
    densities[(pick >= special / 2) & (pick < special)] = np.inf
    return {
        "densities": torch.tensor(densities, dtype=torch.float32),
        "t_starts": torch.tensor(t_starts, dtype=torch.float32),
        "t_ends": torch.tensor(np.maximum(t_ends, t_starts), dtype=torch.float32),
        "rgbs": torch.tensor(rng.random((n_rays, n_samples, 3)), dtype=torch.float32),
        "background": torch.tensor(rng.random(3), dtype=torch.float32),
    }


def reference_weights(densities: torch.Tensor, t_starts: torch.Tensor, t_ends: torch.Tensor) -> np.ndarray:
    """Closed form in float64: ``w_i = exp(-sum_{j<i} tau_j) (1 - exp(-tau_i))``, ``tau = sigma * delta``.

    An infinitely dense interval of zero length has no optical depth (the documented convention).
    """
    sigma = densities.double().numpy()
    delta = np.maximum(t_ends.double().numpy() - t_starts.double().numpy(), 0.0)
    with np.errstate(invalid="ignore", over="ignore"):
        tau = np.where(delta > 0, np.minimum(sigma * delta, MAX_OPTICAL_DEPTH), 0.0)
    before = np.cumsum(tau, axis=1) - tau
    return np.exp(-before) * -np.expm1(-tau)


@PROPERTY
@given(stiff_rays())
def test_volume_render_identities_and_finite_gradients(rays):
    densities = rays["densities"].clone().requires_grad_(True)
    rgbs = rays["rgbs"].clone().requires_grad_(True)
    t_starts, t_ends = rays["t_starts"], rays["t_ends"]
    out = volume_render(densities, rgbs, t_starts, t_ends, rays["background"])
    for key in ("rgb", "opacity", "depth", "weights"):
        assert torch.isfinite(out[key]).all(), key

    weights = out["weights"].detach().double()
    assert ((weights >= 0) & (weights <= 1)).all()
    total = weights.sum(-1)
    assert (total <= 1 + 1e-6).all()
    torch.testing.assert_close(out["opacity"].double(), total.clamp(max=1), atol=1e-6, rtol=0)
    # Sample by sample against the float64 closed form: float32 accuracy even after an opaque interval.
    ref = reference_weights(densities.detach(), t_starts, t_ends)
    np.testing.assert_allclose(weights.numpy(), ref, atol=1e-6, rtol=0)

    near, far = t_starts[:, 0], t_ends[:, -1]
    assert ((out["depth"] >= near) & (out["depth"] <= far)).all()
    mids = 0.5 * (t_starts.double().numpy() + t_ends.double().numpy())
    opacity = ref.sum(-1)
    depth_ref = (ref * mids).sum(-1) + (1 - opacity) * far.double().numpy()
    span = (far - near).double().numpy()
    # float32 rounding of the interval bounds (about 1e-7 of |far|) plus the weights' error over the span.
    error = np.abs(out["depth"].detach().double().numpy() - depth_ref)
    assert (error <= 1e-4 * span + 1e-6 * np.abs(far.double().numpy())).all()
    rgb_ref = (ref[..., None] * rays["rgbs"].double().numpy()).sum(1) + (1 - opacity)[:, None] * rays[
        "background"
    ].double().numpy()
    np.testing.assert_allclose(out["rgb"].detach().double().numpy(), rgb_ref, atol=1e-5, rtol=0)
    assert ((out["rgb"] >= 0) & (out["rgb"] <= 1 + 1e-5)).all()

    (out["rgb"].sum() + out["depth"].sum() / far.abs().clamp_min(1).sum() + out["opacity"].sum()).backward()
    assert torch.isfinite(densities.grad).all() and torch.isfinite(rgbs.grad).all()


@PROPERTY
@given(stiff_rays())
def test_render_weights_transmittance_is_monotone_and_consistent(rays):
    weights, transmittance = render_weights(rays["densities"], rays["t_starts"], rays["t_ends"])
    assert torch.isfinite(weights).all() and torch.isfinite(transmittance).all()
    assert ((transmittance >= 0) & (transmittance <= 1)).all()
    assert (transmittance[:, 1:] <= transmittance[:, :-1]).all()  # light only gets absorbed
    assert torch.all(weights <= transmittance)  # w_i = T_i * alpha_i with alpha_i in [0, 1]
    # What reaches the next interval is what reached this one minus what this one absorbed.
    torch.testing.assert_close(transmittance[:, 1:], (transmittance - weights)[:, :-1], atol=1e-5, rtol=1e-4)


# ------------------------------------------------------------------------------------------------- losses


@PROPERTY
@given(
    beta=st.floats(1e-6, 1e3),
    magnitudes=st.lists(st.floats(-12.0, 6.0), min_size=1, max_size=64),
    signs=st.lists(st.booleans(), min_size=64, max_size=64),
)
def test_log_huber_matches_closed_form_with_finite_gradient(beta, magnitudes, signs):
    r = np.array([(10.0**m) * (1 if s else -1) for m, s in zip(magnitudes, signs, strict=False)])
    residual = torch.tensor(r, dtype=torch.float32, requires_grad=True)
    value = log_huber(residual, beta)
    (grad,) = torch.autograd.grad(value.sum(), residual)
    assert torch.isfinite(value).all() and torch.isfinite(grad).all()
    a = np.abs(residual.detach().double().numpy())
    expected = np.where(a < beta, 0.5 * a * a, beta * beta * (0.5 + np.log(np.maximum(a, beta) / beta)))
    np.testing.assert_allclose(value.detach().double().numpy(), expected, rtol=2e-5, atol=1e-30)
    slope = np.where(a < beta, a, beta * beta / np.maximum(a, beta)) * np.sign(residual.detach().numpy())
    np.testing.assert_allclose(grad.double().numpy(), slope, rtol=2e-5, atol=1e-30)
    assert (value >= 0).all()


@PROPERTY
@given(beta=st.floats(1e-6, 1e3))
def test_log_huber_value_and_slope_are_continuous_at_beta(beta):
    x = torch.tensor([beta * (1 - 1e-9), beta, beta * (1 + 1e-9)], dtype=torch.float64, requires_grad=True)
    value = log_huber(x, beta)
    (grad,) = torch.autograd.grad(value.sum(), x)
    np.testing.assert_allclose(value.detach().numpy(), 0.5 * beta * beta, rtol=1e-8)
    np.testing.assert_allclose(grad.numpy(), beta, rtol=1e-8)


@PROPERTY
@given(
    beta=st.floats(1e-6, 1e3),
    log_residual=st.floats(-12.0, 6.0),
    n=st.integers(1, 300),
    valid_fraction=st.floats(0.0, 1.0),
    seed=st.integers(0, 2**32 - 1),
)
def test_depth_loss_is_finite_and_ignores_invalid_rays(beta, log_residual, n, valid_fraction, seed):
    rng = np.random.default_rng(seed)
    target = torch.tensor(rng.uniform(0.0, 10.0, n), dtype=torch.float32)
    valid = torch.tensor(rng.random(n) < valid_fraction)
    target = torch.where(valid, target, torch.tensor(float("nan")))
    offset = torch.tensor(rng.choice([-1.0, 1.0], n) * 10.0**log_residual, dtype=torch.float32)
    pred = (torch.nan_to_num(target, nan=3.0) + offset).requires_grad_(True)
    loss = depth_loss(pred, target, valid, beta)
    (grad,) = torch.autograd.grad(loss, pred)
    loss = loss.detach()
    assert math.isfinite(float(loss)) and float(loss) >= 0
    assert torch.isfinite(grad).all()
    assert (grad[~valid] == 0).all()
    if not valid.any():
        assert float(loss) == 0.0
    else:
        residual = (pred.detach() - torch.nan_to_num(target))[valid].double()
        expected = log_huber(residual, beta).mean()
        assert float(loss) == pytest.approx(float(expected), rel=1e-4, abs=1e-30)


# ------------------------------------------------------------------------------------------- octree rays


def slab_reference(
    svo: SparseVoxelOctree, o: np.ndarray, d: np.ndarray, t_min: np.ndarray, t_max: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """First hit by testing every occupied leaf, in float32 as the octree documents: planes at
    ``origin + integer * leaf_size``, zero direction components replaced by +1e-30, positive overlap only."""
    leaves = morton_decode(svo.codes[-1]).numpy()
    v = np.float32(svo.leaf_size)
    origin = svo.origin.numpy()
    lo = origin + leaves.astype(np.float32) * v
    hi = origin + (leaves + 1).astype(np.float32) * v
    d = np.where(np.abs(d) < TINY_DIR, TINY_DIR, d).astype(np.float32)
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        ta, tb = (lo - o[:, None]) / d[:, None], (hi - o[:, None]) / d[:, None]
        entry = np.maximum(np.minimum(ta, tb).max(-1), t_min[:, None])
        exit_ = np.minimum(np.maximum(ta, tb).min(-1), t_max[:, None])
    first = np.where(entry < exit_, entry, np.inf).min(1)
    hit = np.isfinite(first)
    return np.where(hit, first, t_max).astype(np.float32), hit


@st.composite
def octree_and_rays(draw) -> tuple[SparseVoxelOctree, dict[str, np.ndarray]]:
    """A few points voxelised at a drawn depth (often the deepest, 21 levels), and hard rays for them:
    axis-parallel through leaf centres, grazing (lying in a leaf's face plane or along its edge), starting
    inside occupied leaves, and random ones; a quarter of them with a clipped [t_min, t_max].

    Far from the origin at 21 levels the leaves are thinner than float32 resolution: those cases check that
    the traversal still agrees with the reference and never gives NaN."""
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    deepest = draw(st.booleans())
    n_points = draw(st.integers(2 if deepest else 1, 12))  # one point spans nothing: a single level
    extent = 10.0 ** draw(st.floats(-3.0, 3.0))
    shift = draw(st.sampled_from([0.0, -1.0, 100.0]))
    points = (shift * extent + rng.uniform(0.0, extent, (n_points, 3))).astype(np.float32)
    if deepest:  # the clamp needs points spread over most of the extent (two close points need fewer levels)
        points[:2, 0] = np.float32([shift * extent + 0.05 * extent, shift * extent + 0.95 * extent])
    # 2**-23 of the extent forces the depth clamp (21 levels, leaf grown); otherwise 3..12 levels.
    leaf = extent * (2.0**-23 if deepest else 2.0 ** -draw(st.integers(2, 11)))
    svo = SparseVoxelOctree.from_points(torch.from_numpy(points), leaf)
    leaves = morton_decode(svo.codes[-1]).numpy()
    v, origin, size = np.float32(svo.leaf_size), svo.origin.numpy(), np.float32(svo.root_size)
    k = 24
    idx = np.arange(k)
    pick = leaves[rng.integers(0, len(leaves), 4 * k)]
    lo = origin + pick.astype(np.float32) * v
    hi = origin + (pick + 1).astype(np.float32) * v
    centre = origin + (pick.astype(np.float32) + np.float32(0.5)) * v

    d_axis = np.eye(3, dtype=np.float32)[rng.integers(0, 3, k)] * rng.choice(np.float32([-1, 1]), (k, 1))
    o_axis = centre[:k] - d_axis * size

    # Grazing: the origin on a face plane of the leaf (its low side, which the + side rule gives to this leaf,
    # or its high side, shared with the neighbour) and the direction inside that plane; half of them also on
    # the low edge shared with a second face (two zero direction components).
    face = rng.integers(0, 3, k)
    other = (face + 1) % 3
    high = rng.random(k) < 0.5
    edge = rng.random(k) < 0.5
    o_graze = centre[k : 2 * k].copy()
    o_graze[idx, face] = np.where(high, hi[k : 2 * k][idx, face], lo[k : 2 * k][idx, face])
    o_graze[edge, other[edge]] = lo[k : 2 * k][edge, other[edge]]
    d_graze = rng.normal(size=(k, 3)).astype(np.float32)
    d_graze[idx, face] = 0.0
    d_graze[edge, other[edge]] = 0.0
    d_graze /= np.linalg.norm(d_graze, axis=1, keepdims=True)
    o_graze = o_graze - d_graze * size  # back off along the ray: zero components keep it in the plane(s)

    o_inside = centre[2 * k : 3 * k]
    d_inside = rng.normal(size=(k, 3)).astype(np.float32)

    o_rand = (origin + rng.uniform(-0.5, 1.5, (k, 3)) * size).astype(np.float32)
    d_rand = centre[3 * k :] - o_rand
    d_rand[::2] = rng.normal(size=(k // 2, 3))

    o = np.concatenate([o_axis, o_graze, o_inside, o_rand]).astype(np.float32)
    d = np.concatenate([d_axis, d_graze, d_inside, d_rand]).astype(np.float32)
    norm = np.linalg.norm(d.astype(np.float64), axis=1, keepdims=True)
    d = (d / np.where(norm > 0, norm, 1.0)).astype(np.float32)
    t_min = np.zeros(len(o), np.float32)
    t_max = np.full(len(o), 4 * size, np.float32)
    clipped = rng.random(len(o)) < 0.25
    clipped[2 * k : 3 * k] = False
    t_min[clipped] = rng.uniform(0, 1, clipped.sum()) * size
    t_max[clipped] = t_min[clipped] + rng.uniform(0, 2, clipped.sum()) * size
    # Rays that must hit: unclipped, through a leaf resolvable in float32 (centre strictly inside it), on
    # the axis, on the leaf's low face or edge (the + side rule), or starting inside it (at t = 0).
    resolvable = ((lo < centre) & (centre < hi)).all(1)
    must_hit = np.concatenate([resolvable[:k], resolvable[k : 2 * k] & ~high, resolvable[2 * k : 3 * k],
                               np.zeros(k, bool)]) & ~clipped
    rays = {"o": o, "d": d, "t_min": t_min, "t_max": t_max, "must_hit": must_hit,
            "starts_inside": np.arange(len(o)) // k == 2, "deepest": np.bool_(deepest)}
    return svo, rays


@PROPERTY
@given(octree_and_rays())
def test_first_hit_matches_slab_reference_on_hard_rays(case):
    svo, rays = case
    o, d, t_min, t_max = rays["o"], rays["d"], rays["t_min"], rays["t_max"]
    if rays["deepest"]:
        assert svo.levels == MAX_LEVELS and svo.leaf_size >= svo.leaf_size_requested
    t, hit = svo.first_hit(*(torch.from_numpy(x) for x in (o, d, t_min, t_max)))
    assert not torch.isnan(t).any()
    t_ref, hit_ref = slab_reference(svo, o, d, t_min, t_max)
    np.testing.assert_array_equal(hit.numpy(), hit_ref)
    np.testing.assert_array_equal(t.numpy(), t_ref)  # same planes, same float32 slab arithmetic
    assert (t >= torch.from_numpy(t_min)).all() and (t <= torch.from_numpy(t_max)).all()
    must_hit = torch.from_numpy(rays["must_hit"])
    assert hit[must_hit].all()
    assert (t[must_hit & torch.from_numpy(rays["starts_inside"])] == 0).all()


@PROPERTY
@given(
    seed=st.integers(0, 2**32 - 1),
    log_origin=st.floats(-40.0, 38.0),
    zero_axes=st.lists(st.integers(0, 2), max_size=2),
)
def test_first_hit_never_nan_for_extreme_rays(seed, log_origin, zero_axes):
    rng = np.random.default_rng(seed)
    svo = SparseVoxelOctree.from_points(torch.from_numpy(rng.uniform(0, 1, (5, 3)).astype(np.float32)), 1e-7)
    o = (rng.choice([-1, 1], (64, 3)) * 10.0**log_origin).astype(np.float32)
    d = rng.normal(size=(64, 3)).astype(np.float32)
    d[:, zero_axes] = 0.0
    d[32:] *= np.float32(1e-38)  # subnormal directions
    t, hit = svo.first_hit(torch.from_numpy(o), torch.from_numpy(d), 0.0, 3e38)
    assert not torch.isnan(t).any() and (t >= 0).all()
    t_ref, hit_ref = slab_reference(svo, o, d, np.zeros(64, np.float32), np.full(64, 3e38, np.float32))
    np.testing.assert_array_equal(hit.numpy(), hit_ref)


@settings(max_examples=60, deadline=None)
@given(
    betas=st.lists(st.floats(1e-6, 1e3), min_size=1, max_size=40),
    log_residual=st.floats(-12, 6),
    seed=st.integers(0, 2**16),
)
def test_log_huber_with_a_beta_per_ray_is_each_ray_s_scalar_loss(betas, log_residual, seed):
    """Sensor depth gives every ray its own beta: the tensor form equals the scalar form ray by ray, finite, with
    finite gradients."""
    g = torch.Generator().manual_seed(seed)
    n = len(betas)
    residual = (torch.rand(n, generator=g, dtype=torch.float64) - 0.5) * 2 * 10.0 ** log_residual
    residual.requires_grad_(True)
    beta = torch.tensor(betas, dtype=torch.float64)
    values = log_huber(residual, beta)
    values.sum().backward()
    assert torch.isfinite(values).all() and torch.isfinite(residual.grad).all()
    for i in range(n):
        scalar = log_huber(residual[i : i + 1].detach(), float(beta[i]))
        assert float(values[i].detach()) == pytest.approx(float(scalar[0]), rel=1e-12, abs=1e-300)
