"""Ray samplers behind one interface: ``sampler(rays, stratified) -> (t_starts, t_ends)``, each [R, S].

Every sampler returns the same number ``S`` of sorted, non-overlapping intervals per ray inside
``[near, far]`` (dense packing keeps shapes static, which lets the training step compile once).

- :class:`UniformSampler`: NeRF's stratified uniform samples.
- :class:`OccGridSampler`: instant-ngp / nerfacc occupancy grid with empty-space skipping; the grid is
  updated from the field's density. The fixed budget of samples is spread over the occupied cells a ray
  crosses (inverse transform sampling of the ray's occupancy), so empty space gets almost none.
- :class:`VoxNeRFSampler` (paper III-C): ``n_importance`` samples from ``N(z, 3 v^2)`` truncated to
  ``z +- 3 sqrt(3) v`` around the first occupied octree leaf ``z``, ``n_rest`` uniform on the rest of
  ``[near, far]``. ``z`` is where the ray passes the leaf's point mean or the leaf's entry, one of
  :data:`WINDOW_CENTRES` (:func:`window_centres` is the one rule, for training's cache and for renders);
  rays that hit no leaf fall back to the occupancy grid, by one of :data:`OCTREE_MISSES`
  (:func:`octree_misses_on` picks it per device).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from voxnerf.prior.octree import SparseVoxelOctree

# Gaussian CDF at -3 and +3 standard deviations: the importance window of the paper.
_PHI_LO = 0.5 * math.erfc(3.0 / math.sqrt(2.0))
_PHI_HI = 1.0 - _PHI_LO

# How the VoxNeRF sampler gives the rays that miss the octree their occupancy-grid intervals:
# - "gather": the fallback samples only the missing rays (a sized gather and scatter, and a branch on whether any
#   ray missed: each reads the hit mask on the host, a device sync per batch on a GPU);
# - "mask": the fallback samples every ray and ``torch.where`` keeps its intervals where the ray missed (fixed
#   shapes, nothing read on the host: on a GPU the batch queues without waiting, and it can be compiled whole).
OCTREE_MISSES = ("gather", "mask")

# Where the VoxNeRF sampler centres its window along a ray that hits the octree:
# - "entry": the first occupied leaf's entry (the paper's z), in front of the surface by up to a leaf diagonal;
# - "surface": where the ray passes the mean of the prior's points in that leaf, inside the leaf
#   (SparseVoxelOctree.surface_hit); an octree saved without leaf means falls back to the entry.
WINDOW_CENTRES = ("entry", "surface")


def window_centres(
    octree: SparseVoxelOctree, centre: str, origins: Tensor, dirs: Tensor, near: Tensor, far: Tensor,
    t_hint: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """The window centre z [N] (normalised ray distance; ``far`` where the ray misses) and hit [N] of rays
    [N, 3] by the :data:`WINDOW_CENTRES` rule ``centre``; ``t_hint`` [N] (NaN: none) only saves work."""
    if centre == "surface":
        return octree.surface_hit(origins, dirs, near, far, t_hint=t_hint)
    if centre == "entry":
        return octree.first_hit(origins, dirs, near, far, t_hint=t_hint)
    raise ValueError(f"window centre {centre!r}: expected one of {', '.join(WINDOW_CENTRES)}")


def octree_misses_on(choice: str, device: torch.device | str) -> str:
    """The :data:`OCTREE_MISSES` entry that ``choice`` ("auto" or one of them) means on ``device``: "auto" is
    "gather" on a CPU, where a sync costs nothing and sampling every ray through the occupancy grid costs the
    fallback's march for each hitting ray too, and "mask" elsewhere (docs/cuda.md). ValueError for anything else."""
    if choice == "auto":
        return "gather" if torch.device(device).type == "cpu" else "mask"
    if choice not in OCTREE_MISSES:
        raise ValueError(f"octree misses {choice!r}: expected auto or one of {', '.join(OCTREE_MISSES)}")
    return choice


@dataclass
class RayBundle:
    """Rays in normalised units. origins, dirs (unit) [R, 3]; near, far [R].

    ``hit_t``/``hit`` [R] optionally carry precomputed octree first hits (the trainer caches them per pixel).
    """

    origins: Tensor
    dirs: Tensor
    near: Tensor
    far: Tensor
    hit_t: Tensor | None = None
    hit: Tensor | None = None

    def __len__(self) -> int:
        return self.origins.shape[0]

    def slice(self, start: int, stop: int) -> RayBundle:
        """Rays ``start:stop`` (views of this bundle's tensors)."""
        return self.take(slice(start, stop))

    def take(self, rows: slice | Tensor) -> RayBundle:
        """The rays ``rows`` selects (a slice, a bool mask or int64 indices), first hits included."""
        hits = (None, None) if self.hit_t is None or self.hit is None else (self.hit_t[rows], self.hit[rows])
        return RayBundle(self.origins[rows], self.dirs[rows], self.near[rows], self.far[rows], *hits)


