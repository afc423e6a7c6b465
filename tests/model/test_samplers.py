"""Samplers: counts, ordering, bounds, the VoxNeRF window and its fallback, occupancy-grid skipping."""

import math

import pytest
import torch

from voxnerf.model.samplers import (
    GRID_UPDATE_BATCH,
    OCTREE_MISSES,
    WINDOW_CENTRES,
    OccGridSampler,
    OccupancyGrid,
    RayBundle,
    UniformSampler,
    VoxNeRFSampler,
    intervals_around_window,
    octree_misses_on,
    window_centres,
)
from voxnerf.prior.octree import SparseVoxelOctree


def _rays(n: int, origin=(0.0, 0.0, 0.0), direction=(1.0, 0.0, 0.0), near=0.01, far=1.7) -> RayBundle:
    o = torch.tensor(origin).expand(n, 3).clone()
    d = torch.nn.functional.normalize(torch.tensor(direction), dim=0).expand(n, 3).clone()
    return RayBundle(o, d, torch.full((n,), near), torch.full((n,), far))


def _check_intervals(starts, ends, rays, s):
    assert starts.shape == ends.shape == (len(rays), s)
    assert torch.all(ends >= starts)
    assert torch.all(starts[:, 1:] >= ends[:, :-1] - 1e-6)
    assert torch.all(starts >= rays.near[:, None] - 1e-6) and torch.all(ends <= rays.far[:, None] + 1e-6)


def test_uniform_sampler_covers_range():
    rays = _rays(16)
    starts, ends = UniformSampler(32)(rays, stratified=True)
    _check_intervals(starts, ends, rays, 32)
    torch.testing.assert_close(starts[:, 0], rays.near)
    torch.testing.assert_close(ends[:, -1], rays.far)


def _wall_octree(x: float = 0.8, leaf: float = 0.02) -> SparseVoxelOctree:
    g = torch.linspace(-0.9, 0.9, 91)
    yy, zz = torch.meshgrid(g, g, indexing="ij")
    pts = torch.stack([torch.full_like(yy, x), yy, zz], -1).reshape(-1, 3)
    return SparseVoxelOctree.from_points(pts, leaf)


def test_voxnerf_sampler_packs_importance_samples_in_window():
    octree = _wall_octree()
    grid = OccupancyGrid(16)
    sampler = VoxNeRFSampler(octree, 16, 8, OccGridSampler(grid, 24))
    rays = _rays(256, direction=(1.0, 0.05, -0.03))
    z, hit = sampler.first_hits(rays)
    assert bool(hit.all())
    starts, ends = sampler(rays, stratified=True)
    _check_intervals(starts, ends, rays, 24)
    t = sampler.sample_points(rays, z, stratified=True)
    inside = ((t - z[:, None]).abs() <= sampler.half_window + 1e-5).sum(-1)
    assert torch.all(inside >= 16), "every importance sample lies in z +- 3 sqrt(3) v"
    mids = t
    assert math.isclose(sampler.half_window, 3 * math.sqrt(3) * octree.leaf_size)
    # Importance samples follow N(z, 3 v^2): their spread is about sqrt(3) v (a bit less after truncation).
    near_z = torch.where((mids - z[:, None]).abs() <= sampler.half_window, mids - z[:, None], torch.nan)
    std = float(torch.nanmean(near_z**2).sqrt())
    assert 0.7 * math.sqrt(3) * octree.leaf_size < std < 1.1 * math.sqrt(3) * octree.leaf_size


def test_the_window_centred_on_the_surface_sits_on_the_wall_and_on_the_entry_in_front_of_it():
    """A wall x = 0.8 of points in leaves of 0.05: the 'entry' window centres on the first leaf's entry face,
    x = 0.8 - 0.025 (the paper's z); the 'surface' window on the wall, where the ray passes the leaf's points."""
    octree = _wall_octree(leaf=0.05)
    rays = _rays(64, direction=(1.0, 0.05, -0.03))
    x_at = {}
    for centre in WINDOW_CENTRES:
        sampler = VoxNeRFSampler(octree, 16, 8, OccGridSampler(OccupancyGrid(16), 24), centre=centre)
        z, hit = sampler.first_hits(rays)
        assert bool(hit.all())
        x_at[centre] = rays.origins[:, 0] + z * rays.dirs[:, 0]
        _check_intervals(*sampler(rays, stratified=True), rays, 24)
    leaf = octree.leaf_size
    torch.testing.assert_close(x_at["entry"], torch.full_like(x_at["entry"], 0.8 - leaf / 2), atol=leaf / 2 + 1e-4,
                               rtol=0)
    assert bool((x_at["entry"] < 0.8 - 1e-3).all())
    torch.testing.assert_close(x_at["surface"], torch.full_like(x_at["surface"], 0.8), atol=2e-3, rtol=0)


