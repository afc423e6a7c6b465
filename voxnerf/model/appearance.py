"""Per-image appearance: a colour gain and bias per channel and training image (exposure, white balance).

The corrections are held at zero mean over the training images (log-gains and biases alike), so the field
learns the images' average exposure and white balance, not that of whichever image it fitted first. Exposure
drifts slowly along a scan's path, so a rendered view takes the corrections of its nearest training cameras
(:meth:`ImageAppearance.view_colour`, :mod:`voxnerf.cameras.neighbours`): learnt from the training images alone. The
half-image protocol of :func:`voxnerf.inference.metrics.half_image_pairs` scores every run beside the plain metrics.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from voxnerf.cameras.neighbours import blend, checked_cameras, nearest_cameras


class ImageAppearance(nn.Module):
    """``rgb' = rgb * exp(g[image]) + b[image]``, where ``g``, ``b`` are the parameters less their means over the
    images; identity at initialisation.

    ``log_gain``, ``bias``: [images, 3] parameters. ``forward(rgb [R, 3] in [0, 1], image [R] int64 training-image
    index) -> [R, 3]`` (not clamped: the colour loss sees the correction as it is).
    """

    def __init__(self, images: int, cameras: Tensor | None = None) -> None:
        super().__init__()
        if images < 1:
            raise ValueError(f"ImageAppearance needs at least one image, got {images}")
        self.log_gain = nn.Parameter(torch.zeros(images, 3))
        self.bias = nn.Parameter(torch.zeros(images, 3))
        # [images, 4, 4] the training cameras' poses (normalised units), where view_colour looks (identity poses
        # when not given: every view then takes the mean correction, the identity)
        self.register_buffer("cameras", checked_cameras(images, cameras, "ImageAppearance"))

    def corrections(self) -> tuple[Tensor, Tensor]:
        """(log-gains, biases) [images, 3] as applied: the parameters less their means over the images."""
        return self.log_gain - self.log_gain.mean(0), self.bias - self.bias.mean(0)

    def forward(self, rgb: Tensor, image: Tensor) -> Tensor:
        log_gain, bias = self.corrections()
        return rgb * torch.exp(log_gain[image]) + bias[image]

    def view_colour(self, rgb: Tensor, c2w: Tensor) -> Tensor:
        """``rgb`` [..., 3] of a view at pose ``c2w`` [4, 4] (normalised units) corrected as its nearest training
        cameras' images were (their log-gains and biases blended by inverse distance)."""
        log_gain, bias = (c.detach() for c in self.corrections())
        index, weight = nearest_cameras(self.cameras, c2w[None].to(rgb.device, torch.float32))
        gain = torch.exp(blend(log_gain, index, weight)[0]).to(rgb.dtype)
        return rgb * gain + blend(bias, index, weight)[0].to(rgb.dtype)

    def summary(self) -> dict:
        """Spread of the learnt corrections (for the report): gains' and biases' min and max over images."""
        log_gain, bias = (c.detach().cpu() for c in self.corrections())
        gain = torch.exp(log_gain)
        return {"images": int(gain.shape[0]), "gain": [float(gain.min()), float(gain.max())],
                "bias": [float(bias.min()), float(bias.max())]}
