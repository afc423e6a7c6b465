"""How noisy an image is: the standard deviation of its pixel noise, estimated from the image alone.

Immerkaer's filter (Fast Noise Variance Estimation, 1996) is the difference of two discrete Laplacians, ``K =
[[1, -2, 1], [-2, 4, -2], [1, -2, 1]]``: it cancels any image that is locally planar, and white noise of standard
deviation sigma leaves a response of standard deviation 6 sigma (the root of the sum of the squared weights).
Edges and texture answer it too; taking the median absolute deviation of the response instead of its mean
counts only the bulk of the pixels, the smooth ones, so a textured image does not pass for a noisy one. Where
texture covers most pixels (a tiny image of a patterned scene) the texture itself reads as some noise.
"""

from __future__ import annotations

import numpy as np

FILTER_GAIN = 6.0  # std of the filter's response to unit white noise: sqrt(1 + 4 + 1 + 4 + 16 + 4 + 1 + 4 + 1)
MAD_TO_STD = 1.4826  # median absolute deviation -> standard deviation, for Gaussian data


def noise_sigma(image: np.ndarray) -> float:
    """uint8 [H, W, 3] (or [H, W]) image -> the noise standard deviation of its grey image, in [0, 1] units.

    Images smaller than 3 x 3 have no response to measure: 0.
    """
    grey = image.astype(np.float32) / 255.0
    if grey.ndim == 3:
        grey = grey.mean(-1)
    h, w = grey.shape
    if h < 3 or w < 3:
        return 0.0
    corner = grey[:-2, :-2] + grey[:-2, 2:] + grey[2:, :-2] + grey[2:, 2:]
    edge = grey[:-2, 1:-1] + grey[2:, 1:-1] + grey[1:-1, :-2] + grey[1:-1, 2:]
    response = corner - 2.0 * edge + 4.0 * grey[1:-1, 1:-1]
    mad = np.median(np.abs(response - np.median(response)))
    return float(MAD_TO_STD * mad / FILTER_GAIN)


def images_noise_sigma(images: list[np.ndarray]) -> float:
    """The median of :func:`noise_sigma` over ``images`` (0 for none): one figure for a set of photographs."""
    return float(np.median([noise_sigma(image) for image in images])) if images else 0.0
