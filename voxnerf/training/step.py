"""One optimisation step: the batch, the model's loss with the run's settings (what ``torch.compile`` compiles),
the divergence guard and the optimiser update."""

from __future__ import annotations

import math
from collections.abc import Callable

import torch

from voxnerf.config import TrainConfig
from voxnerf.errors import TrainingDiverged
from voxnerf.model.voxnerf_model import Batch, Losses, LossSettings, VoxNeRFModel
from voxnerf.training.error_map import ErrorMap
from voxnerf.training.pixels import TrainingPixels, sample_batch
from voxnerf.training.prior_rays import PriorRayBank

DEPTH_BETA_PER_SIGMA = 5.0  # default beta = 5 sigma: the paper's 0.1 m for its 2 cm priors, in any unit

LossFn = Callable[[Batch], Losses]


def make_loss_fn(model: VoxNeRFModel, cfg: TrainConfig, beta: float, n_patch_rays: int, patch: int,
                 n_prior_rays: int = 0) -> LossFn:
    """The model's loss (:meth:`VoxNeRFModel.loss`) with this run's settings, as one function of a batch of
    fixed-shape tensors (what ``torch.compile`` compiles). ``beta`` is in scene units; the batch's last
    ``n_prior_rays`` rays are prior rays, the ``n_patch_rays`` before them smoothness patches of side ``patch``."""
    settings = LossSettings.of(cfg, beta, model.transform.scale, n_patch_rays, patch, n_prior_rays)

    def loss_fn(batch: Batch) -> Losses:
        return model.loss(batch, settings)

    return loss_fn


def divergence_guard(losses: Losses, iteration: int) -> float:
    """The total loss as a float (the step's one host sync); raises TrainingDiverged if it is NaN or inf."""
    loss = float(losses.total.detach())
    if not math.isfinite(loss):
        raise TrainingDiverged(
            f"loss became {loss} at iteration {iteration} (colour {float(losses.colour.detach()):.4g}, "
            f"depth {float(losses.depth.detach()):.4g}, smoothness {float(losses.smoothness.detach()):.4g}, "
            f"distortion {float(losses.distortion.detach()):.4g})"
        )
    return loss


def pixel_offsets(cfg: TrainConfig, n: int, gen: torch.Generator) -> torch.Tensor | None:
    """float32 [n, 2] a uniform random point of each of ``n`` rays' pixels (row, column; pixels from its centre)
    drawn from ``gen`` when ``pixel_jitter`` is on, else None (the rays pass through the centres)."""
    if not cfg.loss.pixel_jitter:
        return None
    return torch.rand(n, 2, generator=gen, device=gen.device) - 0.5