def intervals_from_points(t: Tensor, near: Tensor, far: Tensor) -> tuple[Tensor, Tensor]:
    """Sorted sample distances [R, S] -> intervals [R, S] split at the midpoints between samples, the first
    opening at ``near`` and the last closing at ``far`` [R] (so the intervals tile the whole ray)."""
    return _tile(0.5 * (t[:, 1:] + t[:, :-1]), near, far)


def _tile(splits: Tensor, near: Tensor, far: Tensor) -> tuple[Tensor, Tensor]:
    """Inner split points [R, S-1] -> intervals [R, S] from ``near`` to ``far`` [R]."""
    return torch.cat([near[:, None], splits], dim=1), torch.cat([splits, far[:, None]], dim=1)


def intervals_around_window(
    t: Tensor, near: Tensor, far: Tensor, window_lo: Tensor, window_hi: Tensor
) -> tuple[Tensor, Tensor]:
    """Like :func:`intervals_from_points`, but no interval crosses the window ``[window_lo, window_hi]`` [R]:
    between a sample outside it and one inside, the split is the window's edge, not the midpoint.

    The samples inside then tile exactly the window (clipped to ``[near, far]``), so the field, evaluated at
    each interval's middle, is read inside the window for every importance sample, and a long interval from
    the sparse samples outside never reaches into it.
    """
    a, b = t[:, :-1], t[:, 1:]
    lo, hi = window_lo[:, None], window_hi[:, None]
    split = 0.5 * (a + b)
    split = torch.where((a < lo) & (b >= lo), lo, split)
    split = torch.where((a <= hi) & (b > hi), hi, split)
    return _tile(torch.minimum(torch.maximum(split, a), b), near, far)


def _stratified_unit(n_rays: int, n: int, stratified: bool, device: torch.device) -> Tensor:
    """[R, n] sorted numbers in (0, 1): bin centres, or one uniform draw per bin when stratified."""
    offset = torch.rand(n_rays, n, device=device) if stratified else torch.full((n_rays, n), 0.5, device=device)
    return (torch.arange(n, device=device, dtype=torch.float32) + offset) / n


class UniformSampler:
    """``n_samples`` stratified uniform samples on [near, far]."""

    def __init__(self, n_samples: int) -> None:
        self.n_samples = n_samples

    def __call__(self, rays: RayBundle, stratified: bool) -> tuple[Tensor, Tensor]:
        u = _stratified_unit(len(rays), self.n_samples, stratified, rays.origins.device)
        t = rays.near[:, None] + u * (rays.far - rays.near)[:, None]
        return intervals_from_points(t, rays.near, rays.far)


GRID_UPDATE_BATCH = 65_536  # points per density call of an update: one shape, so a compiled density compiles once


