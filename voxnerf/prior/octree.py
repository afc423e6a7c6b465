"""Sparse Voxel Octree over the geometry prior (paper III-B) and exact first-hit ray casting.

Layout (like kaolin's SPC): level ``l`` (0 = root, ``levels`` = leaves) stores the sorted unique 63-bit
Morton codes of its occupied nodes. Traversal tables derived from them give, per internal node, the index
of each child in the next level (or -1) and the node's mid-planes, so descending needs no searches.

Geometry: the root cube has its min corner at ``origin`` and side ``leaf_size * 2**levels``; leaf
``(i, j, k)`` spans ``[origin + i * leaf_size, origin + (i + 1) * leaf_size]`` per axis, each plane computed
in float32 as ``origin + integer * leaf_size``, so an independent slab test reproduces the traversal bit for
bit. A ray hits a leaf when their intersection inside ``[t_min, t_max]`` has positive length. A zero direction
component counts as +1e-30: a ray lying exactly in a voxel plane belongs to the voxel on the plane's + side.
"""

from __future__ import annotations

import copy
import ctypes
import functools
import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from voxnerf import native

MAX_LEVELS = 21  # 21 bits per axis fit a 63-bit Morton code in an int64

# (shift, mask) steps that spread the low 21 bits of x to every third bit (bit b -> bit 3b).
_SPREAD_STEPS = (
    (32, 0x001F00000000FFFF),
    (16, 0x001F0000FF0000FF),
    (8, 0x100F00F00F00F00F),
    (4, 0x10C30C30C30C30C3),
    (2, 0x1249249249249249),
)
_AXIS_BITS_MASK = 0x1249249249249249
_LOW21_MASK = (1 << MAX_LEVELS) - 1


def _spread_bits(x: Tensor) -> Tensor:
    x = x & _LOW21_MASK
    for shift, mask in _SPREAD_STEPS:
        x = (x | (x << shift)) & mask
    return x


def _compact_bits(x: Tensor) -> Tensor:
    x = x & _AXIS_BITS_MASK
    masks = [m for _, m in _SPREAD_STEPS[:-1]][::-1] + [_LOW21_MASK]
    shifts = [s for s, _ in _SPREAD_STEPS][::-1]
    for shift, mask in zip(shifts, masks, strict=True):
        x = (x ^ (x >> shift)) & mask
    return x


def morton_encode(ijk: Tensor) -> Tensor:
    """Interleave integer coordinates [N, 3] (each in [0, 2**21)) into int64 Morton codes [N].

    Bit ``3b + a`` of the code is bit ``b`` of axis ``a`` (x in the lowest bit), so ``code >> 3`` is the
    parent's code and ``code & 7`` the child slot ``x | y << 1 | z << 2``.
    """
    ijk = ijk.to(torch.int64)
    return _spread_bits(ijk[:, 0]) | (_spread_bits(ijk[:, 1]) << 1) | (_spread_bits(ijk[:, 2]) << 2)


def morton_decode(codes: Tensor) -> Tensor:
    """Inverse of :func:`morton_encode`: int64 codes [N] -> int64 coordinates [N, 3]."""
    codes = codes.to(torch.int64)
    return torch.stack([_compact_bits(codes), _compact_bits(codes >> 1), _compact_bits(codes >> 2)], dim=1)


@dataclass
class _TraversalTables:
    """Per internal level ``l`` (0..L-1), derived from the codes:

    - ``child_index[l]`` int32 [8 * n_l]: entry ``node * 8 + slot`` is the index in ``codes[l + 1]`` of child
      ``slot`` (``x | y << 1 | z << 2``) of node ``node``, or -1 when that child is empty;
    - ``planes[l]`` float32 [3, n_l]: each node's mid-planes, ``origin + (2 * ijk + 1) * half_side``.
    """

    child_index: list[Tensor]
    planes: list[Tensor]

    @staticmethod
    def build(codes: list[Tensor], origin: Tensor, leaf_size: float) -> _TraversalTables:
        levels = len(codes) - 1
        v = torch.tensor(leaf_size, dtype=torch.float32, device=origin.device)
        child_index, planes = [], []
        for level in range(levels):
            children = codes[level + 1]
            parent = torch.searchsorted(codes[level], children >> 3)
            table = torch.full((codes[level].numel() * 8,), -1, dtype=torch.int32, device=children.device)
            index = torch.arange(children.numel(), dtype=torch.int32, device=children.device)
            table[parent * 8 + (children & 7)] = index
            child_index.append(table)
            mid = (morton_decode(codes[level]).T.to(torch.float32) * 2 + 1) * float(2 ** (levels - level - 1))
            planes.append((mid * v + origin[:, None]).contiguous())
        return _TraversalTables(child_index, planes)

    def to(self, device: torch.device) -> _TraversalTables:
        return _TraversalTables([t.to(device) for t in self.child_index], [p.to(device) for p in self.planes])

    def nbytes(self) -> int:
        return sum(t.numel() * t.element_size() for t in self.child_index + self.planes)


