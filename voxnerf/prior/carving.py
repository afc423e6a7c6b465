"""Free-space carving of the sampler's octree by measured depth.

A prior (a noisy point cloud, a smoothed mesh) has leaves where there is nothing: outliers, and noise standing off
a surface, most often beyond an object's silhouette. A ray cast to its first occupied leaf stops there, its
importance samples gather around empty space, and the surface it sees lies further on, reached only by the sparse
samples. A training pixel with a depth measurement says its ray crosses empty space up to shortly before the
measured depth: a leaf that at least ``min_votes`` such rays cross, and that holds no measured surface point, is
removed. Leaves no measurement reaches (unseen space) stay as the prior has them.

All positions and distances are in the octree's units (the normalised frame in training).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from voxnerf.prior.octree import SparseVoxelOctree, morton_decode

MIN_FREE_VOTES = 2  # distinct rays that must cross a leaf before it is carved
MAX_LEAVES_PER_RAY = 32  # leaves one ray votes for at most (a ray crossing more leaves them unvoted)
NUDGE_LEAVES = 1e-3  # how far past a leaf's entry (and exit) a ray is stepped, in leaves
_TINY = 1e-30


@dataclass(frozen=True)
class Carving:
    """The carved octree and what was done: leaves before, leaves removed, leaves holding a measured surface
    point, and the rays that voted on free space."""

    octree: SparseVoxelOctree
    leaves: int
    carved: int
    surface_leaves: int
    rays: int

    def describe(self) -> str:
        return (f"carved {self.carved} of {self.leaves} leaves ({self.carved / max(self.leaves, 1):.1%}) that at "
                f"least {MIN_FREE_VOTES} of {self.rays} measured rays cross and no measured surface point lies in "
                f"({self.surface_leaves} leaves hold one)")


def carve_free_space(octree: SparseVoxelOctree, surface_points: Tensor, origins: Tensor, dirs: Tensor,
                     free_until: Tensor, min_votes: int = MIN_FREE_VOTES) -> Carving:
    """Remove the leaves that measured rays show empty (:func:`empty_leaves`, then :func:`remove_empty`).

    Returns:
        :class:`Carving`; its octree is ``octree`` itself when nothing is carved, or when carving would remove
        every leaf.
    """
    empty, surface_leaves = empty_leaves(octree, surface_points, origins, dirs, free_until, min_votes)
    return remove_empty(octree, empty, surface_leaves, int(origins.shape[0]))


def empty_leaves(octree: SparseVoxelOctree, surface_points: Tensor, origins: Tensor, dirs: Tensor,
                 free_until: Tensor, min_votes: int = MIN_FREE_VOTES) -> tuple[Tensor, int]:
    """The leaves that measured rays show empty -> (bool [L], order of ``codes[-1]``; how many leaves hold a
    surface point).

    Args:
        surface_points: [P, 3] float32, measured surface points (a depth map's pixels back-projected); the leaves
            holding one are never carved.
        origins, dirs: [R, 3] float32, the measured rays (``dirs`` unit length).
        free_until: [R] float32, ray distance up to which each ray crossed empty space (its measured depth less a
            margin for the measurement's noise and the leaf size); non-finite or non-positive: the ray votes
            nothing. A ray votes for every occupied leaf it enters before then, once each.
        min_votes: distinct rays that must cross a leaf for it to be carved.
    """
    if origins.shape != dirs.shape or origins.dim() != 2 or origins.shape[1] != 3:
        raise ValueError(f"origins and dirs must both be [R, 3], got {tuple(origins.shape)}, {tuple(dirs.shape)}")
    if free_until.shape != origins.shape[:1]:
        raise ValueError(f"free_until must be [R] = [{origins.shape[0]}], got {tuple(free_until.shape)}")
    surface = _leaves_holding(octree, surface_points)
    votes = _free_votes(octree, origins, dirs, free_until)
    return (votes >= min_votes) & ~surface, int(surface.sum())


def remove_empty(octree: SparseVoxelOctree, empty: Tensor, surface_leaves: int, rays: int) -> Carving:
    """The :class:`Carving` of ``octree`` that removes the leaves ``empty`` (bool [L], order of ``codes[-1]``),
    unless that would remove every leaf; ``surface_leaves`` and ``rays`` are what the vote saw."""
    n_leaves = octree.codes[-1].numel()
    if empty.shape != (n_leaves,) or empty.dtype != torch.bool:
        raise ValueError(f"empty must be a bool tensor of shape ({n_leaves},), got {empty.dtype} {tuple(empty.shape)}")
    carved = int(empty.sum())
    tree = octree if carved in (0, n_leaves) else octree.keep_leaves(~empty)
    return Carving(tree, n_leaves, carved if tree is not octree else 0, surface_leaves, rays)


def _leaves_holding(octree: SparseVoxelOctree, points: Tensor) -> Tensor:
    """bool [L]: whether any of ``points`` [P, 3] (non-finite rows ignored) falls in each occupied leaf."""
    held = torch.zeros(octree.codes[-1].numel(), dtype=torch.bool, device=octree.device)
    points = points[torch.isfinite(points).all(dim=1)]
    if points.numel():
        pos, found = octree.leaf_index(points)
        held[pos[found]] = True
    return held


def _free_votes(octree: SparseVoxelOctree, origins: Tensor, dirs: Tensor, free_until: Tensor) -> Tensor:
    """int64 [L]: how many of the rays cross each occupied leaf before their ``free_until``. Each ray is traced
    from leaf to leaf (:meth:`SparseVoxelOctree.first_hit`, then on from the hit leaf's exit), at most
    :data:`MAX_LEAVES_PER_RAY` leaves: the cost follows the leaves crossed, not the leaf size."""
    n_leaves = octree.codes[-1].numel()
    votes = torch.zeros(n_leaves, dtype=torch.int64, device=octree.device)
    until = torch.nan_to_num(free_until.float(), nan=0.0, posinf=0.0, neginf=0.0)
    ray = (until > 0).nonzero().squeeze(1)
    t_min = torch.zeros(len(ray), device=until.device)
    nudge = NUDGE_LEAVES * octree.leaf_size
    for _ in range(MAX_LEAVES_PER_RAY):
        if not len(ray):
            break
        o, d = origins[ray], dirs[ray]
        t, hit = octree.first_hit(o, d, t_min, until[ray])
        ray, o, d, t = ray[hit], o[hit], d[hit], t[hit]
        pos, found = octree.leaf_index(o + (t + nudge)[:, None] * d)
        at_entry, found_at_entry = octree.leaf_index(o + t[:, None] * d)  # a leaf the ray clips by < nudge
        pos, found = torch.where(found, pos, at_entry), found | found_at_entry
        votes.index_add_(0, pos[found], torch.ones_like(pos[found]))
        exit_t = torch.where(found, _leaf_exit(octree, pos, o, d), t)
        t_min = torch.maximum(exit_t, t + nudge) + nudge
    return votes


def _leaf_exit(octree: SparseVoxelOctree, pos: Tensor, origins: Tensor, dirs: Tensor) -> Tensor:
    """[R] ray distance where each ray leaves the occupied leaf ``pos`` [R] (index into ``codes[-1]``)."""
    lo = octree.origin + morton_decode(octree.codes[-1][pos]).float() * octree.leaf_size
    far_side = torch.where(dirs > 0, lo + octree.leaf_size, lo)
    moving = dirs.abs() > _TINY  # an axis the ray does not move along bounds nothing
    exits = torch.where(moving, (far_side - origins) / torch.where(moving, dirs, 1.0), math.inf)
    return exits.clamp_min(0.0).amin(dim=1)
