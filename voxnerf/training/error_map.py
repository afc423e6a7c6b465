"""Training pixels drawn where the field is still wrong (instant-ngp's error map).

The training images are cut into square cells of ``CELL`` pixels a side. Each cell keeps a running estimate of the
squared colour error of the training rays drawn in it (the mean over the channels, as the colour loss; the first
visit sets it, later ones move it by ``ALPHA``). A batch draws ``share`` of its rays from the cells in proportion to
their pixels times that estimate (a uniform pixel inside the cell) and the rest uniformly over every pixel, so no
pixel goes unvisited and a cell whose error is typical is drawn as often as a uniform batch would draw it. Each
drawn pixel also gets its importance weight (:meth:`ErrorMap.draw`); a run with ``error_map_weights`` weighs the
colour loss by them, so the draws lower the loss's variance and leave what it converges to as it was.

Tensor contract: flat pixel indices are int64 ``[R]`` into the [N, H, W] grid of :class:`TrainingPixels`; errors are
float32 ``[R]`` squared colour errors (colours in [0, 1]).
"""

from __future__ import annotations

import torch

from voxnerf.training.pixels import TrainingPixels

CELL = 8  # pixels per side of a cell
ALPHA = 0.2  # how far each later visit moves a cell's estimate


class ErrorMap:
    """The per-cell error estimates of one run's training images (on the training device)."""

    def __init__(self, pixels: TrainingPixels, share: float) -> None:
        if not 0.0 < share < 1.0:
            raise ValueError(f"error map: the share of rays drawn by error must lie in (0, 1), got {share}")
        self.pixels, self.share = pixels, share
        n, h, w = pixels.shape
        device = pixels.images.device
        self.rows, self.cols = -(-h // CELL), -(-w // CELL)
        sizes = pixels.sizes if pixels.sizes is not None else torch.tensor([[h, w]], device=device).expand(n, 2)
        top = torch.arange(self.rows, device=device) * CELL
        left = torch.arange(self.cols, device=device) * CELL
        # [N * rows * cols]: each cell's height and width inside its image (0 where it lies in the padding)
        shape = (n, self.rows, self.cols)
        self.cell_h = (sizes[:, 0, None] - top[None]).clamp(0, CELL)[:, :, None].expand(shape).reshape(-1)
        self.cell_w = (sizes[:, 1, None] - left[None]).clamp(0, CELL)[:, None, :].expand(shape).reshape(-1)
        self.area = (self.cell_h * self.cell_w).float()
        self.error = torch.zeros(n * self.rows * self.cols, device=device)
        self.visited = torch.zeros(n * self.rows * self.cols, dtype=torch.bool, device=device)
        self.updated = False  # whether update ran (kept on the host: draw reads no device value)

    def cell_of(self, flat: torch.Tensor) -> torch.Tensor:
        """int64 [R]: the cell of each flat pixel index."""
        img, py, px = self.pixels.index_of(flat)
        return (img * self.rows + py // CELL) * self.cols + px // CELL

    def draw(self, count: int, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        """(flat [count] int64, weights [count] float32): pixel indices, ``share`` of them by error (all uniform
        before any visit) and the rest uniform; and each pixel's importance weight, its probability under uniform
        draws over its probability under this mixture (weighing the colour loss by them keeps its expectation the
        uniform batch's: the draws then only lower the variance)."""
        by_error = int(round(self.share * count)) if self.updated else 0
        uniform = self.pixels.random_pixels(count - by_error, gen)
        if by_error == 0:
            return uniform, torch.ones(count, device=uniform.device)
        # A cell not visited yet counts as the largest error seen, so it is explored.
        estimate = torch.where(self.visited, self.error, self.error.max()) + 1e-12
        cell = torch.multinomial(self.area * estimate, by_error, replacement=True, generator=gen)
        n, h, w = self.pixels.shape
        img, rest = cell // (self.rows * self.cols), cell % (self.rows * self.cols)
        row, col = rest // self.cols, rest % self.cols
        u = torch.rand(by_error, 2, generator=gen, device=gen.device)
        py = row * CELL + (u[:, 0] * self.cell_h[cell]).long()
        px = col * CELL + (u[:, 1] * self.cell_w[cell]).long()
        flat = torch.cat([uniform, img * (h * w) + py * w + px])
        by_error_share = by_error / count
        pixel_by_error = estimate[self.cell_of(flat)] / (self.area * estimate).sum()  # a pixel's chance per draw
        probability = (1.0 - by_error_share) / self.pixels.pixel_count + by_error_share * pixel_by_error
        return flat, (1.0 / self.pixels.pixel_count) / probability

    def update(self, flat: torch.Tensor, error: torch.Tensor) -> None:
        """Fold the squared errors [R] of the rays through pixels ``flat`` [R] into their cells' estimates; a
        non-finite error is left out (the divergence guard reports it). Masks, not a boolean index, so nothing waits
        for the device."""
        ok = torch.isfinite(error)
        cell = self.cell_of(flat)
        total = torch.zeros_like(self.error).index_add_(0, cell, torch.where(ok, error.float(), 0.0))
        count = torch.zeros_like(self.error).index_add_(0, cell, ok.float())
        seen = count > 0
        mean = total / count.clamp_min(1.0)
        moved = torch.where(self.visited, self.error + ALPHA * (mean - self.error), mean)
        self.error = torch.where(seen, moved, self.error)
        self.visited = self.visited | seen
        self.updated = True