# Leaf sides tried by :func:`coverage_octree`, in units of the prior's sigma, and how many more rays (as a
# fraction) than through the coarsest of them may slip through the chosen one.
# Leaves around a leaf whose points give its surface (SparseVoxelOctree.leaf_means): a ray's first occupied leaf
# is often one the prior's noise reached in front of the surface, holding a few points near its back; the 3x3x3
# block around it also holds the surface's leaves behind it, so their mean lies near the surface, not the noise.
SURFACE_REACH = 1
COVERAGE_LEAF_SCALES = (1.0, 1.5, 2.0, 3.0)
COVERAGE_MISS_TOLERANCE = 0.01


@dataclass
class SparseVoxelOctree:
    """Occupied nodes of an octree, level by level, as sorted Morton codes.

    Attributes:
        codes: ``levels + 1`` sorted unique int64 tensors; ``codes[0] == [0]`` is the root, ``codes[-1]`` the
            occupied leaves (integer leaf coordinates in [0, 2**levels)).
        origin: [3] float32, min corner of the root cube (units of the input points).
        leaf_size: side of a leaf voxel (same units).
        levels: depth of the leaves (1..21).
        leaf_size_requested: the ``leaf_size`` asked for; larger ``leaf_size`` means depth was clamped.
        leaf_means: [L, 3] float32 (order of ``codes[-1]``), the mean of the points the octree was built from in
            the 3x3x3 leaves around each leaf (:data:`SURFACE_REACH`): where :meth:`surface_hit` puts the surface.
            None for an octree saved before it was kept (:meth:`surface_hit` then answers the leaf's entry, like
            :meth:`first_hit`).
    """

    codes: list[Tensor]
    origin: Tensor
    leaf_size: float
    levels: int
    leaf_size_requested: float
    leaf_means: Tensor | None = None
    _tables: _TraversalTables = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if len(self.codes) != self.levels + 1:
            raise ValueError(f"expected {self.levels + 1} code levels, got {len(self.codes)}")
        if self.leaf_means is not None and self.leaf_means.shape != (self.codes[-1].numel(), 3):
            raise ValueError(f"leaf_means must be [{self.codes[-1].numel()}, 3] like the leaves, "
                             f"got {tuple(self.leaf_means.shape)}")
        self._tables = _TraversalTables.build(self.codes, self.origin, self.leaf_size)

    @property
    def root_size(self) -> float:
        return self.leaf_size * 2**self.levels

    @property
    def device(self) -> torch.device:
        return self.origin.device

    @classmethod
    def from_points(
        cls, points: Tensor, leaf_size: float, *, max_levels: int = MAX_LEVELS, with_means: bool = True
    ) -> SparseVoxelOctree:
        """Voxelise points [N, 3] with leaves of side ``leaf_size`` (paper: v = max sigma).

        The root's min corner is the points' min corner minus ``leaf_size / 2``; ``levels`` is the smallest
        depth whose root covers the points, clamped to [1, max_levels]. When clamped, the leaf grows to
        ``extent / 2**max_levels`` (recorded against ``leaf_size_requested``). ``with_means``: keep
        ``leaf_means`` of ``points`` (False leaves them None, for a candidate tree that may be thrown away).
        """
        if points.dim() != 2 or points.shape[1] != 3 or points.shape[0] == 0:
            raise ValueError(f"points must be a non-empty [N, 3] tensor, got shape {tuple(points.shape)}")
        if not bool(torch.isfinite(points).all()):
            raise ValueError("points contain NaN or inf")
        if not (math.isfinite(leaf_size) and leaf_size > 0):
            raise ValueError(f"leaf_size must be positive and finite, got {leaf_size}")
        if not 1 <= max_levels <= MAX_LEVELS:
            raise ValueError(f"max_levels must be in [1, {MAX_LEVELS}], got {max_levels}")
        points = points.to(torch.float32)
        lo = points.amin(0).double()
        span = float((points.amax(0).double() - lo).max())
        levels = max(1, math.ceil(math.log2(span / leaf_size + 1.0)))  # root side >= span + one leaf
        leaf = leaf_size
        if levels > max_levels:
            levels = max_levels
            leaf = span / (2**max_levels - 1) * (1 + 1e-6)
        origin = (lo - 0.5 * leaf).to(torch.float32)
        ijk = torch.floor((points - origin) / leaf).clamp_(0, 2**levels - 1).to(torch.int64)
        codes = [torch.unique(morton_encode(ijk))]
        for _ in range(levels):
            codes.append(torch.unique_consecutive(codes[-1] >> 3))
        octree = cls(codes[::-1], origin, float(leaf), levels, float(leaf_size))
        if with_means:
            octree.leaf_means = octree.means_of(points, reach=SURFACE_REACH)
        return octree

    def state_dict(self) -> dict:
        """What :meth:`from_state_dict` restores: codes and scalars (traversal tables are derived)."""
        return {
            "codes": list(self.codes),
            "origin": self.origin,
            "leaf_size": self.leaf_size,
            "levels": self.levels,
            "leaf_size_requested": self.leaf_size_requested,
            "leaf_means": self.leaf_means,
        }

    @classmethod
    def from_state_dict(cls, state: dict) -> SparseVoxelOctree:
        means = state.get("leaf_means")  # absent from octrees saved before leaf means were kept
        return cls(
            [c.to(torch.int64) for c in state["codes"]],
            state["origin"].to(torch.float32),
            float(state["leaf_size"]),
            int(state["levels"]),
            float(state["leaf_size_requested"]),
            None if means is None else means.to(torch.float32),
        )

    def to(self, device: torch.device | str) -> SparseVoxelOctree:
        """A copy on ``device`` (traversal tables moved, not rebuilt)."""
        moved = copy.copy(self)
        moved.codes = [c.to(device) for c in self.codes]
        moved.origin = self.origin.to(device)
        moved.leaf_means = None if self.leaf_means is None else self.leaf_means.to(device)
        moved._tables = self._tables.to(torch.device(device))
        return moved

    def summary(self) -> dict:
        """JSON-able description: depth, leaf size, root cube, occupied nodes per level, memory in bytes."""
        return {
            "levels": self.levels,
            "leaf_size": self.leaf_size,
            "leaf_size_requested": self.leaf_size_requested,
            "depth_clamped": self.leaf_size != self.leaf_size_requested,
            "root_origin": [float(x) for x in self.origin.tolist()],
            "root_size": self.root_size,
            "nodes_per_level": [int(c.numel()) for c in self.codes],
            "memory_bytes": int(sum(c.numel() * c.element_size() for c in self.codes)),
            "traversal_table_bytes": self._tables.nbytes(),
        }

    def keep_leaves(self, keep: Tensor) -> SparseVoxelOctree:
        """The octree of the leaves where ``keep`` [L] (bool, order of ``codes[-1]``) is True, on the same root and
        leaf grid (inner nodes rebuilt from the kept leaves). Raises ValueError when it keeps none."""
        if keep.shape != self.codes[-1].shape or keep.dtype != torch.bool:
            raise ValueError(f"keep must be a bool tensor of shape {tuple(self.codes[-1].shape)}")
        if not bool(keep.any()):
            raise ValueError("keep_leaves would leave the octree empty")
        keep = keep.to(self.device)
        codes = [self.codes[-1][keep]]
        for _ in range(self.levels):
            codes.append(torch.unique_consecutive(codes[-1] >> 3))
        means = None if self.leaf_means is None else self.leaf_means[keep]
        return SparseVoxelOctree(codes[::-1], self.origin, self.leaf_size, self.levels, self.leaf_size_requested, means)

    def leaf_ijk(self, points: Tensor) -> Tensor:
        """Integer leaf coordinates [N, 3] (int64, may lie outside [0, 2**levels)) of points [N, 3]."""
        origin = self.origin.to(points.device)
        return torch.floor((points.to(torch.float32) - origin) / self.leaf_size).to(torch.int64)

    def leaf_index(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """Index into ``codes[-1]`` [N] (int64) of the leaf holding each point [N, 3], and whether it is occupied."""
        ijk = self.leaf_ijk(points)
        inside = ((ijk >= 0) & (ijk < 2**self.levels)).all(dim=1)
        leaves = self.codes[-1].to(points.device)
        codes = morton_encode(ijk.clamp(0, 2**self.levels - 1))
        pos = torch.searchsorted(leaves, codes).clamp_(max=leaves.numel() - 1)
        return pos, inside & (leaves[pos] == codes)

    def means_of(self, points: Tensor, reach: int = 0) -> Tensor:
        """Mean [L, 3] float32 of the points falling in each occupied leaf (order of ``codes[-1]``), or with
        ``reach`` r > 0 in the (2r + 1)^3 leaves around it (each point counted once per leaf whose block holds
        it); a leaf none of ``points`` falls in gets its centre."""
        device = points.device
        pos, found = self.leaf_index(points)
        pos, pts = pos[found], points[found].to(torch.float64)
        leaves = self.codes[-1].to(device)
        n_leaves = leaves.numel()
        sums = torch.zeros(n_leaves, 3, dtype=torch.float64, device=device).index_add_(0, pos, pts)
        counts = torch.zeros(n_leaves, dtype=torch.float64, device=device).index_add_(
            0, pos, torch.ones_like(pos, dtype=torch.float64)
        )
        ijk = morton_decode(leaves)
        if reach > 0:
            own_sums, own_counts = sums, counts
            sums, counts = torch.zeros_like(own_sums), torch.zeros_like(own_counts)
            steps = torch.arange(-reach, reach + 1, device=device)
            for offset in torch.cartesian_prod(steps, steps, steps):
                other = ijk + offset
                inside = ((other >= 0) & (other < 2**self.levels)).all(dim=1)
                codes = morton_encode(other.clamp(0, 2**self.levels - 1))
                at = torch.searchsorted(leaves, codes).clamp_(max=n_leaves - 1)
                occupied = (inside & (leaves[at] == codes)).to(torch.float64)
                sums += own_sums[at] * occupied[:, None]
                counts += own_counts[at] * occupied
        centres = self.origin.to(device).double() + (ijk.double() + 0.5) * self.leaf_size
        means = torch.where(counts[:, None] > 0, sums / counts.clamp_min(1)[:, None], centres)
        return means.to(torch.float32)

    def lookup_leaf(self, values: Tensor, points: Tensor) -> tuple[Tensor, Tensor]:
        """Per-leaf ``values`` [L, C] at the leaves holding ``points`` [N, 3] -> ([N, C], occupied [N]); rows of
        unoccupied points are arbitrary."""
        pos, found = self.leaf_index(points)
        return values[pos], found

    def leaf_occupied(self, points: Tensor) -> Tensor:
        """Whether each point [N, 3] lies in an occupied leaf -> bool [N]."""
        return self.leaf_index(points)[1]

    def first_hit(
        self,
        origins: Tensor,
        dirs: Tensor,
        t_min: Tensor | float,
        t_max: Tensor | float,
        *,
        chunk: int | None = None,
        t_hint: Tensor | None = None,
        use_kernel: bool | None = None,
    ) -> tuple[Tensor, Tensor]:
        """Distance to the first occupied leaf along each ray (exact).

        Args:
            origins, dirs: [N, 3] float on any device; dirs non-zero (``t`` is in units of ``|dir|``). A zero
                direction component counts as +1e-30, so a ray lying in a voxel plane belongs to the voxel on
                the plane's + side.
            t_min, t_max: [N] or scalars; only the part of the ray in [t_min, t_max] counts.
            chunk: most (ray, node) candidates expanded at once, bounding temporaries to about ``chunk * 200``
                bytes (default 2**17 on CPU, 2**21 on GPU).
            t_hint: [N] optional guess of where each ray meets the surface (NaN: none), e.g. the prior's pseudo
                depth. The search first stops a leaf diagonal past the guess and looks again over the whole
                segment only for the rays that found nothing there, so the result is the same with or without
                it; good guesses save expanding the nodes behind the first surface.
            use_kernel: trace CPU rays with the C kernel (``octree_trace.c``: the same arithmetic, one ray at a
                time, stopping at its first hit). Default: where it could be built; False: the PyTorch path.
        Returns:
            t_hit [N] float32: ``max(entry, t_min)`` of the first hit leaf, ``t_max`` where there is none;
            hit [N] bool.

        Method (like kaolin's SPC ray tracing): a frontier of every (ray, occupied node) pair whose segment
        has positive length descends level by level. A node's segment is split at its three mid-planes into
        at most 4 consecutive child segments; occupied children with positive length join the next frontier.
        Leaf candidates are reduced to the smallest entry per ray. Frontiers larger than ``chunk`` are halved
        and descended one after the other, so memory stays bounded whatever the rays.
        """
        if origins.dim() != 2 or origins.shape[1] != 3 or dirs.shape != origins.shape:
            shapes = f"{tuple(origins.shape)} and {tuple(dirs.shape)}"
            raise ValueError(f"origins and dirs must both be [N, 3], got {shapes}")
        device = origins.device
        n = origins.shape[0]
        t_min = torch.as_tensor(t_min, dtype=torch.float32, device=device).expand(n)
        t_max = torch.as_tensor(t_max, dtype=torch.float32, device=device).expand(n)
        if t_hint is not None:
            if t_hint.shape != (n,):
                raise ValueError(f"t_hint must be [N] = [{n}] like the rays, got {tuple(t_hint.shape)}")
            return self._first_hit_near(origins, dirs, t_min, t_max, t_hint, chunk, use_kernel)
        if device.type == "cpu" and (kernel_available() if use_kernel is None else use_kernel):
            best = self._trace_native(*self._root_segments(origins, dirs, t_min, t_max))
            hit = torch.isfinite(best)
            return torch.where(hit, best, t_max), hit
        tables = self._tables if device == self.device else self._tables.to(device)
        rays, root = self._root_frontier(*self._root_segments(origins, dirs, t_min, t_max))
        best = torch.full((n,), float("inf"), device=device)
        if chunk is None:
            chunk = _DEFAULT_CHUNK if device.type == "cpu" else _DEFAULT_CHUNK_GPU
        # On CPU, torch's intra-op threads leave cores idle on these gathers: give each core its own rays.
        workers = min(torch.get_num_threads(), _MAX_WORKERS) if device.type == "cpu" else 1
        count = root.ray.numel()
        if workers > 1 and count >= 2 * _MIN_RAYS_PER_PART:
            size = max(_MIN_RAYS_PER_PART, -(-count // (4 * workers)))  # 4 parts per worker: balance
            parts = [root.slice(i, i + size) for i in range(0, count, size)]
            with ThreadPoolExecutor(workers) as pool:
                list(pool.map(lambda part: self._descend(part, rays, tables, best, chunk), parts))
        else:
            self._descend(root, rays, tables, best, chunk)
        hit = torch.isfinite(best)
        return torch.where(hit, best, t_max), hit

    def surface_hit(
        self, origins: Tensor, dirs: Tensor, t_min: Tensor | float, t_max: Tensor | float, *,
        t_hint: Tensor | None = None,
    ) -> tuple[Tensor, Tensor]:
        """Where each ray meets the surface at its first occupied leaf: the distance at which it passes the
        leaf's point mean (``leaf_means``; the plane through the mean across the ray), clamped to a leaf diagonal
        past the leaf's entry. :meth:`first_hit` answers the leaf's entry, which lies in front of the surface by up to
        a leaf diagonal (half a leaf's chord on average).

        Args and returns as :meth:`first_hit` (``t_hint`` likewise only saves work); t [N] float32 is
        ``t_max`` where a ray hits no leaf, and the leaf's entry where the octree keeps no means.
        """
        t_entry, hit = self.first_hit(origins, dirs, t_min, t_max, t_hint=t_hint)
        if self.leaf_means is None:
            return t_entry, hit
        device = origins.device
        n = origins.shape[0]
        t_max = torch.as_tensor(t_max, dtype=torch.float32, device=device).expand(n)
        o = origins.to(torch.float32)
        d = dirs.to(torch.float32)
        norm2 = (d * d).sum(-1)
        step = 1e-3 * self.leaf_size / norm2.sqrt().clamp_min(_TINY_DIR)  # just inside the entered leaf
        inside = o + (t_entry + step)[:, None] * d
        pos, found = self.leaf_index(inside)
        mean = self.leaf_means.to(device)[pos]
        t_mean = ((mean - o) * d).sum(-1) / norm2.clamp_min(_TINY_DIR)
        # A leaf diagonal past the entry bounds the ray's segment in the leaf; a ray clipping the leaf's corner
        # leaves it sooner, but passes the mean's plane, its surface, within the diagonal.
        t_last = torch.minimum(t_entry + math.sqrt(3.0) * self.leaf_size / norm2.sqrt().clamp_min(_TINY_DIR), t_max)
        t = torch.minimum(torch.maximum(t_mean, t_entry), torch.maximum(t_last, t_entry))
        return torch.where(hit & found, t, t_entry), hit

    def _root_segments(
        self, origins: Tensor, dirs: Tensor, t_min: Tensor, t_max: Tensor
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """float32 origins [N, 3], dirs [N, 3] (zero components as +1e-30) and each ray's segment (t0 [N], t1 [N])
        inside the root's cube [origin, origin + 2**levels * leaf] and [t_min, t_max] (slab test); a ray whose
        segment has no positive length (t0 >= t1, or NaN) misses."""
        device = origins.device
        origin = self.origin.to(device)
        v = torch.tensor(self.leaf_size, dtype=torch.float32, device=device)
        o = origins.to(torch.float32)
        d = dirs.to(torch.float32)
        d = torch.where(d.abs() < _TINY_DIR, torch.full_like(d, _TINY_DIR), d)
        lo = origin + 0.0 * v
        hi = origin + float(2**self.levels) * v
        ta, tb = (lo - o) / d, (hi - o) / d
        t0 = torch.maximum(torch.minimum(ta, tb).amax(1), t_min)
        t1 = torch.minimum(torch.maximum(ta, tb).amin(1), t_max)
        return o, d, t0, t1

    def _root_frontier(self, o: Tensor, d: Tensor, t0: Tensor, t1: Tensor) -> tuple[_Rays, _Frontier]:
        """The rays' packed form and the frontier of (ray, root) pairs whose root segment has positive length."""
        device = o.device
        rays = _Rays(torch.cat([o, d], dim=1).T.contiguous(), _first_slot(d))
        ray = torch.nonzero(t0 < t1).squeeze(1)
        root = _Frontier(
            ray,
            torch.zeros(ray.numel(), dtype=torch.int32, device=device),
            torch.stack([t0.index_select(0, ray), t1.index_select(0, ray)]),
        )
        return rays, root

    def _trace_native(self, o: Tensor, d: Tensor, t0: Tensor, t1: Tensor) -> Tensor:
        """Entry [N] of each ray's first hit leaf (+inf where none) by the C kernel; CPU float32 inputs as
        :meth:`_root_segments` returns them."""
        lib = _trace_library()
        if isinstance(lib, str):
            raise RuntimeError(f"the octree tracing kernel is unavailable: {lib}")
        tables = self._tables if self.device.type == "cpu" else self._tables.to(torch.device("cpu"))
        o, d, t0, t1 = (x.contiguous() for x in (o, d, t0, t1))
        first_slot = _first_slot(d).contiguous()
        planes = (ctypes.c_void_p * self.levels)(*(p.data_ptr() for p in tables.planes))
        children = (ctypes.c_void_p * self.levels)(*(c.data_ptr() for c in tables.child_index))
        nodes = torch.tensor([p.shape[1] for p in tables.planes], dtype=torch.int64)
        t_hit = torch.empty_like(t0)
        lib.octree_first_hit(o.data_ptr(), d.data_ptr(), t0.data_ptr(), t1.data_ptr(), first_slot.data_ptr(),
                             planes, children, nodes.data_ptr(), self.levels, o.shape[0], t_hit.data_ptr(),
                             torch.get_num_threads())
        return t_hit

    def _first_hit_near(
        self, origins: Tensor, dirs: Tensor, t_min: Tensor, t_max: Tensor, t_hint: Tensor, chunk: int | None,
        use_kernel: bool | None,
    ) -> tuple[Tensor, Tensor]:
        """``first_hit`` searching up to ``t_hint`` plus a leaf diagonal first, then the misses in full.
        t_min, t_max, t_hint: [N] float32."""
        device = origins.device
        reach = self.leaf_size * math.sqrt(3.0) / dirs.to(torch.float32).norm(dim=1).clamp_min(_TINY_DIR)
        cap = t_hint.to(device=device, dtype=torch.float32) + reach
        cap = torch.where(torch.isfinite(cap), torch.minimum(cap, t_max), t_max)
        t, hit = self.first_hit(origins, dirs, t_min, cap, chunk=chunk, use_kernel=use_kernel)
        again = torch.nonzero(~hit & (cap < t_max)).squeeze(1)
        if again.numel():
            t_again, hit_again = self.first_hit(
                origins[again], dirs[again], t_min[again], t_max[again], chunk=chunk, use_kernel=use_kernel
            )
            t[again], hit[again] = t_again, hit_again
        return t, hit

    def _descend(
        self, root: _Frontier, rays: _Rays, tables: _TraversalTables, best: Tensor, chunk: int
    ) -> None:
        """Descend ``root`` (level-0 candidates) to the leaves, lowering ``best`` [N] to each ray's hit."""
        stack = [(0, root)]
        while stack:
            level, frontier = stack.pop()
            if frontier.ray.numel() > chunk:
                stack.extend((level, part) for part in frontier.halves())
                continue
            if frontier.ray.numel() == 0:
                continue
            planes, child_index = tables.planes[level], tables.child_index[level]
            child, bounds, valid = _split_segments(frontier, rays, planes, child_index)
            if level == self.levels - 1:
                nearest = torch.where(valid, bounds[:4], float("inf")).amin(0)
                best.scatter_reduce_(0, frontier.ray, nearest, "amin")
                continue
            stack.append((level + 1, _children(frontier, child, bounds, valid)))


_DEFAULT_CHUNK = 1 << 17  # candidates per expansion on CPU: tensors stay cache-sized
_DEFAULT_CHUNK_GPU = 1 << 21  # ~400 MB of temporaries; large enough to keep the GPU busy
_MIN_RAYS_PER_PART = 16384
_MAX_WORKERS = 4  # more Python threads contend for the GIL and oversubscribe the intra-op pool
_TINY_DIR = 1e-30  # stands in for zero direction components: no 0/0 in the slab tests


_TRACE_SOURCE = Path(__file__).with_name("octree_trace.c")
_c_ptr, _c_i64 = ctypes.c_void_p, ctypes.c_int64


@functools.cache
def _trace_library() -> ctypes.CDLL | str:
    """The loaded tracing kernel, or a one-line reason why there is none."""
    signature = [_c_ptr] * 8 + [ctypes.c_int, _c_i64, _c_ptr, ctypes.c_int]
    return native.load(_TRACE_SOURCE, {"octree_first_hit": signature})


def kernel_loaded() -> bool:
    """Whether this process has loaded the tracing kernel (nothing is built or loaded to answer)."""
    return native.loaded(_trace_library)


def kernel_available() -> bool:
    """Whether the C tracing kernel is built and loaded (building it on the first call)."""
    return not isinstance(_trace_library(), str)


def _first_slot(d: Tensor) -> Tensor:
    """[N] int32: the child slot ``x | y << 1 | z << 2`` a ray of direction ``d`` [N, 3] enters first (the
    octant opposite its direction)."""
    bits = torch.arange(3, dtype=torch.int32, device=d.device)
    return ((d < 0).int() << bits).sum(1, dtype=torch.int32)


@dataclass
class _Rays:
    """Ray data for traversal: origins and dirs as rows [6, N] and the child slot each ray enters first
    (the octant opposite its direction) [N] int32."""

    origin_dir: Tensor
    first_slot: Tensor


@dataclass
class _Frontier:
    """(ray, node) candidates at one level: ray index [M] int64, node index [M] int32 in that level's codes,
    and the ray's segment inside the node, ``bounds`` [2, M] = (t0, t1)."""

    ray: Tensor
    node: Tensor
    bounds: Tensor

    def slice(self, start: int, stop: int) -> _Frontier:
        return _Frontier(self.ray[start:stop], self.node[start:stop], self.bounds[:, start:stop])

    def halves(self) -> tuple[_Frontier, _Frontier]:
        m = self.ray.numel() // 2
        return self.slice(m, None), self.slice(0, m)


def _split_segments(
    f: _Frontier, rays: _Rays, planes: Tensor, child_index: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """Split each candidate's segment [t0, t1] at the node's mid-planes into 4 consecutive child segments.

    Returns for the 4 children: node index in the next level [4, M] int32 (-1 if unoccupied), segment
    bounds [5, M] (child k spans ``bounds[k]..bounds[k + 1]``) and valid [4, M]: the child is occupied and
    its segment has positive length.
    """
    m = f.ray.numel()
    device = f.ray.device
    od = rays.origin_dir.index_select(1, f.ray)
    tm = planes.index_select(1, f.node)
    tm -= od[:3]
    tm /= od[3:]  # [3, M] mid-plane crossing times
    x, y, z = tm.unbind(0)
    bounds = torch.empty(5, m, device=device)
    bounds[0], bounds[4] = f.bounds[0], f.bounds[1]
    lo_xy, hi_xy = torch.minimum(x, y), torch.maximum(x, y)
    torch.minimum(lo_xy, z, out=bounds[1])
    torch.maximum(lo_xy, torch.minimum(hi_xy, z), out=bounds[2])
    torch.maximum(hi_xy, z, out=bounds[3])
    torch.clamp(bounds[1:4], bounds[:1], bounds[4:], out=bounds[1:4])
    # Lookup keys node * 8 + slot of the 4 children. The ray starts in the octant opposite its direction,
    # then flips the earliest-crossed axis, then all but the latest, then all three. Ties (ordered z < y < x
    # here) give zero-length segments, so any consistent order does.
    xy, yz, xz = (x < y).view(torch.uint8), (y < z).view(torch.uint8), (x < z).view(torch.uint8)
    first_x, first_y = xy & xz, yz & ~xy
    last_x, last_y = ~(xy | xz) & 1, xy & ~yz
    key = torch.empty(4, m, dtype=torch.int32, device=device)
    torch.add(f.node * 8, rays.first_slot.index_select(0, f.ray), out=key[0])
    torch.bitwise_xor(key[0], first_x | (first_y << 1) | ((first_x | first_y) ^ 1) << 2, out=key[1])
    torch.bitwise_xor(key[0], 7, out=key[3])
    torch.bitwise_xor(key[3], last_x | (last_y << 1) | ((last_x | last_y) ^ 1) << 2, out=key[2])
    child = child_index.index_select(0, key.view(-1)).view(4, m)
    valid = (child >= 0) & (bounds[:4] < bounds[1:])
    return child, bounds, valid


def _children(f: _Frontier, child: Tensor, bounds: Tensor, valid: Tensor) -> _Frontier:
    """The next level's frontier: the valid children, in the order of ``valid.flatten()``."""
    m = f.ray.numel()
    idx = torch.nonzero(valid.view(-1)).squeeze(1)  # ascending: child 0 of all parents, then child 1...
    row_starts = torch.searchsorted(idx, torch.arange(m, 4 * m, m, device=idx.device)).tolist()
    parent = idx.clone()
    for start in row_starts:
        parent[start:] -= m  # parent = idx - k * m in row k, without an integer division
    flat = bounds.view(-1)
    segment = torch.empty(2, idx.numel(), device=flat.device)
    torch.index_select(flat, 0, idx, out=segment[0])
    torch.index_select(flat, 0, idx + m, out=segment[1])
    node = child.view(-1).index_select(0, idx)
    return _Frontier(f.ray.index_select(0, parent), node, segment)


def coverage_octree(
    points: Tensor,
    sigma: float,
    origins: Tensor,
    dirs: Tensor,
    t_min: Tensor,
    t_max: Tensor,
    scales: tuple[float, ...] = COVERAGE_LEAF_SCALES,
    tolerance: float = COVERAGE_MISS_TOLERANCE,
) -> tuple[SparseVoxelOctree, dict[str, float]]:
    """The octree with the smallest leaf ``s * sigma`` that the given rays slip through about as rarely as
    through the coarsest candidate (at most ``tolerance`` more of them miss every leaf).

    The paper sets the leaf to sigma, which assumes the prior samples its surface densely. A sparse point
    cloud (about one point per sigma^2 of surface, spread over a shell of several sigma by its noise) leaves
    gaps between occupied leaves at that size; a ray that slips through loses its importance samples. The
    rays should be training rays (points, rays: same frame; ``t_min``/``t_max`` [N]). Returns the octree and
    ``{str(s): fraction of the rays that hit no leaf}`` for every candidate tried.
    """
    misses: dict[str, float] = {}
    trees: dict[float, SparseVoxelOctree] = {}
    for scale in scales:
        trees[scale] = SparseVoxelOctree.from_points(points, sigma * scale, with_means=False)
        _, hit = trees[scale].first_hit(origins, dirs, t_min, t_max)
        misses[f"{scale:g}"] = float(1.0 - hit.float().mean())
    best = min(misses.values())
    chosen = trees[next(s for s in scales if misses[f"{s:g}"] <= best + tolerance)]
    chosen.leaf_means = chosen.means_of(points, reach=SURFACE_REACH)  # only the kept tree's
    return chosen, misses
