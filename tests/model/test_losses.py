"""Losses: values, continuity at beta, robustness and the smoothness term."""

import torch

from voxnerf.model.losses import color_loss, depth_loss, depth_smoothness_loss, distortion_loss, log_huber


def test_log_huber_values_and_continuity_at_beta():
    beta = 0.1
    r = torch.tensor([0.0, 0.05, -0.05, 0.2, 1.0])
    expected = torch.tensor([0.0, 0.5 * 0.05**2, 0.5 * 0.05**2, beta**2 * (0.5 + torch.log(torch.tensor(2.0))),
                             beta**2 * (0.5 + torch.log(torch.tensor(10.0)))])
    torch.testing.assert_close(log_huber(r, beta), expected)
    eps = 1e-4
    below, at, above = log_huber(torch.tensor([beta - eps, beta, beta + eps], dtype=torch.float64), beta)
    assert abs(float(below - at)) < 2 * beta * eps and abs(float(above - at)) < 2 * beta * eps
    x = torch.tensor([beta - 1e-6, beta + 1e-6], dtype=torch.float64, requires_grad=True)
    log_huber(x, beta).sum().backward()
    torch.testing.assert_close(x.grad, torch.tensor([beta, beta], dtype=torch.float64), atol=1e-5, rtol=0)


def test_log_huber_is_finite_for_extreme_residuals():
    r = torch.tensor([1e-12, 1e-6, 1e6, 3e38, float("inf")], requires_grad=True)
    for beta in (1e-6, 0.1, 100.0):
        value = log_huber(r, beta)
        assert torch.isfinite(value).all()
        (g,) = torch.autograd.grad(value.sum(), r)
        assert torch.isfinite(g).all()
    # Outliers pull less than an L2 or L1 loss would: gradient beta^2 / r.
    x = torch.tensor([10.0], requires_grad=True)
    log_huber(x, 0.1).backward()
    torch.testing.assert_close(x.grad, torch.tensor([0.01 / 10.0]))


def test_depth_loss_ignores_invalid_rays():
    pred = torch.tensor([1.0, 2.0, 3.0])
    target = torch.tensor([1.0, float("nan"), 3.5])
    valid = torch.isfinite(target)
    value = depth_loss(pred, target, valid, beta=0.1)
    expected = log_huber(torch.tensor([0.0, 0.5]), 0.1).mean()
    torch.testing.assert_close(value, expected)
    assert float(depth_loss(pred, target, torch.zeros(3, dtype=torch.bool), 0.1)) == 0.0


def test_smoothness_zero_on_constant_and_positive_on_ramp():
    flat = torch.full((2, 8, 8), 3.0)
    mask = torch.ones(2, 8, 8, dtype=torch.bool)
    assert float(depth_smoothness_loss(flat, mask)) == 0.0
    ramp = torch.arange(8.0).view(1, 1, 8).expand(2, 8, 8)
    # Scale 1: |Gx| = 1; scale 2 (2x2 averages): 2; scale 3: 4; Gy = 0.
    torch.testing.assert_close(depth_smoothness_loss(ramp, mask, scales=3), torch.tensor(7.0))
    # A masked-out outlier does not count.
    spiky = flat.clone()
    spiky[0, 4, 4] = 1e6
    mask2 = mask.clone()
    mask2[0, 4, 4] = False
    assert float(depth_smoothness_loss(spiky, mask2, scales=1)) == 0.0


def test_color_loss_is_mse():
    a, b = torch.zeros(4, 3), torch.full((4, 3), 0.5)
    assert float(color_loss(a, b)) == 0.25


def _brute_distortion(w: torch.Tensor, s0: torch.Tensor, s1: torch.Tensor) -> torch.Tensor:
    near, far = s0[:, :1], s1[:, -1:]
    mid = ((0.5 * (s0 + s1)) - near) / (far - near)
    length = (s1 - s0) / (far - near)
    pair = (w[:, :, None] * w[:, None, :] * (mid[:, :, None] - mid[:, None, :]).abs()).sum((1, 2))
    return (pair + (w * w * length).sum(-1) / 3).mean()


def test_distortion_loss_equals_the_quadratic_pairwise_sum():
    g = torch.Generator().manual_seed(0)
    edges = torch.sort(torch.rand(5, 13, generator=g, dtype=torch.float64) * 4 + 1, dim=1).values
    s0, s1 = edges[:, :-1], edges[:, 1:]
    w = torch.rand(5, 12, generator=g, dtype=torch.float64)
    w = w / w.sum(-1, keepdim=True) * 0.9
    torch.testing.assert_close(distortion_loss(w, s0, s1), _brute_distortion(w, s0, s1))


def test_distortion_loss_prefers_one_thin_surface_and_ignores_the_scene_scale():
    s = torch.linspace(0, 1, 9, dtype=torch.float64)[None]
    s0, s1 = s[:, :-1], s[:, 1:]
    peaked = torch.zeros(1, 8, dtype=torch.float64)
    peaked[0, 3] = 1.0
    spread = torch.full((1, 8), 1 / 8, dtype=torch.float64)
    assert float(distortion_loss(peaked, s0, s1)) < float(distortion_loss(spread, s0, s1))
    torch.testing.assert_close(distortion_loss(spread, 1000 * s0 + 5, 1000 * s1 + 5), distortion_loss(spread, s0, s1))


def test_distortion_loss_is_finite_with_zero_length_rays_and_weights():
    s0 = torch.zeros(2, 4)
    w = torch.tensor([[0.0, 0.0, 0.0, 0.0], [0.5, 0.5, 0.0, 0.0]], requires_grad=True)
    value = distortion_loss(w, s0, s0)
    (grad,) = torch.autograd.grad(value, w)
    assert torch.isfinite(value) and torch.isfinite(grad).all()
