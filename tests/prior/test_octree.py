"""Sparse Voxel Octree: Morton codes, structure, and first-hit ray casting against a brute-force slab test."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
import torch

from voxnerf.prior import octree
from voxnerf.prior.octree import SparseVoxelOctree, coverage_octree, kernel_available, morton_decode, morton_encode

TINY = np.float32(1e-30)  # the octree's stand-in for zero direction components


def interleave_reference(ijk: np.ndarray) -> list[int]:
    """Morton codes bit by bit in Python integers."""
    codes = []
    for x, y, z in ijk.tolist():
        code = 0
        for b in range(21):
            code |= ((x >> b) & 1) << (3 * b) | ((y >> b) & 1) << (3 * b + 1) | ((z >> b) & 1) << (3 * b + 2)
        codes.append(code)
    return codes


def reference_leaves(points: np.ndarray, svo: SparseVoxelOctree) -> np.ndarray:
    """Occupied leaf coordinates [L, 3] straight from the points (float32 arithmetic, as documented)."""
    origin = svo.origin.numpy()
    ijk = np.floor((points.astype(np.float32) - origin) / np.float32(svo.leaf_size)).astype(np.int64)
    return np.unique(np.clip(ijk, 0, 2**svo.levels - 1), axis=0)


def brute_first_hit(
    svo: SparseVoxelOctree,
    leaves: np.ndarray,
    o: np.ndarray,
    d: np.ndarray,
    t_min: np.ndarray,
    t_max: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Slab test of every occupied leaf, smallest clipped entry with positive overlap, in float32."""
    v = np.float32(svo.leaf_size)
    origin = svo.origin.numpy()
    lo = origin + leaves.astype(np.float32) * v
    hi = origin + (leaves + 1).astype(np.float32) * v
    d = np.where(np.abs(d) < TINY, TINY, d).astype(np.float32)
    t_out = np.empty(len(o), np.float32)
    hit_out = np.empty(len(o), bool)
    for s in range(0, len(o), 128):
        oo, dd = o[s : s + 128, None, :], d[s : s + 128, None, :]
        ta, tb = (lo - oo) / dd, (hi - oo) / dd
        entry = np.maximum(np.minimum(ta, tb).max(-1), t_min[s : s + 128, None])
        exit_ = np.minimum(np.maximum(ta, tb).min(-1), t_max[s : s + 128, None])
        entry = np.where(entry < exit_, entry, np.inf).min(1)
        hit_out[s : s + 128] = np.isfinite(entry)
        t_out[s : s + 128] = np.where(np.isfinite(entry), entry, t_max[s : s + 128])
    return t_out, hit_out


