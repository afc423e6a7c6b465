"""The noise of an image measured from the image alone (voxnerf/data/image_noise.py)."""

from __future__ import annotations

import numpy as np
import pytest

from voxnerf.data.image_noise import images_noise_sigma, noise_sigma


def _plane(h=120, w=160):
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    return np.repeat((0.2 + 0.5 * x / w + 0.2 * y / h)[..., None], 3, axis=-1)  # a smooth ramp, [0, 1]


def _uint8(image):
    return np.clip(np.round(image * 255.0), 0, 255).astype(np.uint8)


@pytest.mark.parametrize("sigma", [2.0, 5.0, 10.0])
def test_white_noise_on_a_smooth_image_is_measured(sigma):
    rng = np.random.default_rng(0)
    grey_noise = rng.normal(0.0, sigma / 255.0, (120, 160, 1))  # the same noise in every channel: grey noise sigma
    assert noise_sigma(_uint8(_plane() + grey_noise)) * 255.0 == pytest.approx(sigma, rel=0.1)


def test_a_clean_image_measures_the_rounding_to_8_bits_alone():
    assert noise_sigma(_uint8(_plane())) * 255.0 < 0.5


def test_texture_and_edges_do_not_pass_for_noise():
    rng = np.random.default_rng(1)
    image = _plane()
    image[:, 80:] *= 0.4  # a hard edge
    image[20:60, 20:60] = np.where((np.indices((40, 40)).sum(0) // 8) % 2, 0.9, 0.1)[..., None]  # a checkerboard
    clean = noise_sigma(_uint8(image)) * 255.0
    noisy = noise_sigma(_uint8(image + rng.normal(0.0, 5.0 / 255.0, image.shape[:2] + (1,)))) * 255.0
    assert clean < 0.5 and noisy == pytest.approx(5.0, rel=0.15)


def test_tiny_images_and_no_images_measure_nothing():
    assert noise_sigma(np.zeros((2, 9, 3), np.uint8)) == 0.0
    assert images_noise_sigma([]) == 0.0


def test_a_set_of_images_is_summed_up_by_its_median():
    rng = np.random.default_rng(2)
    images = [_uint8(_plane() + rng.normal(0.0, s / 255.0, (120, 160, 1))) for s in (1.0, 4.0, 40.0)]
    assert images_noise_sigma(images) * 255.0 == pytest.approx(4.0, rel=0.15)
    assert noise_sigma(images[0][..., 0]) == pytest.approx(noise_sigma(images[0]))  # grey in, the same answer
