"""The colour the training images show near a point: their pixels pooled in voxels of several sizes.

A view that looks at a surface no training view saw leaves its ray nearly transparent there (the field was never
asked to be opaque at it), and the ray shows what lies behind its last sample. :class:`ColourPrior` gives such a
ray the colour the training images show nearest to where the prior says the surface is: the training pixels, each
placed at its depth target, pooled per voxel at ``levels`` sizes from ``finest`` cells across the canonical box
down to halves of it; a point reads the mean colour of the finest voxel around it that holds a pixel.

Tensor contract: points are float32 ``[N, 3]`` in normalised units (the canonical box ``[-1, 1]^3``; points
outside it read the voxel at the box's face); colours float32 ``[N, 3]`` in ``[0, 1]`` (sRGB, as the images).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

# Cells across the box of the finest level (2 / 256 normalised units: about 2 cm in a 5 m room) and the levels,
# each with half the cells of the one before, down to 8 cells across (a quarter of the box). A surface no training
# view saw reads one of the coarse levels; 4 cells across gained more on the tuning rooms' mean but lost 0.31 dB of
# extrapolation on one of them (docs/benchmarks.md, "What a view shows where no training view looked").
FINEST = 256
LEVELS = 6


def _cell_keys(points: Tensor, cells: int) -> Tensor:
    """int64 [N]: the flat index of the voxel around each point on a grid of ``cells`` per axis over the box."""
    index = ((points + 1.0) * (cells / 2.0)).floor().long().clamp(0, cells - 1)
    return (index[:, 0] * cells + index[:, 1]) * cells + index[:, 2]


@dataclass
class ColourPrior:
    """Mean training colour per occupied voxel, level by level from fine to coarse.

    ``cells`` [L] int: cells per axis of each level; ``keys[l]`` int64 [K_l] sorted voxel keys of level ``l``;
    ``colours[l]`` float32 [K_l, 3] their mean colours; ``pixels``: how many pixels were pooled.
    """

    cells: list[int]
    keys: list[Tensor]
    colours: list[Tensor]
    pixels: int

    @staticmethod
    def pool(points: Tensor, colours: Tensor, finest: int = FINEST, levels: int = LEVELS) -> ColourPrior:
        """The prior of pixels at ``points`` [N, 3] (normalised) with ``colours`` [N, 3] in [0, 1]. ValueError
        for mismatched shapes or a non-finite value (a pixel without a depth target is left out by the caller)."""
        if points.ndim != 2 or points.shape[1] != 3 or colours.shape != points.shape:
            raise ValueError(f"colour prior: points and colours must both be [N, 3], got {tuple(points.shape)} "
                             f"and {tuple(colours.shape)}")
        if not (bool(torch.isfinite(points).all()) and bool(torch.isfinite(colours).all())):
            raise ValueError("colour prior: points and colours must be finite")
        if finest < 2 or levels < 1 or finest >> (levels - 1) < 1:
            raise ValueError(f"colour prior: {levels} levels from {finest} cells do not fit")
        cells_per_level = [finest >> level for level in range(levels)]
        # The pixels are pooled once, on the finest grid; each coarser level pools the voxels of the one before
        # (a voxel's index halved is its parent's: floor(floor(y) / 2) = floor(y / 2)).
        key, inverse = torch.unique(_cell_keys(points.float(), finest), sorted=True, return_inverse=True)
        total = torch.zeros(len(key), 3, device=points.device).index_add_(0, inverse, colours.float())
        count = torch.zeros(len(key), device=points.device).index_add_(0, inverse, torch.ones_like(points[:, 0]))
        keys, means = [], []
        for level, cells in enumerate(cells_per_level):
            if level:
                finer = 2 * cells
                index = torch.stack([key // (finer * finer), key // finer % finer, key % finer], -1) // 2
                key, inverse = torch.unique((index[:, 0] * cells + index[:, 1]) * cells + index[:, 2], sorted=True,
                                            return_inverse=True)
                total = torch.zeros(len(key), 3, device=points.device).index_add_(0, inverse, total)
                count = torch.zeros(len(key), device=points.device).index_add_(0, inverse, count)
            keys.append(key)
            means.append(total / count[:, None])
        return ColourPrior(cells_per_level, keys, means, int(points.shape[0]))

    def lookup(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """(colours [N, 3], found [N] bool): the mean colour of the finest voxel around each point that holds a
        pixel; found is False (colour 0) only where no level holds one (an empty prior)."""
        colour = torch.zeros(points.shape[0], 3, device=points.device)
        found = torch.zeros(points.shape[0], dtype=torch.bool, device=points.device)
        for cells, keys, means in zip(self.cells, self.keys, self.colours, strict=True):
            if len(keys) == 0:
                continue
            key = _cell_keys(points.float(), cells)
            at = torch.searchsorted(keys, key).clamp_max(len(keys) - 1)
            new = (keys[at] == key) & ~found
            colour = torch.where(new[:, None], means[at], colour)
            found = found | new
        return colour, found

    def to(self, device: torch.device | str) -> ColourPrior:
        return ColourPrior(list(self.cells), [k.to(device) for k in self.keys], [c.to(device) for c in self.colours],
                           self.pixels)

    def state_dict(self) -> dict:
        """Colours saved as float16 (its step near 1 is 1/1024, finer than an 8-bit image's 1/255)."""
        return {"cells": list(self.cells), "keys": [k.cpu() for k in self.keys],
                "colours": [c.cpu().half() for c in self.colours], "pixels": self.pixels}

    @staticmethod
    def from_state_dict(state: dict) -> ColourPrior:
        return ColourPrior([int(c) for c in state["cells"]], [k.long() for k in state["keys"]],
                           [c.float() for c in state["colours"]], int(state["pixels"]))

    def summary(self) -> dict:
        return {"pixels": self.pixels, "levels": len(self.cells), "finest_cells": self.cells[0] if self.cells else 0,
                "finest_voxels": len(self.keys[0]) if self.keys else 0}
