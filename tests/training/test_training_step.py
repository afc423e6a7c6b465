"""One training step (voxnerf/training/step.py): the loss function, the batch, the divergence guard."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch

from voxnerf.cameras.pose_refinement import PoseRefinement
from voxnerf.config import TrainConfig
from voxnerf.errors import TrainingDiverged
from voxnerf.model.losses import PAPER_BETA, color_loss
from voxnerf.model.samplers import RayBundle
from voxnerf.model.voxnerf_model import Batch, Losses, VoxNeRFModel
from voxnerf.training.pixels import TrainingPixels
from voxnerf.training.step import TrainStep, divergence_guard, make_loss_fn


class StubModel(VoxNeRFModel):
    """The model's outputs and loss over a stub renderer: colour = mean of the starts, depth = the first start
    times ``depth_scale``."""

    def __init__(self, scale: float = 1.0, depth_scale: float = 1.0) -> None:
        self.transform = SimpleNamespace(scale=scale)
        self.depth_scale = depth_scale
        self.appearance = self.pose_refinement = None

    def render_samples(self, origins, dirs, starts, ends, background=None):
        rgb = starts.mean(-1, keepdim=True).expand(-1, 3)
        if background is not None:  # as if half transparent
            rgb = 0.5 * rgb + 0.5 * background
        return {"rgb": rgb, "depth": starts[:, 0] * self.depth_scale}

    def ray_bundle(self, origins, dirs):
        return SimpleNamespace(origins=origins, dirs=dirs)


def _inputs(rays: int, with_depth: bool, target_beta=None, depth_weight: float = 0.3):
    g = torch.Generator().manual_seed(0)
    starts = torch.rand(rays, 4, generator=g, requires_grad=True)
    target_t = torch.rand(rays, generator=g) if with_depth else None
    target_ok = torch.ones(rays, dtype=torch.bool) if with_depth else None
    return torch.zeros(rays, 3), torch.ones(rays, 3), starts, starts + 0.1, torch.rand(rays, 3, generator=g), \
        target_t, target_ok, target_beta, torch.zeros(rays, dtype=torch.int64), torch.tensor(depth_weight)


def test_without_depth_targets_the_loss_is_the_colour_loss():
    cfg = TrainConfig(max_iters=1)
    args = _inputs(16, with_depth=False)
    total, lc, ld, lreg, ldist, _ = make_loss_fn(StubModel(), cfg, 0.1, 0, 8)(Batch(*args))
    assert total is lc and float(ld) == 0 and float(lreg) == 0 and float(ldist) == 0
    expected = color_loss(args[2].mean(-1, keepdim=True).expand(-1, 3), args[4])
    assert float(lc.detach()) == pytest.approx(float(expected.detach()))


def test_depth_and_smoothness_terms_add_with_their_weights():
    cfg = TrainConfig(max_iters=1, lambda_depth=0.5, lambda_smooth=0.25)
    args = _inputs(16 + 2 * 4 * 4, with_depth=True, depth_weight=0.5)
    total, lc, ld, lreg, *_ = make_loss_fn(StubModel(), cfg, PAPER_BETA, 2 * 4 * 4, 4)(Batch(*args))
    assert float(total.detach()) == pytest.approx(float((lc + 0.5 * (ld + 0.25 * lreg)).detach()))
    ld, lreg = ld.detach(), lreg.detach()
    assert float(ld) > 0 and float(lreg) > 0


def test_the_depth_terms_do_not_depend_on_the_scene_unit():
    """Millimetres: beta 1000x, depths 1000x in scene units (normalised depths the same): the same loss."""
    cfg = TrainConfig(max_iters=1, lambda_smooth=0.5)
    args = _inputs(16 + 4 * 4, with_depth=True)
    metres = make_loss_fn(StubModel(scale=0.5), cfg, 0.1, 16, 4)(Batch(*args))
    millimetres = make_loss_fn(StubModel(scale=0.5e-3), cfg, 100.0, 16, 4)(Batch(*args))
    for a, b in zip(metres[:5], millimetres[:5], strict=True):
        assert float(a.detach()) == pytest.approx(float(b.detach()), rel=1e-5)


def test_a_per_ray_beta_of_one_is_the_run_beta_and_a_wider_beta_lowers_the_depth_term():
    cfg = TrainConfig(max_iters=1)
    rays = 64
    plain = make_loss_fn(StubModel(depth_scale=40.0), cfg, 0.1, 0, 8)(Batch(*_inputs(rays, True)))
    ones = make_loss_fn(StubModel(depth_scale=40.0), cfg, 0.1, 0, 8)(Batch(*_inputs(rays, True, torch.ones(rays))))
    wide_batch = Batch(*_inputs(rays, True, torch.full((rays,), 4.0)))
    wide = make_loss_fn(StubModel(depth_scale=40.0), cfg, 0.1, 0, 8)(wide_batch)
    assert float(ones[2].detach()) == pytest.approx(float(plain[2].detach()), rel=1e-6)
    # residuals far beyond beta are in the log branch, beta^2 (1/2 + ln(r / beta)), which grows with beta
    assert float(wide[2].detach()) > float(plain[2].detach())


def test_the_guard_returns_the_loss_and_raises_on_nan_with_the_terms():
    t = torch.tensor
    assert divergence_guard(Losses(t(0.5), t(0.4), t(0.1), t(0.0), t(0.0)), 3) == 0.5
    with pytest.raises(TrainingDiverged, match=r"loss became nan at iteration 7 \(colour 0.4, depth nan, "
                                               r"smoothness 0, distortion 0\)"):
        divergence_guard(Losses(t(math.nan), t(0.4), t(math.nan), t(0.0), t(0.0)), 7)


def _pixels(with_caches: bool) -> TrainingPixels:
    n, h, w = 2, 4, 5
    images = torch.arange(n * h * w * 3, dtype=torch.uint8).view(n, h, w, 3)
    c2w = torch.eye(4).expand(n, 4, 4).clone()
    intr = torch.tensor([[4.0, 4.0, 2.5, 2.0]] * n)
    pixels = TrainingPixels(images, c2w, intr)
    if with_caches:
        pixels.pseudo_t = torch.full((n, h, w), 2.0)
        pixels.pseudo_t[0, 0, 0] = math.nan
        pixels.depth_t = pixels.pseudo_t
        pixels.depth_beta_scale = torch.ones(n, h, w)
        pixels.hit_t, pixels.hit = torch.full((n, h, w), 1.5), torch.ones(n, h, w, dtype=torch.bool)
    return pixels


class StubOptimizer:
    def __init__(self, log: list) -> None:
        self.log = log

    def zero_grad(self, set_to_none: bool) -> None:
        self.log.append(("zero_grad", set_to_none))

    def step(self) -> None:
        self.log.append("step")


@pytest.mark.parametrize("with_caches", [False, True])
def test_a_batch_carries_rays_samples_and_targets(with_caches):
    seen = []

    def sampler(rays, training):
        seen.append((getattr(rays, "hit_t", None), training, torch.is_grad_enabled()))
        return torch.zeros(len(rays.origins), 4), torch.ones(len(rays.origins), 4)

    cfg = TrainConfig(max_iters=1, rays_per_batch=32, smooth_patches=1, patch_size=2)
    step = TrainStep(StubModel(), StubOptimizer([]), _pixels(with_caches), cfg, None, with_caches, sampler,
                     torch.Generator().manual_seed(0))
    batch = step.batch()
    assert isinstance(batch, Batch)
    rays = 32 + (4 if with_caches else 0)
    assert batch.origins.shape == batch.dirs.shape == (rays, 3) and batch.target_rgb.shape == (rays, 3)
    assert float(batch.target_rgb.max()) <= 1.0
    assert batch.image.shape == (rays,) and batch.image.dtype == torch.int64 and int(batch.image.max()) < 2
    assert float(batch.depth_weight) == pytest.approx(cfg.loss.lambda_depth)
    hit_t, training, grad = seen[0]
    assert training and not grad and (hit_t is not None) == with_caches
    if with_caches:
        assert torch.equal(batch.target_ok, torch.isfinite(batch.target_t))
        assert batch.target_beta.shape == (rays,)
    else:
        assert batch.target_t is None and batch.target_ok is None and batch.target_beta is None


@pytest.mark.parametrize("with_prior_rays", [False, True])
def test_a_random_training_background_is_one_colour_per_ray_and_step(with_prior_rays):
    def sampler(rays, training):
        return torch.zeros(len(rays.origins), 4), torch.ones(len(rays.origins), 4)

    cfg = TrainConfig(max_iters=1, rays_per_batch=32, train_background="random", prior_rays=4)
    bank = None
    if with_prior_rays:
        rays = RayBundle(torch.zeros(4, 3), torch.ones(4, 3), torch.zeros(4), torch.ones(4))
        bank = SimpleNamespace(draw=lambda n, gen: (rays, torch.ones(4), None))
    step = TrainStep(StubModel(), StubOptimizer([]), _pixels(True), cfg, None, True, sampler,
                     torch.Generator().manual_seed(0), prior_rays=bank)
    first, second = step.batch().background, step.batch().background
    assert first.shape == (len(step.batch().origins), 3) and first.shape[0] == 32 + 4 * with_prior_rays
    assert float(first.min()) >= 0.0 and float(first.max()) <= 1.0 and not torch.equal(first, second)
    fixed_cfg = TrainConfig(max_iters=1, rays_per_batch=32, train_background="fixed")
    fixed = TrainStep(StubModel(), StubOptimizer([]), _pixels(True), fixed_cfg,
                      None, True, sampler, torch.Generator().manual_seed(0))
    assert fixed.batch().background is None


def test_the_colour_loss_composites_over_the_batch_background():
    cfg = TrainConfig(max_iters=1)
    args = _inputs(16, with_depth=False)
    background = torch.rand(16, 3)
    _, lc, *_ = make_loss_fn(StubModel(), cfg, 0.1, 0, 8)(Batch(*args, None, background))
    expected = color_loss(0.5 * args[2].mean(-1, keepdim=True).expand(-1, 3) + 0.5 * background, args[4])
    assert float(lc.detach()) == pytest.approx(float(expected.detach()))


def test_losses_zero_the_gradients_then_backpropagate_and_apply_steps():
    log: list = []
    w = torch.tensor(2.0, requires_grad=True)

    def loss_fn(batch):
        return Losses(w * 3, w, w * 0, w * 0, w * 0)

    step = TrainStep(StubModel(), StubOptimizer(log), _pixels(False), TrainConfig(max_iters=1), loss_fn, False,
                     None, torch.Generator())
    losses = step.losses(Batch(*range(10)))
    assert float(losses.total.detach()) == 6.0 and float(w.grad) == 3.0 and log == [("zero_grad", True)]
    step.apply()
    assert log[-1] == "step"


@pytest.mark.parametrize("with_prior_rays", [False, True])
def test_every_nth_batch_carries_the_pose_corrections_with_their_gradient(with_prior_rays):
    def sampler(rays, training):
        return torch.zeros(len(rays.origins), 4), torch.ones(len(rays.origins), 4)

    model = StubModel()
    model.pose_refinement = PoseRefinement(2)
    bank = None
    if with_prior_rays:
        rays = RayBundle(torch.zeros(4, 3), torch.ones(4, 3), torch.zeros(4), torch.ones(4))
        bank = SimpleNamespace(draw=lambda n, gen: (rays, torch.ones(4), None))
    cfg = TrainConfig(max_iters=1, rays_per_batch=32, prior_rays=4, pose_refinement="so3xr3", pose_every=3)
    step = TrainStep(model, StubOptimizer([]), _pixels(True), cfg, None, True, sampler,
                     torch.Generator().manual_seed(0), prior_rays=bank)
    carried = [step.batch().pose_corrections for _ in range(7)]
    assert [c.requires_grad for c in carried] == [True, False, False, True, False, False, True]
    assert all(c.shape == (2, 6) for c in carried)
    assert step.graphs == 2
    without = TrainStep(StubModel(), StubOptimizer([]), _pixels(True), cfg, None, True, sampler,
                        torch.Generator().manual_seed(0))
    assert without.batch().pose_corrections is None and without.graphs == 1


def test_detached_pose_corrections_still_move_the_rays_but_leave_the_poses_without_a_gradient():
    seen = []
    model = StubModel()
    render = model.render_samples
    model.render_samples = lambda o, d, *a, **k: seen.append(o) or render(o, d, *a, **k)
    poses = PoseRefinement(2)
    with torch.no_grad():
        poses.delta[0, 3] = 0.2
    args = _inputs(8, with_depth=False)
    loss_fn = make_loss_fn(model, TrainConfig(max_iters=1, lambda_pose=0.5), 0.1, 0, 8)
    total, *_ = loss_fn(Batch(*args, None, None, poses.corrections().detach()))
    total.backward()
    assert poses.delta.grad is None
    torch.testing.assert_close(seen[0], args[0] + torch.tensor([0.1, 0.0, 0.0]))  # image 0, held at zero mean
    total, *_ = loss_fn(Batch(*args, None, None, poses.corrections()))
    total.backward()
    assert poses.delta.grad is not None and float(poses.delta.grad.abs().sum()) > 0


def test_the_loss_reports_each_image_ray_s_squared_colour_error_detached():
    args = _inputs(16 + 4 * 4, with_depth=True)
    losses = make_loss_fn(StubModel(), TrainConfig(max_iters=1), 0.1, 16, 4)(Batch(*args))
    expected = ((args[2].mean(-1, keepdim=True).expand(-1, 3) - args[4]) ** 2).mean(-1)
    assert torch.allclose(losses.ray_error, expected.detach()) and not losses.ray_error.requires_grad


def test_with_an_error_map_the_step_draws_where_the_last_steps_erred_and_folds_their_errors_in():
    def sampler(rays, training):
        return torch.zeros(len(rays.origins), 4), torch.ones(len(rays.origins), 4)

    hot = torch.tensor([1, 2, 3])  # (image, row, column) of the one pixel the field gets wrong
    w = torch.tensor(1.0, requires_grad=True)

    def loss_fn(batch):
        wrong = (batch.image == hot[0]) & (batch.target_rgb == _pixels(False).images[tuple(hot)].float() / 255).all(-1)
        return Losses(w * 1, w, w * 0, w * 0, w * 0, torch.where(wrong, 0.5, 1e-4))

    cfg = TrainConfig(max_iters=1, rays_per_batch=64, error_map=0.5)
    step = TrainStep(StubModel(), StubOptimizer([]), _pixels(False), cfg, loss_fn, False, sampler,
                     torch.Generator().manual_seed(0))
    for _ in range(4):
        step.losses(step.batch())
    assert bool(step.error_map.visited.all())  # one 8 x 8 cell per 4 x 5 image
    assert float(step.error_map.error[1]) > 100 * float(step.error_map.error[0])
    images = torch.cat([step.batch().image for _ in range(20)])
    assert float((images == 1).float().mean()) > 0.7  # half by error (nearly all image 1), half uniform
    plain = TrainStep(StubModel(), StubOptimizer([]), _pixels(False), TrainConfig(max_iters=1, rays_per_batch=64),
                      loss_fn, False, sampler, torch.Generator().manual_seed(0))
    assert plain.error_map is None


@pytest.mark.parametrize("with_prior_rays", [False, True])
def test_with_error_map_weights_the_drawn_rays_carry_their_importance_weights_and_the_rest_one(with_prior_rays):
    def sampler(rays, training):
        return torch.zeros(len(rays.origins), 4), torch.ones(len(rays.origins), 4)

    bank = None
    if with_prior_rays:
        rays = RayBundle(torch.zeros(4, 3), torch.ones(4, 3), torch.zeros(4), torch.ones(4))
        bank = SimpleNamespace(draw=lambda n, gen: (rays, torch.ones(4), None))
    cfg = TrainConfig(max_iters=1, rays_per_batch=32, smooth_patches=1, patch_size=2, prior_rays=4, error_map=0.5,
                      error_map_weights=True)
    step = TrainStep(StubModel(), StubOptimizer([]), _pixels(True), cfg, None, True, sampler,
                     torch.Generator().manual_seed(0), prior_rays=bank)
    step.error_map.update(torch.arange(40), torch.linspace(0.0, 1.0, 40))
    batch = step.batch()
    weight = batch.colour_weight
    assert weight.shape == (32 + 4 + 4 * with_prior_rays,) and not torch.equal(weight[:32], torch.ones(32))
    assert torch.equal(weight[32:36], torch.ones(4))  # the patch rays
    if with_prior_rays:
        assert torch.equal(weight[36:], torch.zeros(4))  # no colour term for prior rays without unseen flags
    unweighted = TrainStep(StubModel(), StubOptimizer([]), _pixels(True), cfg.updated(error_map_weights=False), None,
                           True, sampler, torch.Generator().manual_seed(0))
    assert unweighted.batch().colour_weight is None