def make_rays(svo: SparseVoxelOctree, leaves: np.ndarray, n: int, rng: np.random.Generator):
    """A mix of hard rays: random, aimed at leaves, axis-parallel, lying in voxel planes, starting inside
    occupied leaves, pointing away from the octree, with and without t_min/t_max clipping."""
    v = np.float32(svo.leaf_size)
    origin = svo.origin.numpy()
    size = np.float32(svo.root_size)
    centres = origin + (leaves[rng.integers(0, len(leaves), n)].astype(np.float32) + 0.5) * v
    o = (origin + rng.uniform(-0.2, 1.2, (n, 3)) * size).astype(np.float32)
    d = rng.normal(size=(n, 3)).astype(np.float32)
    k = n // 8
    d[k : 2 * k] = centres[k : 2 * k] - o[k : 2 * k]  # aimed at occupied leaves
    axis = rng.integers(0, 3, k)
    d[2 * k : 3 * k] = np.eye(3, dtype=np.float32)[axis] * rng.choice([-1, 1], (k, 1))  # axis-parallel
    o[2 * k : 3 * k] = centres[2 * k : 3 * k] - d[2 * k : 3 * k] * size * 0.3
    # Lying exactly in voxel planes (origin on a plane, zero direction component on that axis).
    o[3 * k : 4 * k] = origin + np.floor((centres[3 * k : 4 * k] - origin) / v) * v
    o[3 * k : 4 * k, 2] = centres[3 * k : 4 * k, 2] - 0.3 * size
    d[3 * k : 4 * k] = np.array([0, 0, 1], np.float32)
    d[3 * k : 3 * k + k // 2, 0] = rng.normal(size=k // 2)  # in the plane x = const only
    d[3 * k : 3 * k + k // 2, 2] = 1.0
    o[3 * k + k // 2 : 4 * k, 0] = centres[3 * k + k // 2 : 4 * k, 0]
    d[3 * k + k // 2 : 4 * k, 0] = 0.0
    o[4 * k : 5 * k] = centres[4 * k : 5 * k]  # inside occupied leaves
    o[5 * k : 6 * k] = origin - 0.1 * size  # outside, pointing away
    d[5 * k : 6 * k] = -np.abs(d[5 * k : 6 * k])
    d[6 * k :: 2] = centres[6 * k :: 2] - o[6 * k :: 2]  # half the clipped rays aimed at leaves
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t_min = np.zeros(n, np.float32)
    t_max = np.full(n, 10 * size, np.float32)
    t_min[6 * k :] = rng.uniform(0, 0.5, n - 6 * k) * size
    t_max[6 * k :] = t_min[6 * k :] + rng.uniform(0, 1.0, n - 6 * k) * size
    return o, d, t_min, t_max


def test_morton_known_values_and_round_trip():
    known = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1], [2, 0, 0], [3, 5, 7]])
    assert morton_encode(known).tolist() == [0, 1, 2, 4, 7, 8, 431]
    top = 2**21 - 1
    extreme = torch.tensor([[top, top, top], [top, 0, 0], [0, top, 0], [0, 0, top], [0, 0, 0]])
    assert morton_encode(extreme)[0].item() == 2**63 - 1
    rng = np.random.default_rng(0)
    ijk = np.concatenate([rng.integers(0, 2**21, (2000, 3)), extreme.numpy()])
    codes = morton_encode(torch.from_numpy(ijk))
    assert codes.dtype == torch.int64
    assert codes.tolist() == interleave_reference(ijk)
    assert torch.equal(morton_decode(codes), torch.from_numpy(ijk))


@pytest.mark.parametrize(("num_points", "leaf_size"), [(400, 0.05), (3000, 0.01), (6, 2.0**-16)])
def test_structure_matches_points(num_points, leaf_size):
    rng = np.random.default_rng(num_points)
    points = rng.uniform(-1.0, 2.0, (num_points, 3)).astype(np.float32)
    svo = SparseVoxelOctree.from_points(torch.from_numpy(points), leaf_size)
    assert svo.leaf_size == leaf_size and svo.root_size >= 3.0
    assert svo.codes[0].tolist() == [0] and len(svo.codes) == svo.levels + 1
    if leaf_size < 1e-4:
        assert svo.levels >= 15
    leaves = reference_leaves(points, svo)
    in_morton_order = leaves[np.argsort(interleave_reference(leaves))]
    assert np.array_equal(morton_decode(svo.codes[-1]).numpy(), in_morton_order)
    for level in range(1, svo.levels + 1):
        codes = svo.codes[level]
        assert torch.all(codes[1:] > codes[:-1])  # sorted, unique
        assert torch.isin(codes >> 3, svo.codes[level - 1]).all()  # every parent is present
        assert torch.equal(torch.unique(codes >> 3), svo.codes[level - 1])  # and no parent is childless
    summary = json.loads(json.dumps(svo.summary()))
    assert summary["nodes_per_level"][-1] == len(leaves)
    assert summary["memory_bytes"] == 8 * sum(summary["nodes_per_level"])


def test_leaf_occupied_matches_numpy():
    rng = np.random.default_rng(1)
    points = rng.normal(size=(2000, 3)).astype(np.float32)
    svo = SparseVoxelOctree.from_points(torch.from_numpy(points), 0.1)
    queries = np.concatenate([points, rng.uniform(-5, 5, (5000, 3)).astype(np.float32)])
    occupied = {tuple(x) for x in reference_leaves(points, svo).tolist()}
    ijk = np.floor((queries - svo.origin.numpy()) / np.float32(svo.leaf_size)).astype(np.int64)
    expected = np.array([tuple(x) in occupied for x in ijk.tolist()])
    result = svo.leaf_occupied(torch.from_numpy(queries)).numpy()
    assert result[: len(points)].all()
    assert np.array_equal(result, expected)
    assert 0 < result[len(points) :].sum() < len(queries) - len(points)


def test_state_dict_round_trip():
    points = torch.from_numpy(np.random.default_rng(2).uniform(0, 1, (500, 3)).astype(np.float32))
    svo = SparseVoxelOctree.from_points(points, 0.03)
    buffer = io.BytesIO()
    torch.save(svo.state_dict(), buffer)
    buffer.seek(0)
    restored = SparseVoxelOctree.from_state_dict(torch.load(buffer))
    assert restored.summary() == svo.summary()
    assert all(torch.equal(a, b) for a, b in zip(restored.codes, svo.codes, strict=True))
    o = torch.rand(300, 3) * 1.4 - 0.2
    d = torch.nn.functional.normalize(torch.randn(300, 3), dim=1)
    t_a, h_a = svo.first_hit(o, d, 0.0, 5.0)
    t_b, h_b = restored.to("cpu").first_hit(o, d, 0.0, 5.0)
    assert torch.equal(t_a, t_b) and torch.equal(h_a, h_b)
    assert torch.equal(restored.leaf_means, svo.leaf_means)
    assert torch.equal(restored.surface_hit(o, d, 0.0, 5.0)[0], svo.surface_hit(o, d, 0.0, 5.0)[0])


def test_an_octree_saved_without_leaf_means_puts_the_surface_at_the_leafs_entry():
    points = torch.from_numpy(np.random.default_rng(3).uniform(0, 1, (500, 3)).astype(np.float32))
    state = SparseVoxelOctree.from_points(points, 0.05).state_dict()
    del state["leaf_means"]  # as checkpoints written before the octree kept them
    old = SparseVoxelOctree.from_state_dict(state)
    assert old.leaf_means is None
    o = torch.rand(300, 3) * 1.4 - 0.2
    d = torch.nn.functional.normalize(torch.randn(300, 3), dim=1)
    t_entry, hit = old.first_hit(o, d, 0.0, 5.0)
    t, hit_s = old.surface_hit(o, d, 0.0, 5.0)
    assert torch.equal(t, t_entry) and torch.equal(hit, hit_s)


def test_leaf_means_must_match_the_leaves():
    svo = SparseVoxelOctree.from_points(torch.rand(200, 3), 0.1)
    with pytest.raises(ValueError, match="leaf_means must be"):
        SparseVoxelOctree(svo.codes, svo.origin, svo.leaf_size, svo.levels, svo.leaf_size_requested,
                          svo.leaf_means[:-1])


def test_kept_leaves_keep_their_means():
    points = torch.from_numpy(np.random.default_rng(4).uniform(0, 1, (3000, 3)).astype(np.float32))
    svo = SparseVoxelOctree.from_points(points, 0.1)
    keep = torch.arange(svo.codes[-1].numel()) % 3 != 0
    kept = svo.keep_leaves(keep)
    assert torch.equal(kept.codes[-1], svo.codes[-1][keep])
    assert torch.equal(kept.leaf_means, svo.leaf_means[keep])


def test_the_surface_hit_lies_on_a_noisy_wall_where_the_entry_lies_in_front_of_it():
    """Rays towards a wall z = 0 sampled with noise (std 0.01) in leaves of 0.03: the leaf's entry is a median
    of about half a leaf in front of the wall; where the ray passes the leaf's point mean is within the noise
    of the wall, and never before the entry or past a leaf diagonal."""
    rng = np.random.default_rng(6)
    wall = np.c_[rng.uniform(-1, 1, (200_000, 2)), rng.normal(0, 0.01, 200_000)].astype(np.float32)
    svo = SparseVoxelOctree.from_points(torch.from_numpy(wall), 0.03)
    n = 2000
    o = torch.tensor([[0.0, 0.0, 1.0]]).repeat(n, 1)
    gen = torch.Generator().manual_seed(0)
    d = torch.nn.functional.normalize(torch.cat([torch.rand(n, 2, generator=gen) - 0.5, -torch.ones(n, 1)], 1), dim=1)
    t_entry, hit = svo.first_hit(o, d, 0.0, 3.0)
    t, hit_s = svo.surface_hit(o, d, 0.0, 3.0)
    assert torch.equal(hit, hit_s) and hit.float().mean() > 0.99
    assert (t >= t_entry).all() and (t <= t_entry + 3**0.5 * svo.leaf_size + 1e-6).all()
    z_entry, z_surface = (o + t_entry[:, None] * d)[hit, 2], (o + t[:, None] * d)[hit, 2]
    assert float(z_entry.median()) > 0.02, "the first leaf's entry lies in front of the wall"
    assert abs(float(z_surface.median())) < 0.005 and float(z_surface.abs().quantile(0.9)) < 0.02


# Both tracing paths: the PyTorch frontier (any device) and the C kernel (CPU, where it could be built).
_NO_KERNEL = pytest.mark.skipif(not kernel_available(), reason="the tracing kernel could not be built")
TRACE_PATHS = pytest.mark.parametrize("use_kernel", [False, pytest.param(True, marks=_NO_KERNEL)],
                                      ids=["torch", "kernel"])


@TRACE_PATHS
@pytest.mark.parametrize(
    ("num_points", "leaf_size", "seed"), [(300, 0.05, 0), (2000, 0.01, 1), (40, 2.0**-16, 2), (1, 0.5, 3)]
)
def test_first_hit_matches_brute_force(num_points, leaf_size, seed, use_kernel):
    rng = np.random.default_rng(seed)
    points = rng.uniform(0.0, 1.0, (num_points, 3)).astype(np.float32)
    svo = SparseVoxelOctree.from_points(torch.from_numpy(points), leaf_size)
    leaves = reference_leaves(points, svo)
    o, d, t_min, t_max = make_rays(svo, leaves, 4000, rng)
    t, hit = svo.first_hit(*(torch.from_numpy(x) for x in (o, d, t_min, t_max)), use_kernel=use_kernel)
    t_ref, hit_ref = brute_first_hit(svo, leaves, o, d, t_min, t_max)
    assert not torch.isnan(t).any()
    assert np.array_equal(hit.numpy(), hit_ref)
    assert np.array_equal(t.numpy(), t_ref)  # bit for bit: same planes, same slab arithmetic
    k = len(o) // 8
    assert hit[k : 2 * k].all() and hit[4 * k : 5 * k].all()  # aimed at / starting inside occupied leaves
    assert (t[4 * k : 5 * k] == 0).all()  # inside an occupied leaf: t_hit = t_min
    assert not hit[5 * k : 6 * k].any()  # pointing away
    assert torch.equal(t[5 * k : 6 * k], torch.from_numpy(t_max[5 * k : 6 * k]))
    if num_points > 1:
        assert 0 < hit[6 * k :].sum() < len(o) - 6 * k  # clipping hides some hits


@TRACE_PATHS
@pytest.mark.parametrize(("num_points", "leaf_size", "seed"), [(2000, 0.01, 5), (300, 0.05, 6)])
def test_first_hit_with_a_hint_is_bit_identical_whatever_the_hint(num_points, leaf_size, seed, use_kernel):
    """Hints at, before and behind the true hit, NaN, before t_min and past t_max all give the plain result."""
    rng = np.random.default_rng(seed)
    points = rng.uniform(0.0, 1.0, (num_points, 3)).astype(np.float32)
    svo = SparseVoxelOctree.from_points(torch.from_numpy(points), leaf_size)
    o, d, t_min, t_max = (torch.from_numpy(x) for x in make_rays(svo, reference_leaves(points, svo), 4000, rng))
    t, hit = svo.first_hit(o, d, t_min, t_max, use_kernel=use_kernel)
    assert 0.2 < hit.float().mean() < 0.95
    n = len(o)
    jitter = torch.from_numpy(rng.normal(0.0, 5 * leaf_size, n).astype(np.float32))
    hints = {
        "exact": torch.where(hit, t, torch.nan),
        "noisy": torch.where(hit, t, t_max) + jitter,
        "too_early": t - 10 * leaf_size,
        "too_late": t + 0.5,
        "nan": torch.full((n,), torch.nan),
        "before_t_min": t_min - 1.0,
        "past_t_max": t_max + 1.0,
        "mixed": torch.from_numpy(rng.choice([np.nan, 0.0, 0.3, 1.0, 1e30], n).astype(np.float32)),
    }
    for name, hint in hints.items():
        t_h, hit_h = svo.first_hit(o, d, t_min, t_max, t_hint=hint, use_kernel=use_kernel)
        assert torch.equal(hit_h, hit), name
        assert torch.equal(t_h, t), name
    with pytest.raises(ValueError, match=r"t_hint must be \[N\]"):
        svo.first_hit(o, d, t_min, t_max, t_hint=t[:10])


@TRACE_PATHS
def test_first_hit_ray_in_plane_takes_plus_side(use_kernel):
    # Two leaves sharing the plane x = 1: ray lies in that plane, so only the +x leaf counts.
    svo = SparseVoxelOctree.from_points(torch.tensor([[0.5, 0.5, 0.5], [1.5, 0.5, 2.5]]), 1.0)
    assert svo.origin.tolist() == [0.0, 0.0, 0.0]
    o = torch.tensor([[1.0, 0.5, -1.0], [0.999, 0.5, -1.0], [1.0, 1.0, -1.0]])
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    t, hit = svo.first_hit(o, d, 0.0, 10.0, use_kernel=use_kernel)
    assert hit.tolist() == [True, True, False]
    assert t.tolist() == [3.0, 1.0, 10.0]


@TRACE_PATHS
def test_first_hit_is_chunk_and_thread_independent(use_kernel):
    rng = np.random.default_rng(4)
    points = torch.from_numpy(rng.normal(size=(3000, 3)).astype(np.float32))
    svo = SparseVoxelOctree.from_points(points, 0.05)
    o = torch.zeros(40000, 3)
    d = torch.nn.functional.normalize(torch.randn(40000, 3), dim=1)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        t_one, h_one = svo.first_hit(o, d, 0.0, 100.0, use_kernel=use_kernel)
        torch.set_num_threads(2)
        t_two, h_two = svo.first_hit(o, d, 0.0, 100.0, use_kernel=use_kernel)
        t_small, h_small = svo.first_hit(o, d, 0.0, 100.0, chunk=4096, use_kernel=use_kernel)
    finally:
        torch.set_num_threads(threads)
    assert 0.3 < h_one.float().mean() < 1.0
    assert torch.equal(t_one, t_two) and torch.equal(h_one, h_two)
    assert torch.equal(t_one, t_small) and torch.equal(h_one, h_small)


@TRACE_PATHS
def test_first_hit_never_nan_on_degenerate_input(use_kernel):
    svo = SparseVoxelOctree.from_points(torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]), 0.25)
    o = torch.tensor([[-1e6, 0.1, 0.1], [0.1, 0.1, -5.0], [0.1, 0.1, -5.0], [2.0, 2.0, 2.0], [0.1, 0.1, 0.1]])
    tiny = 1e-40  # subnormal
    d = torch.tensor([[1.0, 0, 0], [tiny, -0.0, 1.0], [0, 0, 1.0], [-1.0, -1.0, -1.0], [1.0, 0, 0]])
    o = torch.cat([o, torch.tensor([[-1e30, 0.1, 0.1]])])
    d = torch.cat([d, torch.tensor([[1.0, 0.0, 0.0]])])
    t_min = torch.tensor([0.0, 0.0, 0.0, 0.0, 0.05, 0.0])
    t, hit = svo.first_hit(o, d, t_min, 1e38, use_kernel=use_kernel)
    assert not torch.isnan(t).any()
    # At 1e30 the voxels are thinner than float32 resolution: a miss, but no NaN.
    assert hit.tolist() == [True, True, True, True, False, False]
    assert t[0].item() == pytest.approx(1e6 - 0.125) and t[1].item() == t[2].item() == pytest.approx(4.875)


