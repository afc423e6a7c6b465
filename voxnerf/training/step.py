"""One optimisation step: the batch, the differentiable loss (what ``torch.compile`` compiles), the divergence
guard and the optimiser update."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import torch

from voxnerf.cameras.pose_refinement import moved_rays, pose_penalty
from voxnerf.config import TrainConfig
from voxnerf.errors import TrainingDiverged
from voxnerf.model.losses import color_loss, depth_loss, depth_smoothness_loss, distortion_loss
from voxnerf.model.voxnerf_model import VoxNeRFModel
from voxnerf.training.pixels import TrainingPixels, sample_batch
from voxnerf.training.prior_rays import PriorRayBank

PAPER_BETA = 0.1  # the paper's log-Huber beta, metres
DEPTH_BETA_PER_SIGMA = 5.0  # default beta = 5 sigma: the paper's 0.1 m for its 2 cm priors, in any unit


class Batch(NamedTuple):
    """The loss function's arguments, in its order: rays [R, 3] each, sample intervals, targets, each ray's
    training image [R] int64, and lambda_d now (a 0-d tensor: a schedule changes it without recompiling)."""

    origins: torch.Tensor
    dirs: torch.Tensor
    starts: torch.Tensor
    ends: torch.Tensor
    target_rgb: torch.Tensor
    target_t: torch.Tensor | None
    target_ok: torch.Tensor | None
    target_beta: torch.Tensor | None  # [R] each ray's beta over the run's (None: the run's beta everywhere)
    image: torch.Tensor
    depth_weight: torch.Tensor
    colour_weight: torch.Tensor | None = None  # [R] each ray's weight in the colour loss (None: image rays 1)
    background: torch.Tensor | None = None  # [R, 3] each ray's background colour (None: the model's)
    # [images, 6] the pose corrections moving the image rays (None: no pose refinement); detached on the steps
    # that leave the poses as they are
    pose_corrections: torch.Tensor | None = None


class Losses(NamedTuple):
    """Scalar tensors of one step: the total and its colour, depth, smoothness and distortion terms."""

    total: torch.Tensor
    colour: torch.Tensor
    depth: torch.Tensor
    smoothness: torch.Tensor
    distortion: torch.Tensor


LossFn = Callable[..., tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]]


def make_loss_fn(model: VoxNeRFModel, cfg: TrainConfig, beta: float, n_patch_rays: int, patch: int,
                 n_prior_rays: int = 0) -> LossFn:
    """The differentiable part of a step (field, rendering, losses) as one function of fixed-shape tensors.

    ``beta`` is in scene units. The depth terms compare depths in units of ``beta / 0.1``: for the paper's
    beta = 0.1 m that is metres, and for any other unit (mm, km) the same physical scene gets the same loss,
    so lambda_d keeps its meaning whatever the scene's units and normalisation. A ray's ``target_beta`` scales
    its beta (sensor depth is trusted less far away). The model's ``appearance`` (when it has one) corrects the
    rendered colour of each ray's training image before the colour loss. With a ``pose_refinement`` the batch's
    ``pose_corrections`` move each image ray as its training image's row says (the sample intervals stay those
    of the given pose: a correction is far smaller than the sampling window) and their regulariser joins the
    loss; detached corrections (a step that leaves the poses alone) make the step as cheap as one without
    refinement, since no gradient then flows into the sample positions and directions. The batch's last
    ``n_prior_rays`` rays are prior rays (:mod:`voxnerf.training.prior_rays`): depth targets only, left out of
    the colour loss; the smoothness patches come just before them.
    """
    to_units, lam_dist = PAPER_BETA / (beta * model.transform.scale), cfg.distortion_weight
    appearance, lam_pose = getattr(model, "appearance", None), cfg.lambda_pose

    def loss_fn(origins, dirs, starts, ends, target_rgb, target_t, target_ok, target_beta, image, depth_weight,
                colour_weight=None, background=None, pose_corrections=None):
        n_image = origins.shape[0] - n_prior_rays
        if pose_corrections is not None:
            origins, dirs = refined_rays(pose_corrections, origins, dirs, image, n_image)
        out = model.render_samples(origins, dirs, starts, ends, background)
        rgb = out["rgb"][:n_image] if appearance is None else appearance(out["rgb"][:n_image], image[:n_image])
        if colour_weight is None:
            lc = color_loss(rgb, target_rgb[:n_image])
        else:  # prior rays weighted in (their targets: the mean colour), normalised by the image rays
            per_ray = ((torch.cat([rgb, out["rgb"][n_image:]]) - target_rgb) ** 2).mean(-1)
            lc = (per_ray * colour_weight).sum() / n_image
        total = lc
        if pose_corrections is not None and lam_pose > 0:
            total = total + pose_penalty(pose_corrections, 0.1 * lam_pose, lam_pose)
        ld = lreg = ldist = torch.zeros((), device=origins.device)
        if lam_dist > 0:
            ldist = distortion_loss(out["weights"], starts, ends)
            total = total + lam_dist * ldist
        if target_t is not None:
            depth = out["depth"] * to_units
            ray_beta = PAPER_BETA if target_beta is None else PAPER_BETA * target_beta
            ld = depth_loss(depth, target_t * to_units, target_ok, ray_beta)
            if n_patch_rays:
                d = depth[n_image - n_patch_rays : n_image].view(-1, patch, patch)
                m = target_ok[n_image - n_patch_rays : n_image].view(-1, patch, patch)
                lreg = depth_smoothness_loss(d, m, cfg.smooth_scales)
            total = total + depth_weight * (ld + cfg.lambda_smooth * lreg)
        return total, lc, ld, lreg, ldist

    return loss_fn


def refined_rays(corrections: torch.Tensor, origins: torch.Tensor, dirs: torch.Tensor, image: torch.Tensor,
                 n_image: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays [R, 3] with the first ``n_image`` (the image rays) moved by their training image's row of the pose
    ``corrections`` [images, 6]; the rest (prior rays) as they are."""
    if n_image == origins.shape[0]:  # no prior rays: nothing to put back
        return moved_rays(corrections, origins, dirs, image)
    moved_o, moved_d = moved_rays(corrections, origins[:n_image], dirs[:n_image], image[:n_image])
    return torch.cat([moved_o, origins[n_image:]]), torch.cat([moved_d, dirs[n_image:]])


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


