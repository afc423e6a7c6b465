"""Volume rendering identities and stability."""

import math

import torch

from voxnerf.model.volume_rendering import render_weights, volume_render


def _intervals(r: int, s: int, length: float = 1.0):
    edges = torch.linspace(0.5, 0.5 + length, s + 1).expand(r, s + 1)
    return edges[:, :-1].contiguous(), edges[:, 1:].contiguous()


def test_weights_sum_to_opacity_closed_form():
    torch.manual_seed(0)
    starts, ends = _intervals(64, 32)
    density = torch.rand(64, 32) * 5
    weights, trans = render_weights(density, starts, ends)
    tau = (density * (ends - starts)).sum(-1)
    torch.testing.assert_close(weights.sum(-1), 1 - torch.exp(-tau), rtol=1e-5, atol=1e-6)
    assert torch.all(trans[:, 0] == 1)
    assert torch.all((weights >= 0) & (weights <= 1))


def test_constant_colour_and_depth_of_opaque_wall():
    starts, ends = _intervals(4, 100, length=2.0)
    density = torch.zeros(4, 100)
    density[:, 50:] = 1e6  # a wall at t = 0.5 + 1.0
    rgb = torch.tensor([0.2, 0.4, 0.6]).expand(4, 100, 3)
    out = volume_render(density, rgb, starts, ends, torch.tensor([1.0, 1.0, 1.0]))
    torch.testing.assert_close(out["rgb"], torch.tensor([[0.2, 0.4, 0.6]] * 4))
    torch.testing.assert_close(out["opacity"], torch.ones(4))
    torch.testing.assert_close(out["depth"], torch.full((4,), 1.51), atol=1e-3, rtol=0)


def test_empty_ray_shows_background_at_far():
    starts, ends = _intervals(2, 8)
    out = volume_render(torch.zeros(2, 8), torch.rand(2, 8, 3), starts, ends, torch.tensor([0.1, 0.2, 0.3]))
    torch.testing.assert_close(out["rgb"], torch.tensor([[0.1, 0.2, 0.3]] * 2))
    torch.testing.assert_close(out["depth"], ends[:, -1])
    assert torch.all(out["opacity"] == 0)


def test_stiff_inputs_stay_finite_with_finite_gradients():
    starts = torch.tensor([[0.0, 1e-9, 2e-9, 1.0, 1e6]])
    ends = torch.tensor([[1e-9, 2e-9, 1.0, 1e6, 2e6]])
    for value in (0.0, 1e-12, 1.0, 1e10, math.inf):
        density = torch.full((1, 5), value, requires_grad=True)
        out = volume_render(density, torch.rand(1, 5, 3), starts, ends)
        (out["rgb"].sum() + out["depth"].sum() + out["opacity"].sum()).backward()
        for key in ("rgb", "depth", "opacity"):
            assert torch.isfinite(out[key]).all(), (value, key)
        assert torch.isfinite(density.grad).all(), value
        assert 0 <= float(out["opacity"].detach()) <= 1


def test_transmittance_matches_product_form_on_mild_input():
    starts, ends = _intervals(3, 16)
    density = torch.rand(3, 16)
    weights, trans = render_weights(density, starts, ends)
    alpha = 1 - torch.exp(-density * (ends - starts))
    prod = torch.cumprod(torch.cat([torch.ones(3, 1), 1 - alpha[:, :-1]], -1), -1)
    torch.testing.assert_close(trans, prod, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(weights, prod * alpha, rtol=1e-5, atol=1e-6)