class TrainStep:
    """The step, split where the divergence guard looks: ``batch()``, ``losses(batch)`` (forward and
    backward) and ``apply()`` (the optimiser update, only after the guard passed). With pose refinement, every
    ``cfg.corrections.pose_every``-th batch carries the corrections with their gradient and the others carry them
    detached (those steps move the rays as the poses stand and leave the poses alone)."""

    def __init__(self, model: VoxNeRFModel, optimizer: torch.optim.Optimizer, pixels: TrainingPixels,
                 cfg: TrainConfig, loss_fn: LossFn, use_patches: bool, sampler, gen: torch.Generator,
                 prior_rays: PriorRayBank | None = None) -> None:
        self.model, self.optimizer, self.pixels, self.cfg = model, optimizer, pixels, cfg
        self.prior_rays = prior_rays
        self.mean_colour = pixels.mean_colour() if prior_rays is not None else None
        self.loss_fn, self.use_patches, self.sampler, self.gen = loss_fn, use_patches, sampler, gen
        # lambda_d now, as a tensor the schedule sets
        self.depth_weight = torch.tensor(float(cfg.loss.lambda_depth), device=pixels.images.device)
        self.batches = 0  # batches drawn by this step (which ones refine the poses)
        share = float(cfg.loss.error_map)
        self.error_map = ErrorMap(pixels, share) if share > 0 else None
        self._drawn: torch.Tensor | None = None  # the last batch's pixels drawn by the error map (flat [R])

    def batch(self) -> Batch:
        pixels = self.pixels
        flat = colour_weight = None
        if self.error_map is not None:
            flat, weights = self.error_map.draw(int(self.cfg.schedule.rays_per_batch), self.gen)
            self._drawn = flat
        img, py, px = sample_batch(pixels, self.cfg, self.use_patches, self.gen, flat)
        if flat is not None and self.cfg.loss.error_map_weights:  # the patch rays after them weigh 1
            colour_weight = torch.cat([weights, weights.new_ones(len(img) - len(flat))])
        rays = self.model.ray_bundle(*pixels.rays(img, py, px, pixel_offsets(self.cfg, len(img), self.gen)))
        if pixels.hit_t is not None:
            rays.hit_t, rays.hit = pixels.hit_t[img, py, px], pixels.hit[img, py, px]
        with torch.no_grad():
            starts, ends = self.sampler(rays, True)
        target_rgb = pixels.images[img, py, px].float() / 255.0
        target_t = target_ok = target_beta = None
        if pixels.depth_t is not None:
            target_t = pixels.depth_t[img, py, px]
            target_ok = torch.isfinite(target_t)
        if pixels.depth_beta_scale is not None:
            target_beta = pixels.depth_beta_scale[img, py, px]
        batch = Batch(rays.origins, rays.dirs, starts, ends, target_rgb, target_t, target_ok, target_beta, img,
                      self.depth_weight, colour_weight, background=self._random_background(len(img)),
                      pose_corrections=self._pose_corrections())
        self.batches += 1
        return batch if self.prior_rays is None or target_t is None else self._with_prior_rays(batch)

    @property
    def graphs(self) -> int:
        """How many forms the batches take for a compiled loss function: two where only every
        ``cfg.corrections.pose_every``-th one carries the pose corrections with their gradient, else one."""
        return 2 if self.model.pose_refinement is not None and self.cfg.corrections.pose_every > 1 else 1

    def _pose_corrections(self) -> torch.Tensor | None:
        """The model's pose corrections [images, 6] for this batch: with their gradient on every
        ``cfg.corrections.pose_every``-th batch, detached on the others; None without pose refinement."""
        poses = self.model.pose_refinement
        if poses is None:
            return None
        corrections = poses.corrections()
        return corrections if self.batches % self.cfg.corrections.pose_every == 0 else corrections.detach()

    def _random_background(self, n: int) -> torch.Tensor | None:
        """[n, 3] a uniform random colour behind each ray when ``train_background`` is 'random' (else None: the
        model's background). A ray can then match its pixel only by turning opaque, so the field cannot make a
        seen surface translucent and let the background tint it."""
        if self.cfg.loss.train_background != "random":
            return None
        return torch.rand(n, 3, generator=self.gen, device=self.gen.device)

    def _with_prior_rays(self, batch: Batch) -> Batch:
        """``batch`` with ``cfg.loss.prior_rays`` prior rays appended (image 0, beta scale 1, colour target the training
        images' mean colour, which counts only where ``prior_ray_colour`` weighs in the rays to unseen surfaces)."""
        rays, target_t, unseen = self.prior_rays.draw(int(self.cfg.loss.prior_rays), self.gen)
        with torch.no_grad():
            starts, ends = self.sampler(rays, True)
        n = len(rays)
        beta = None if batch.target_beta is None else torch.cat([batch.target_beta, torch.ones_like(target_t)])
        colour = self.mean_colour.expand(n, 3)
        weight = None
        if unseen is not None or batch.colour_weight is not None:  # else the prior rays carry no colour term
            prior_weight = target_t.new_zeros(n) if unseen is None else self.cfg.loss.prior_ray_colour * unseen.float()
            image_weight = batch.colour_weight
            if image_weight is None:
                image_weight = torch.ones_like(batch.target_rgb[:, 0])
            weight = torch.cat([image_weight, prior_weight])
        return Batch(torch.cat([batch.origins, rays.origins]), torch.cat([batch.dirs, rays.dirs]),
                     torch.cat([batch.starts, starts]), torch.cat([batch.ends, ends]),
                     torch.cat([batch.target_rgb, colour]), torch.cat([batch.target_t, target_t]),
                     torch.cat([batch.target_ok, torch.ones_like(target_t, dtype=torch.bool)]), beta,
                     torch.cat([batch.image, batch.image.new_zeros(n)]), batch.depth_weight, weight,
                     None if batch.background is None else torch.cat([batch.background, self._random_background(n)]),
                     batch.pose_corrections)

    def losses(self, batch: Batch) -> Losses:
        losses = self.loss_fn(batch)
        self.optimizer.zero_grad(set_to_none=True)
        losses.total.backward()
        if self.error_map is not None and self._drawn is not None and losses.ray_error is not None:
            self.error_map.update(self._drawn, losses.ray_error[: len(self._drawn)])
        return losses

    def apply(self) -> None:
        self.optimizer.step()