class OccupancyGrid(nn.Module):
    """A ``res^3`` binary occupancy grid over the canonical box ``[-1, 1]^3``, kept from an EMA of density.

    Update rule (nerfacc's): evaluate density at a jittered point of every cell (during warm-up) or of a
    random quarter of the cells plus the occupied ones, ``ema = max(decay * ema, density)``, occupied where
    ``ema * cell_size > threshold`` or above the mean (whichever is lower).
    """

    def __init__(self, resolution: int = 64, threshold: float = 0.01, decay: float = 0.95) -> None:
        super().__init__()
        self.resolution, self.threshold, self.decay = resolution, threshold, decay
        n = resolution**3
        self.register_buffer("density_ema", torch.full((n,), float("inf")))
        self.register_buffer("occupied", torch.ones(n, dtype=torch.bool))
        self.register_buffer("updates", torch.zeros((), dtype=torch.int64))

    @property
    def cell_size(self) -> float:
        return 2.0 / self.resolution

    def cell_index(self, points: Tensor) -> Tensor:
        """[N, 3] normalised points -> [N] flat cell index (points outside are clamped to the border)."""
        ijk = ((points + 1.0) * (0.5 * self.resolution)).floor().long().clamp(0, self.resolution - 1)
        return (ijk[:, 0] * self.resolution + ijk[:, 1]) * self.resolution + ijk[:, 2]

    def is_occupied(self, points: Tensor) -> Tensor:
        """[N, 3] -> [N] bool; points outside the box are empty."""
        inside = (points.abs() <= 1.0).all(-1)
        return self.occupied[self.cell_index(points)] & inside

    @torch.no_grad()
    def seed_from_points(self, points: Tensor, dilation: int = 1) -> None:
        """Start from the cells holding ``points`` [N, 3] (a prior), dilated by ``dilation`` cells."""
        grid = torch.zeros(self.resolution**3, device=points.device)
        grid[self.cell_index(points)] = 1.0
        grid = grid.view(1, 1, *(self.resolution,) * 3)
        grid = nn.functional.max_pool3d(grid, 2 * dilation + 1, stride=1, padding=dilation).reshape(-1)
        seeded = grid > 0
        self.occupied.copy_(seeded)
        self.density_ema.copy_(torch.where(seeded, self.threshold / self.cell_size * 10, 0.0))

    @torch.no_grad()
    def prepare(self, density_fn: Callable[[Tensor], Tensor], batch: int = GRID_UPDATE_BATCH) -> None:
        """Call ``density_fn`` once on ``batch`` points, as :meth:`update` calls it: a compiled one compiles now."""
        density_fn(self.density_ema.new_zeros(batch, 3))

    @torch.no_grad()
    def update(self, density_fn: Callable[[Tensor], Tensor], warmup: bool, batch: int = GRID_UPDATE_BATCH) -> None:
        """Refresh the EMA from ``density_fn`` ([N, 3] -> [N] densities) and re-threshold.

        ``density_fn`` always gets exactly ``batch`` points (the last chunk is padded), so a compiled function
        sees one shape and compiles once.
        """
        n = self.resolution**3
        device = self.density_ema.device
        if warmup:
            cells = torch.arange(n, device=device)
        else:
            random_cells = torch.randint(0, n, (n // 4,), device=device)
            cells = torch.cat([random_cells, self.occupied.nonzero().squeeze(-1)])
        r = self.resolution
        ijk = torch.stack([cells // (r * r), (cells // r) % r, cells % r], dim=-1)
        points = (ijk + torch.rand(ijk.shape, device=device)) * self.cell_size - 1.0
        padded = torch.cat([points, points.new_zeros(-len(points) % batch, 3)])
        density = torch.cat([density_fn(padded[i : i + batch]) for i in range(0, len(padded), batch)])
        density = density[: len(points)]
        density = torch.nan_to_num(density.float(), nan=0.0, posinf=1e10)
        ema = self.density_ema.clone()
        ema = torch.where(torch.isinf(ema), torch.zeros_like(ema), ema)
        ema[cells] = torch.maximum(ema[cells] * self.decay, density)
        self.density_ema.copy_(ema)
        limit = min(self.threshold / self.cell_size, float(ema.mean()))
        self.occupied.copy_(ema > limit)
        self.updates += 1


class OccGridSampler:
    """Empty-space skipping with an :class:`OccupancyGrid` and a fixed number of samples per ray.

    The ray is marched at ``n_march`` points; the samples follow the piecewise-constant density
    ``occupied + floor`` (``floor`` keeps rays through empty space sampled uniformly).
    """

    def __init__(self, grid: OccupancyGrid, n_samples: int, n_march: int = 128, floor: float = 1e-3) -> None:
        self.grid, self.n_samples, self.n_march, self.floor = grid, n_samples, n_march, floor

    def __call__(self, rays: RayBundle, stratified: bool) -> tuple[Tensor, Tensor]:
        r, m, device = len(rays), self.n_march, rays.origins.device
        edges = torch.linspace(0.0, 1.0, m + 1, device=device)
        span = (rays.far - rays.near)[:, None]
        centers = rays.near[:, None] + 0.5 * (edges[1:] + edges[:-1]) * span  # [R, M]
        points = rays.origins[:, None, :] + centers[..., None] * rays.dirs[:, None, :]
        occ = self.grid.is_occupied(points.reshape(-1, 3)).view(r, m).float()
        pdf = occ + self.floor
        cdf = torch.cat([torch.zeros(r, 1, device=device), torch.cumsum(pdf, -1)], dim=-1)
        cdf = cdf / cdf[:, -1:]
        u = _stratified_unit(r, self.n_samples, stratified, device)
        idx = torch.searchsorted(cdf, u, right=True).clamp(1, m)
        c0, c1 = cdf.gather(1, idx - 1), cdf.gather(1, idx)
        e0, e1 = edges[idx - 1], edges[idx]
        frac = ((u - c0) / (c1 - c0).clamp_min(1e-12)).clamp(0.0, 1.0)
        t = rays.near[:, None] + (e0 + frac * (e1 - e0)) * span
        return intervals_from_points(t, rays.near, rays.far)


class VoxNeRFSampler:
    """The paper's surface-guided sampler (III-C) on a :class:`SparseVoxelOctree`."""

    def __init__(
        self, octree: SparseVoxelOctree, n_importance: int, n_rest: int, fallback: OccGridSampler,
        misses: str = "gather", centre: str = "entry", width: float = 1.0,
    ) -> None:
        self.octree, self.n_importance, self.n_rest, self.fallback = octree, n_importance, n_rest, fallback
        if fallback.n_samples != n_importance + n_rest:
            raise ValueError("the fallback sampler must give n_importance + n_rest samples")
        if misses not in OCTREE_MISSES:
            raise ValueError(f"octree misses {misses!r}: expected one of {', '.join(OCTREE_MISSES)}")
        self.misses = misses  # how the rays that miss the octree get the fallback's intervals (OCTREE_MISSES)
        if centre not in WINDOW_CENTRES:
            raise ValueError(f"window centre {centre!r}: expected one of {', '.join(WINDOW_CENTRES)}")
        self.centre = centre  # where the window sits on a ray that hits (WINDOW_CENTRES)
        if not (math.isfinite(width) and width > 0):
            raise ValueError(f"window width must be a positive multiple of the paper's, got {width}")
        self.width = width  # the window's half-width and the Gaussian's std, in multiples of the paper's

    @property
    def half_window(self) -> float:
        """3 * sqrt(3) * v (the paper's) times ``width``: half the importance window (normalised units)."""
        return 3.0 * math.sqrt(3.0) * self.octree.leaf_size * self.width

    def first_hits(self, rays: RayBundle) -> tuple[Tensor, Tensor]:
        """Window centres z [R] and hit [R]: the bundle's cached ones (the trainer's, cast by the same rule) or
        :func:`window_centres`."""
        if rays.hit_t is not None and rays.hit is not None:
            return rays.hit_t, rays.hit
        return window_centres(self.octree, self.centre, rays.origins, rays.dirs, rays.near, rays.far)

    def sample_points(self, rays: RayBundle, z: Tensor, stratified: bool) -> Tensor:
        """Sorted sample distances [R, n_importance + n_rest] around first hits ``z`` [R]."""
        device, r = rays.origins.device, len(rays)
        half = self.half_window
        std = half / 3.0
        rows = r if stratified else 1  # bin centres are the same for every ray: [1, n], broadcast
        # Truncated normal by inverse CDF of stratified quantiles in [Phi(-3), Phi(3)].
        u = _stratified_unit(rows, self.n_importance, stratified, device)
        q = torch.special.ndtri(_PHI_LO + u * (_PHI_HI - _PHI_LO))
        t_imp = z[:, None] + std * q
        # Uniform on [near, z - half] U [z + half, far].
        before = (z - half - rays.near).clamp_min(0.0)
        after = (rays.far - (z + half)).clamp_min(0.0)
        s = _stratified_unit(rows, self.n_rest, stratified, device) * (before + after)[:, None]
        t_rest = torch.where(
            s < before[:, None], rays.near[:, None] + s, (z + half)[:, None] + (s - before[:, None])
        )
        t = torch.cat([t_imp, t_rest], dim=1)
        t = torch.minimum(torch.maximum(t, rays.near[:, None]), rays.far[:, None])
        return torch.sort(t, dim=1).values

    def __call__(self, rays: RayBundle, stratified: bool) -> tuple[Tensor, Tensor]:
        z, hit = self.first_hits(rays)
        t = self.sample_points(rays, z, stratified)
        starts, ends = intervals_around_window(t, rays.near, rays.far, z - self.half_window, z + self.half_window)
        if self.misses == "mask":
            fs, fe = self.fallback(RayBundle(rays.origins, rays.dirs, rays.near, rays.far), stratified)
            miss = ~hit[:, None]
            return torch.where(miss, fs, starts), torch.where(miss, fe, ends)
        if bool((~hit).any()):
            miss = ~hit
            sub = RayBundle(rays.origins[miss], rays.dirs[miss], rays.near[miss], rays.far[miss])
            fs, fe = self.fallback(sub, stratified)
            starts = starts.index_put((miss,), fs)
            ends = ends.index_put((miss,), fe)
        return starts, ends
