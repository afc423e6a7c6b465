"""Training pixels drawn by their running colour error (voxnerf/training/error_map.py)."""

from __future__ import annotations

import math

import pytest
import torch

from voxnerf.training.error_map import ALPHA, CELL, ErrorMap
from voxnerf.training.pixels import TrainingPixels


def _pixels(n: int = 2, h: int = 20, w: int = 28, sizes: list[list[int]] | None = None) -> TrainingPixels:
    return TrainingPixels(torch.zeros(n, h, w, 3, dtype=torch.uint8), torch.eye(4).expand(n, 4, 4).clone(),
                          torch.tensor([[5.0, 5.0, w / 2, h / 2]] * n),
                          sizes=None if sizes is None else torch.tensor(sizes))


def _flat(img: int, y: int, x: int, h: int = 20, w: int = 28) -> int:
    return (img * h + y) * w + x


@pytest.mark.parametrize("share", [0.0, 1.0, -0.1, math.nan])
def test_a_share_outside_zero_to_one_is_refused(share):
    with pytest.raises(ValueError, match="share"):
        ErrorMap(_pixels(), share)


def test_before_any_update_every_ray_is_drawn_uniformly():
    errors = ErrorMap(_pixels(), 0.5)
    a, weights = errors.draw(64, torch.Generator().manual_seed(3))
    b = _pixels().random_pixels(64, torch.Generator().manual_seed(3))
    assert torch.equal(a, b) and torch.equal(weights, torch.ones(64))


def test_a_cell_with_a_large_error_is_drawn_far_more_often_than_its_share_of_pixels():
    pixels = _pixels()
    errors = ErrorMap(pixels, 0.5)
    every = pixels.real_pixels()
    error = torch.full((len(every),), 1e-4)
    hot = errors.cell_of(every) == errors.cell_of(torch.tensor([_flat(1, 9, 17)]))[0]
    error[hot] = 1e-1
    errors.update(every, error)
    flat, _ = errors.draw(4000, torch.Generator().manual_seed(0))
    in_hot = (errors.cell_of(flat) == errors.cell_of(torch.tensor([_flat(1, 9, 17)]))[0]).float().mean()
    share_of_pixels = CELL * CELL / (2 * 20 * 28)
    assert float(in_hot) > 0.4  # half the rays by error, nearly all of those in the hot cell
    assert float(in_hot) > 5 * share_of_pixels


def test_draws_stay_inside_each_image_of_a_padded_grid():
    pixels = _pixels(sizes=[[20, 28], [11, 13]])
    errors = ErrorMap(pixels, 0.9)
    every = pixels.real_pixels()
    errors.update(every, torch.rand(len(every)))
    flat, _ = errors.draw(5000, torch.Generator().manual_seed(1))
    inside = pixels.inside().reshape(-1)
    assert bool(inside[flat].all())
    img, rem = flat // (20 * 28), flat % (20 * 28)
    second = img == 1
    assert int((rem[second] // 28).max()) == 10 and int((rem[second] % 28).max()) == 12  # the edge cells reached


def test_the_first_visit_sets_a_cell_and_later_ones_move_it_by_alpha():
    errors = ErrorMap(_pixels(), 0.5)
    flat = torch.tensor([_flat(0, 0, 0), _flat(0, 1, 1)])  # one cell
    cell = errors.cell_of(flat[:1])
    errors.update(flat, torch.tensor([0.2, 0.4]))
    assert float(errors.error[cell]) == pytest.approx(0.3)
    errors.update(flat[:1], torch.tensor([1.3]))
    assert float(errors.error[cell]) == pytest.approx(0.3 + ALPHA * 1.0)
    assert int(errors.visited.sum()) == 1


def test_a_non_finite_error_is_left_out():
    errors = ErrorMap(_pixels(), 0.5)
    flat = torch.tensor([_flat(0, 0, 0), _flat(0, 0, 1), _flat(1, 12, 20)])
    errors.update(flat, torch.tensor([math.nan, 0.5, math.inf]))
    assert bool(torch.isfinite(errors.error).all())
    assert float(errors.error[errors.cell_of(flat[:1])]) == pytest.approx(0.5)
    assert not bool(errors.visited[errors.cell_of(flat[2:])])


@pytest.mark.parametrize("sizes", [None, [[20, 28], [11, 13]]])
def test_the_importance_weights_give_back_the_uniform_mean_of_anything_over_the_pixels(sizes):
    """E[w f] over the mixture's draws is the uniform mean of f: each weight is the pixel's uniform probability over
    its probability under the mixture."""
    pixels = _pixels(sizes=sizes)
    errors = ErrorMap(pixels, 0.5)
    every = pixels.real_pixels()
    errors.update(every, torch.rand(len(every), generator=torch.Generator().manual_seed(2)) ** 4)
    f = torch.rand(2 * 20 * 28, generator=torch.Generator().manual_seed(5))
    flat, weights = errors.draw(200_000, torch.Generator().manual_seed(7))
    assert float((weights * f[flat]).mean()) == pytest.approx(float(f[every].mean()), rel=0.02)
    assert float(weights.mean()) == pytest.approx(1.0, rel=0.02)
    assert bool((weights > 0).all()) and float(weights.max()) <= 2.0 + 1e-5  # at most 1 / (1 - share)