def test_a_narrower_window_packs_its_samples_closer_to_the_centre():
    octree = _wall_octree()
    rays = _rays(256, direction=(1.0, 0.05, -0.03))
    spread = {}
    for width in (1.0, 0.5):
        sampler = VoxNeRFSampler(octree, 16, 8, OccGridSampler(OccupancyGrid(16), 24), width=width)
        assert math.isclose(sampler.half_window, 3 * math.sqrt(3) * octree.leaf_size * width)
        z, _ = sampler.first_hits(rays)
        t = sampler.sample_points(rays, z, stratified=True)
        inside = ((t - z[:, None]).abs() <= sampler.half_window + 1e-5)
        assert bool((inside.sum(-1) >= 16).all())
        spread[width] = float(torch.where(inside, t - z[:, None], torch.nan).pow(2).nanmean().sqrt())
    assert 0.4 < spread[0.5] / spread[1.0] < 0.6


@pytest.mark.parametrize("width", [0.0, -1.0, math.inf, math.nan])
def test_a_window_width_is_a_positive_finite_multiple(width):
    with pytest.raises(ValueError, match="window width"):
        VoxNeRFSampler(_wall_octree(), 16, 8, OccGridSampler(OccupancyGrid(16), 24), width=width)


def test_a_window_centre_is_one_of_the_known_rules():
    octree = _wall_octree()
    with pytest.raises(ValueError, match="window centre 'middle'"):
        VoxNeRFSampler(octree, 16, 8, OccGridSampler(OccupancyGrid(16), 24), centre="middle")
    rays = _rays(4)
    with pytest.raises(ValueError, match="window centre 'middle'"):
        window_centres(octree, "middle", rays.origins, rays.dirs, rays.near, rays.far)


def test_voxnerf_importance_intervals_tile_the_window():
    """The field is read at interval middles: all n_importance of them must lie inside z +- 3 sqrt(3) v, and
    the importance intervals must cover exactly that window (no long interval from the sparse samples
    reaches into it)."""
    octree = _wall_octree()
    sampler = VoxNeRFSampler(octree, 8, 4, OccGridSampler(OccupancyGrid(16), 12))
    rays = _rays(128, direction=(1.0, 0.05, -0.03))
    z, _ = sampler.first_hits(rays)
    for stratified in (True, False):
        starts, ends = sampler(rays, stratified)
        _check_intervals(starts, ends, rays, 12)
        half = sampler.half_window
        mids = 0.5 * (starts + ends)
        inside = (mids - z[:, None]).abs() < half
        assert torch.all(inside.sum(-1) == 8)
        width_inside = ((ends - starts) * inside).sum(-1)
        torch.testing.assert_close(width_inside, torch.full_like(z, 2 * half), rtol=1e-4, atol=1e-5)


def test_window_split_is_clipped_to_the_ray():
    """A window reaching past near/far still gives sorted intervals inside [near, far]."""
    t = torch.tensor([[0.05, 0.1, 0.2, 0.9]])
    starts, ends = intervals_around_window(
        t, torch.tensor([0.0]), torch.tensor([1.0]), torch.tensor([-0.5]), torch.tensor([0.15])
    )
    torch.testing.assert_close(starts, torch.tensor([[0.0, 0.075, 0.15, 0.55]]))
    torch.testing.assert_close(ends, torch.tensor([[0.075, 0.15, 0.55, 1.0]]))