@TRACE_PATHS
def test_first_hit_misses_rays_with_nan_or_inf_and_says_so(use_kernel):
    svo = SparseVoxelOctree.from_points(torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]), 0.25)
    nan, inf = float("nan"), float("inf")
    o = torch.tensor([[nan, 0.1, 0.1], [0.1, 0.1, -5.0], [inf, 0.1, 0.1], [0.1, 0.1, -5.0]])
    d = torch.tensor([[1.0, 0.0, 0.0], [nan, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    t, hit = svo.first_hit(o, d, 0.0, 50.0, use_kernel=use_kernel)
    assert hit.tolist() == [False, False, False, True]
    assert t[:3].tolist() == [50.0] * 3


def test_without_a_compiler_tracing_falls_back_to_torch(tmp_path, monkeypatch):
    rng = np.random.default_rng(7)
    svo = SparseVoxelOctree.from_points(torch.from_numpy(rng.uniform(0, 1, (500, 3)).astype(np.float32)), 0.05)
    o = torch.full((2000, 3), 0.5) + torch.randn(2000, 3)
    d = torch.nn.functional.normalize(torch.randn(2000, 3), dim=1)
    expected = svo.first_hit(o, d, 0.0, 10.0, use_kernel=False)
    monkeypatch.setenv("VOXNERF_CACHE", str(tmp_path))  # an empty cache: it would have to be built
    monkeypatch.setenv("PATH", str(tmp_path))
    monkeypatch.delenv("CC", raising=False)
    octree._trace_library.cache_clear()
    try:
        assert not kernel_available()
        t, hit = svo.first_hit(o, d, 0.0, 10.0)  # the default: the kernel where it can be had
        assert torch.equal(t, expected[0]) and torch.equal(hit, expected[1])
        with pytest.raises(RuntimeError, match="no C compiler"):
            svo.first_hit(o, d, 0.0, 10.0, use_kernel=True)
    finally:
        octree._trace_library.cache_clear()


def test_depth_clamp_grows_the_leaf():
    points = torch.tensor([[0.0, 0.0, 0.0], [100.0, 3.0, 7.0]])
    svo = SparseVoxelOctree.from_points(points, 0.01, max_levels=6)
    assert svo.levels == 6 and svo.leaf_size > 0.01 and svo.leaf_size_requested == 0.01
    assert svo.summary()["depth_clamped"] is True
    assert svo.root_size >= 100.0 + svo.leaf_size
    assert svo.leaf_occupied(points).all()


@pytest.mark.parametrize(
    ("points", "leaf_size"),
    [(torch.zeros(0, 3), 0.1), (torch.tensor([[0.0, float("nan"), 0.0]]), 0.1), (torch.zeros(3, 3), 0.0)],
)
def test_from_points_rejects_bad_input(points, leaf_size):
    with pytest.raises(ValueError):
        SparseVoxelOctree.from_points(points, leaf_size)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_first_hit_on_cuda_matches_cpu():
    rng = np.random.default_rng(5)
    points = torch.from_numpy(rng.normal(size=(5000, 3)).astype(np.float32))
    svo = SparseVoxelOctree.from_points(points, 0.02)
    o = torch.from_numpy(rng.uniform(-1, 1, (100_000, 3)).astype(np.float32))
    d = torch.nn.functional.normalize(torch.randn(100_000, 3), dim=1)
    t_cpu, h_cpu = svo.first_hit(o, d, 0.0, 10.0)
    t_gpu, h_gpu = svo.to("cuda").first_hit(o.cuda(), d.cuda(), 0.0, 10.0)
    assert t_gpu.is_cuda and h_gpu.is_cuda
    assert torch.equal(t_gpu.cpu(), t_cpu) and torch.equal(h_gpu.cpu(), h_cpu)
    assert torch.equal(svo.to("cuda").leaf_occupied(points.cuda()).cpu(), svo.leaf_occupied(points))


def test_leaf_means_are_the_mean_of_each_leafs_points():
    rng = np.random.default_rng(5)
    pts = torch.from_numpy(rng.uniform(0, 1, (5000, 3))).float()
    svo = SparseVoxelOctree.from_points(pts, 0.1)
    means = svo.means_of(pts)
    ijk = svo.leaf_ijk(pts).numpy()
    for key in {tuple(k) for k in ijk[:50]}:
        members = (ijk == key).all(axis=1)
        (pos,), found = svo.leaf_index(pts[members][:1])
        assert found.item()
        np.testing.assert_allclose(means[pos].numpy(), pts[members].numpy().mean(0), atol=1e-6)
    values, found = svo.lookup_leaf(means, pts)
    assert found.all()
    # every mean lies inside the leaf that holds its points
    assert (svo.leaf_ijk(values) == svo.leaf_ijk(pts)).all()


def _plane_rays(n: int, seed: int):
    gen = torch.Generator().manual_seed(seed)
    origins = torch.cat([torch.rand(n, 2, generator=gen) * 1.6 - 0.8, torch.ones(n, 1)], 1)
    tilt = (torch.rand(n, 2, generator=gen) - 0.5) * 0.2  # every ray meets the plane inside its 2 x 2 extent
    dirs = torch.nn.functional.normalize(torch.cat([tilt, -torch.ones(n, 1)], 1))
    return origins, dirs, torch.zeros(n), torch.full((n,), 3.0)


@pytest.mark.parametrize("points_per_sigma2", [0.5, 20.0])
def test_coverage_octree_grows_the_leaf_only_for_sparse_priors(points_per_sigma2):
    sigma = 0.02
    n = int(points_per_sigma2 * 4 / sigma**2)  # a 2 x 2 plane with noise sigma
    rng = np.random.default_rng(6)
    plane = np.c_[rng.uniform(-1, 1, (n, 2)), rng.normal(0, sigma, n)]
    svo, misses = coverage_octree(torch.from_numpy(plane).float(), sigma, *_plane_rays(4000, 7))
    assert svo.leaf_means is not None and svo.leaf_means.shape == (svo.codes[-1].numel(), 3)  # the kept tree
    assert set(misses) == {"1", "1.5", "2", "3"}
    chosen = svo.leaf_size_requested / sigma
    assert misses[f"{chosen:g}"] <= min(misses.values()) + 0.01
    if points_per_sigma2 < 1:  # rays slip through sigma leaves: a larger leaf is chosen
        assert misses["1"] > 0.05 and chosen > 1
    else:  # dense: the paper's leaf
        assert misses["1"] < 0.01 and chosen == 1
