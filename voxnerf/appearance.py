"""Per-image appearance: a colour gain and bias per channel and training image (exposure, white balance).

Training-only: the field stays canonical and evaluation views render without it, so runs with and without it
are compared by the half-image protocol of :func:`voxnerf.metrics.half_image_scores`.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn


class ImageAppearance(nn.Module):
    """``rgb' = rgb * exp(log_gain[image]) + bias[image]``; identity at initialisation.

    ``log_gain``, ``bias``: [images, 3] parameters. ``forward(rgb [R, 3] in [0, 1], image [R] int64 training-image
    index) -> [R, 3]`` (not clamped: the colour loss sees the correction as it is).
    """

    def __init__(self, images: int) -> None:
        super().__init__()
        if images < 1:
            raise ValueError(f"ImageAppearance needs at least one image, got {images}")
        self.log_gain = nn.Parameter(torch.zeros(images, 3))
        self.bias = nn.Parameter(torch.zeros(images, 3))

    def forward(self, rgb: Tensor, image: Tensor) -> Tensor:
        return rgb * torch.exp(self.log_gain[image]) + self.bias[image]

    def summary(self) -> dict:
        """Spread of the learnt corrections (for the report): gains' and biases' min and max over images."""
        gain = torch.exp(self.log_gain.detach()).cpu()
        bias = self.bias.detach().cpu()
        return {"images": int(gain.shape[0]), "gain": [float(gain.min()), float(gain.max())],
                "bias": [float(bias.min()), float(bias.max())]}