def test_voxnerf_sampler_falls_back_to_occupancy_grid_on_miss():
    octree = _wall_octree()
    grid = OccupancyGrid(16)
    grid.occupied.zero_()
    cell = grid.cell_index(torch.tensor([[-0.5, 0.0, 0.0]]))
    grid.occupied[cell] = True
    fallback = OccGridSampler(grid, 24)
    sampler = VoxNeRFSampler(octree, 16, 8, fallback)
    rays = _rays(8, direction=(-1.0, 0.0, 0.0), far=0.95)  # away from the wall: no hit
    _, hit = sampler.first_hits(rays)
    assert not bool(hit.any())
    starts, ends = sampler(rays, stratified=False)
    _check_intervals(starts, ends, rays, 24)
    mids = 0.5 * (starts + ends)
    in_cell = ((mids > 0.5 - 0.125) & (mids < 0.5)).float().mean()
    assert in_cell > 0.9, "the occupancy grid's only occupied cell gets the samples"


def test_occupancy_grid_update_tracks_density():
    grid = OccupancyGrid(8)

    def density(p):
        return torch.where(p[:, 0] > 0.5, torch.full_like(p[:, 0], 100.0), torch.zeros_like(p[:, 0]))

    for i in range(3):
        grid.update(density, warmup=i == 0)
    centres = torch.tensor([[0.8, 0.0, 0.0], [-0.8, 0.0, 0.0]])
    assert grid.is_occupied(centres).tolist() == [True, False]


def test_occgrid_sampler_uniform_when_grid_full():
    grid = OccupancyGrid(8)
    rays = _rays(4)
    starts, ends = OccGridSampler(grid, 10)(rays, stratified=False)
    widths = ends - starts
    torch.testing.assert_close(widths[:, 1:-1], widths[:, 1:2].expand(4, 8), rtol=1e-3, atol=1e-4)


def test_prepare_calls_density_once_with_the_updates_shape_and_leaves_the_grid_alone():
    grid, seen = OccupancyGrid(8), []

    def density(p):
        seen.append((tuple(p.shape), p.dtype, torch.is_grad_enabled()))
        return torch.zeros(len(p))

    before = (grid.density_ema.clone(), grid.occupied.clone(), int(grid.updates))
    grid.prepare(density)
    assert seen == [((GRID_UPDATE_BATCH, 3), torch.float32, False)]
    assert (torch.equal(grid.density_ema, before[0]) and torch.equal(grid.occupied, before[1])
            and int(grid.updates) == before[2])
    grid.update(density, warmup=True)  # 512 cells: one padded chunk, the shape prepare used
    assert seen[1] == seen[0]


def test_occupancy_grid_update_calls_density_with_one_shape():
    """A compiled density function must see one shape: every chunk is exactly ``batch`` points, the last padded,
    and the padding does not reach the grid."""
    grid, seen = OccupancyGrid(8), []

    def density(p):
        seen.append(len(p))
        return torch.where(p[:, 0] > 0.5, torch.full_like(p[:, 0], 100.0), torch.zeros_like(p[:, 0]))

    grid.update(density, warmup=True, batch=100)  # 512 cells: 5 full chunks and 12 points
    assert seen == [100] * 6
    assert int(grid.occupied.sum()) == 8 * 8 * 2  # the two cell layers with x > 0.5; the zero padding is not
    assert grid.is_occupied(torch.tensor([[0.8, 0.0, 0.0], [-0.8, 0.0, 0.0]])).tolist() == [True, False]