class TrainStep:
    """The step, split where the divergence guard looks: ``batch()``, ``losses(batch)`` (forward and
    backward) and ``apply()`` (the optimiser update, only after the guard passed). With pose refinement, every
    ``cfg.pose_every``-th batch carries the corrections with their gradient and the others carry them detached
    (those steps move the rays as the poses stand and leave the poses alone)."""

    def __init__(self, model: VoxNeRFModel, optimizer: torch.optim.Optimizer, pixels: TrainingPixels,
                 cfg: TrainConfig, loss_fn: LossFn, use_patches: bool, sampler, gen: torch.Generator,
                 prior_rays: PriorRayBank | None = None) -> None:
        self.model, self.optimizer, self.pixels, self.cfg = model, optimizer, pixels, cfg
        self.prior_rays = prior_rays
        self.mean_colour = pixels.images.float().mean((0, 1, 2)) / 255.0 if prior_rays is not None else None
        self.loss_fn, self.use_patches, self.sampler, self.gen = loss_fn, use_patches, sampler, gen
        self.depth_weight = torch.tensor(float(cfg.lambda_depth), device=pixels.images.device)  # the schedule sets it
        self.batches = 0  # batches drawn by this step (which ones refine the poses)

    def batch(self) -> Batch:
        pixels = self.pixels
        img, py, px = sample_batch(pixels, self.cfg, self.use_patches, self.gen)
        rays = self.model.ray_bundle(*pixels.rays(img, py, px))
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
                      self.depth_weight, background=self._random_background(len(img)),
                      pose_corrections=self._pose_corrections())
        self.batches += 1
        return batch if self.prior_rays is None or target_t is None else self._with_prior_rays(batch)

    @property
    def graphs(self) -> int:
        """How many forms the batches take for a compiled loss function: two where only every
        ``cfg.pose_every``-th one carries the pose corrections with their gradient, else one."""
        return 2 if getattr(self.model, "pose_refinement", None) is not None and self.cfg.pose_every > 1 else 1

    def _pose_corrections(self) -> torch.Tensor | None:
        """The model's pose corrections [images, 6] for this batch: with their gradient on every
        ``cfg.pose_every``-th batch, detached on the others; None without pose refinement."""
        poses = getattr(self.model, "pose_refinement", None)
        if poses is None:
            return None
        corrections = poses.corrections()
        return corrections if self.batches % self.cfg.pose_every == 0 else corrections.detach()

    def _random_background(self, n: int) -> torch.Tensor | None:
        """[n, 3] a uniform random colour behind each ray when ``train_background`` is 'random' (else None: the
        model's background). A ray can then match its pixel only by turning opaque, so the field cannot make a
        seen surface translucent and let the background tint it."""
        if self.cfg.train_background != "random":
            return None
        return torch.rand(n, 3, generator=self.gen, device=self.gen.device)

    def _with_prior_rays(self, batch: Batch) -> Batch:
        """``batch`` with ``cfg.prior_rays`` prior rays appended (image 0, beta scale 1, colour target the training
        images' mean colour, which counts only where ``prior_ray_colour`` weighs in the rays to unseen surfaces)."""
        rays, target_t, unseen = self.prior_rays.draw(int(self.cfg.prior_rays), self.gen)
        with torch.no_grad():
            starts, ends = self.sampler(rays, True)
        n = len(rays)
        beta = None if batch.target_beta is None else torch.cat([batch.target_beta, torch.ones_like(target_t)])
        colour = self.mean_colour.expand(n, 3)
        weight = None
        if unseen is not None:
            weight = torch.cat([torch.ones_like(batch.target_rgb[:, 0]), self.cfg.prior_ray_colour * unseen.float()])
        return Batch(torch.cat([batch.origins, rays.origins]), torch.cat([batch.dirs, rays.dirs]),
                     torch.cat([batch.starts, starts]), torch.cat([batch.ends, ends]),
                     torch.cat([batch.target_rgb, colour]), torch.cat([batch.target_t, target_t]),
                     torch.cat([batch.target_ok, torch.ones_like(target_t, dtype=torch.bool)]), beta,
                     torch.cat([batch.image, batch.image.new_zeros(n)]), batch.depth_weight, weight,
                     None if batch.background is None else torch.cat([batch.background, self._random_background(n)]),
                     batch.pose_corrections)

    def losses(self, batch: Batch) -> Losses:
        losses = Losses(*self.loss_fn(*batch))
        self.optimizer.zero_grad(set_to_none=True)
        losses.total.backward()
        return losses

    def apply(self) -> None:
        self.optimizer.step()
