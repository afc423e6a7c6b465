"""voxnerf.model.colour_prior: pixels pooled per voxel and read back from the finest voxel that holds one, its
refusals, and its saved form."""

from __future__ import annotations

import pytest
import torch

from voxnerf.model.colour_prior import ColourPrior

RED, BLUE = [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]


def _prior() -> ColourPrior:
    # Two red pixels close together near the box's centre, one blue pixel far away in a corner.
    points = torch.tensor([[0.001, 0.001, 0.001], [0.002, 0.002, 0.002], [0.9, 0.9, 0.9]])
    return ColourPrior.pool(points, torch.tensor([RED, RED, BLUE]), finest=64, levels=4)


def test_a_point_beside_pixels_reads_their_colour_at_the_finest_level():
    colour, found = _prior().lookup(torch.tensor([[0.003, 0.003, 0.003], [0.89, 0.91, 0.9]]))
    assert found.all()
    assert torch.allclose(colour, torch.tensor([RED, BLUE]))


def test_a_point_with_no_pixel_near_it_reads_the_finest_level_that_has_one():
    prior = _prior()
    # 0.1 from the red pixels on each axis: outside their voxel on the grids of 64 and 32 cells (1/32 and 1/16
    # wide), inside it on the grid of 16 (1/8 wide, from 0 to 0.125).
    colour, found = prior.lookup(torch.tensor([[0.1, 0.1, 0.1]]))
    assert found.all() and torch.allclose(colour, torch.tensor([RED]))
    # 0.1 from the blue pixel: they share a voxel only on the coarsest grid (8 cells: 0.75 to 1).
    colour, found = prior.lookup(torch.tensor([[0.8, 0.8, 0.8]]))
    assert found.all() and torch.allclose(colour, torch.tensor([BLUE]))


def test_a_voxel_reads_the_mean_of_its_pixels():
    points = torch.tensor([[0.5, 0.5, 0.5], [0.501, 0.5, 0.5]])
    prior = ColourPrior.pool(points, torch.tensor([RED, BLUE]), finest=16, levels=2)
    colour, _ = prior.lookup(points[:1])
    assert torch.allclose(colour, torch.tensor([[0.5, 0.0, 0.5]]))


def test_where_no_level_holds_a_pixel_nothing_is_found():
    prior = ColourPrior.pool(torch.tensor([[0.9, 0.9, 0.9]]), torch.tensor([RED]), finest=8, levels=2)
    colour, found = prior.lookup(torch.tensor([[-0.9, -0.9, -0.9], [0.8, 0.8, 0.8]]))
    assert found.tolist() == [False, True]
    assert colour[0].tolist() == [0.0, 0.0, 0.0]


def test_points_outside_the_box_read_the_voxel_at_its_face():
    prior = ColourPrior.pool(torch.tensor([[0.99, 0.0, 0.0]]), torch.tensor([RED]), finest=8, levels=1)
    colour, found = prior.lookup(torch.tensor([[5.0, 0.0, 0.0]]))
    assert found.all() and torch.allclose(colour, torch.tensor([RED]))


@pytest.mark.parametrize(("points", "colours", "why"), [
    (torch.zeros(4, 2), torch.zeros(4, 3), "must both be \\[N, 3\\]"),
    (torch.zeros(4, 3), torch.zeros(3, 3), "must both be \\[N, 3\\]"),
    (torch.tensor([[float("nan"), 0.0, 0.0]]), torch.zeros(1, 3), "must be finite"),
    (torch.zeros(1, 3), torch.tensor([[float("inf"), 0.0, 0.0]]), "must be finite"),
])
def test_malformed_or_non_finite_pixels_are_refused(points, colours, why):
    with pytest.raises(ValueError, match=why):
        ColourPrior.pool(points, colours)


def test_more_levels_than_the_finest_grid_halves_into_are_refused():
    with pytest.raises(ValueError, match="do not fit"):
        ColourPrior.pool(torch.zeros(1, 3), torch.zeros(1, 3), finest=4, levels=4)


def test_the_saved_prior_reads_as_the_one_saved():
    prior = _prior()
    state = prior.state_dict()
    assert all(c.dtype == torch.float16 for c in state["colours"])
    again = ColourPrior.from_state_dict(state)
    queries = torch.rand(200, 3) * 2 - 1
    (c1, f1), (c2, f2) = prior.lookup(queries), again.lookup(queries)
    assert torch.equal(f1, f2) and torch.allclose(c1, c2, atol=1e-3)
    assert again.summary() == prior.summary() == {"pixels": 3, "levels": 4, "finest_cells": 64, "finest_voxels": 2}