def _half_missing_rays(n: int) -> RayBundle:
    """``n`` rays, the first half towards the wall of :func:`_wall_octree` (hits), the second half away from it
    (misses), the misses' first hits cast too."""
    towards = _rays(n // 2, direction=(1.0, 0.05, -0.03))
    away = _rays(n - n // 2, direction=(-1.0, 0.02, 0.04), far=0.95)
    return RayBundle(*(torch.cat([a, b]) for a, b in zip(
        (towards.origins, towards.dirs, towards.near, towards.far), (away.origins, away.dirs, away.near, away.far),
        strict=True)))


def _samplers(octree, n_importance=8, n_rest=4) -> dict[str, VoxNeRFSampler]:
    grid = OccupancyGrid(16)
    grid.occupied.zero_()
    grid.occupied[grid.cell_index(torch.tensor([[-0.5, 0.0, 0.0], [0.3, 0.0, 0.0]]))] = True
    fallback = OccGridSampler(grid, n_importance + n_rest)
    return {misses: VoxNeRFSampler(octree, n_importance, n_rest, fallback, misses) for misses in OCTREE_MISSES}


def test_masked_misses_give_the_gathered_intervals():
    """The sync-free path ("mask": the fallback on every ray, kept where the ray missed) gives the intervals the
    gathering one gives, on rays that all hit, all miss, and half and half."""
    octree = _wall_octree()
    samplers = _samplers(octree)
    rays = _half_missing_rays(64)
    rays.hit_t, rays.hit = samplers["gather"].first_hits(rays)
    assert bool(rays.hit[:32].all()) and not bool(rays.hit[32:].any())
    for rows in (slice(0, 32), slice(32, 64), slice(0, 64)):
        part = rays.take(rows)
        gathered = samplers["gather"](part, stratified=False)
        masked = samplers["mask"](part, stratified=False)
        for g, m in zip(gathered, masked, strict=True):
            assert torch.equal(g, m), rows
        _check_intervals(*masked, part, 12)
    # Stratified: the same seed gives the hitting rays the same samples; the missing rays draw from the stream in
    # another shape (every ray against the missing ones), so theirs are only valid intervals.
    out = {}
    for misses, sampler in samplers.items():
        torch.manual_seed(3)
        out[misses] = sampler(rays, stratified=True)
        _check_intervals(*out[misses], rays, 12)
    for g, m in zip(out["gather"], out["mask"], strict=True):
        assert torch.equal(g[:32], m[:32])


def test_masked_misses_need_no_host_sync():
    """The "mask" path compiles as one graph (``fullgraph=True`` fails on any graph break, and reading a tensor's
    value on the host, as the gathering path's branch and sized gather do, is one); the gathering path does not."""
    octree = _wall_octree()
    rays = _half_missing_rays(32)
    samplers = _samplers(octree)
    rays.hit_t, rays.hit = samplers["gather"].first_hits(rays)
    for misses, sampler in samplers.items():
        torch._dynamo.reset()

        def sample(origins, dirs, near, far, hit_t, hit, sampler=sampler):
            return sampler(RayBundle(origins, dirs, near, far, hit_t, hit), False)

        compiled = torch.compile(sample, fullgraph=True, backend="eager")
        args = (rays.origins, rays.dirs, rays.near, rays.far, rays.hit_t, rays.hit)
        if misses == "mask":
            for c, e in zip(compiled(*args), sampler(rays, False), strict=True):
                assert torch.equal(c, e)
        else:
            # a graph break (Unsupported) or a guard on a value only the device knows (UserError: data-dependent)
            with pytest.raises((torch._dynamo.exc.Unsupported, torch._dynamo.exc.UserError)):
                compiled(*args)
    torch._dynamo.reset()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA: the sync debug mode watches CUDA syncs")
def test_masked_misses_make_no_cuda_sync():
    octree = _wall_octree().to(torch.device("cuda"))
    rays = _half_missing_rays(64)
    sampler = _samplers(octree)["mask"]
    sampler.fallback.grid.to("cuda")
    rays = RayBundle(*(x.cuda() for x in (rays.origins, rays.dirs, rays.near, rays.far)))
    rays.hit_t, rays.hit = sampler.first_hits(rays)
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        sampler(rays, stratified=True)
    finally:
        torch.cuda.set_sync_debug_mode("default")


def test_octree_misses_are_gathered_on_a_cpu_and_masked_elsewhere():
    assert octree_misses_on("auto", "cpu") == "gather" and octree_misses_on("auto", torch.device("cpu")) == "gather"
    assert octree_misses_on("auto", "cuda") == "mask" and octree_misses_on("auto", torch.device("cuda:1")) == "mask"
    assert octree_misses_on("mask", "cpu") == "mask" and octree_misses_on("gather", "cuda") == "gather"
    with pytest.raises(ValueError, match="octree misses 'sometimes'"):
        octree_misses_on("sometimes", "cpu")
    with pytest.raises(ValueError, match="octree misses 'auto'"):
        VoxNeRFSampler(_wall_octree(), 8, 4, OccGridSampler(OccupancyGrid(8), 12), "auto")
