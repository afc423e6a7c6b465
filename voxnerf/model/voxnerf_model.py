"""The model: field + samplers + the scene box; its outputs for a batch of training rays and its loss; rendering of
ray batches; and the per-image corrections (pose and appearance), applied here for training and rendering alike.

All geometry here is in normalised units (see :class:`voxnerf.data.scene.SceneTransform`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import torch
from torch import Tensor

from voxnerf.cameras.pose_refinement import PoseRefinement, moved_rays, pose_penalty
from voxnerf.config import TrainConfig
from voxnerf.data.scene import SceneTransform
from voxnerf.model import hash_kernel
from voxnerf.model.appearance import ImageAppearance
from voxnerf.model.colour_prior import ColourPrior
from voxnerf.model.field import RadianceField
from voxnerf.model.losses import PAPER_BETA, color_loss, depth_loss, depth_smoothness_loss, distortion_loss
from voxnerf.model.samplers import (
    OccGridSampler,
    OccupancyGrid,
    RayBundle,
    UniformSampler,
    VoxNeRFSampler,
    octree_misses_on,
)
from voxnerf.model.volume_rendering import volume_render
from voxnerf.prior.octree import SparseVoxelOctree

# Closest distance a ray is sampled from its origin, normalised units (about 1 cm in a 4 m room).
NEAR_MIN = 0.005


def ray_aabb(origins: Tensor, dirs: Tensor, aabb: Tensor) -> tuple[Tensor, Tensor]:
    """Slab test of rays [N, 3] against one box ``aabb`` [2, 3] -> (t_enter, t_exit) [N].

    Axis-parallel rays are handled without 0 * inf: a zero direction component leaves that slab unbounded
    when the origin lies inside it and empty otherwise. A miss gives ``t_enter > t_exit``.
    """
    lo, hi = aabb[0], aabb[1]
    parallel = dirs == 0
    safe = torch.where(parallel, torch.ones_like(dirs), dirs)
    t0, t1 = (lo - origins) / safe, (hi - origins) / safe
    inside = (origins >= lo) & (origins <= hi)
    big = torch.finfo(origins.dtype).max
    t_lo = torch.where(parallel, torch.where(inside, -big, big), torch.minimum(t0, t1))
    t_hi = torch.where(parallel, torch.where(inside, big, -big), torch.maximum(t0, t1))
    return t_lo.amax(-1), t_hi.amin(-1)


def field_for(config: TrainConfig) -> RadianceField:
    """The radiance field (on the CPU, freshly initialised) that ``config``'s resolved preset describes."""
    cfg = config.resolved()
    spec = cfg.model
    field = RadianceField(spec.hash_levels, spec.hash_features, spec.hash_log2_size, spec.hash_max_resolution,
                          cfg.model.hidden_dim, cfg.model.sh_bands)
    field.encoding.use_kernel = cfg.run.hash_kernel and hash_kernel.available()
    return field


class Batch(NamedTuple):
    """A batch of training rays and their targets (what :meth:`VoxNeRFModel.loss` takes; ``torch.compile``
    compiles it as a tuple of tensors). Rays [R, 3] each (normalised units, unit directions), sample intervals
    [R, S], targets, each ray's training image [R] int64, and lambda_d now (a 0-d tensor: a schedule changes it
    without recompiling). The last ``LossSettings.n_prior_rays`` rays are prior rays
    (:mod:`voxnerf.training.prior_rays`); the smoothness patches come just before them."""

    origins: Tensor
    dirs: Tensor
    starts: Tensor
    ends: Tensor
    target_rgb: Tensor
    target_t: Tensor | None
    target_ok: Tensor | None
    target_beta: Tensor | None  # [R] each ray's beta over the run's (None: the run's beta everywhere)
    image: Tensor
    depth_weight: Tensor
    colour_weight: Tensor | None = None  # [R] each ray's weight in the colour loss (None: image rays 1)
    background: Tensor | None = None  # [R, 3] each ray's background colour (None: the model's)
    # [images, 6] the pose corrections moving the image rays (None: no pose refinement); detached on the steps
    # that leave the poses as they are
    pose_corrections: Tensor | None = None


class Losses(NamedTuple):
    """Scalar tensors of one step: the total and its colour, depth, smoothness and distortion terms; and
    ``ray_error`` [R_image], each image ray's squared colour error (the mean over the channels, detached: what
    the error map of the training pixels reads, voxnerf/training/error_map.py)."""

    total: Tensor
    colour: Tensor
    depth: Tensor
    smoothness: Tensor
    distortion: Tensor
    ray_error: Tensor | None = None


@dataclass(frozen=True)
class LossSettings:
    """The constants of a run's loss (paper III-D; ``L = L_c + lambda_d (L_d + lambda_s L_reg) + lambda_dist
    L_dist`` plus the pose regulariser).

    ``depth_units`` turns a ray distance in normalised units into units of ``beta / PAPER_BETA`` (``PAPER_BETA /
    (beta * scale)`` for ``beta`` in scene units): for the paper's beta = 0.1 m that is metres, and for any other
    unit (mm, km) the same physical scene gets the same loss, so lambda_d keeps its meaning whatever the scene's
    units and normalisation."""

    depth_units: float
    distortion_weight: float = 0.0
    lambda_pose: float = 0.0
    lambda_smooth: float = 0.0
    smooth_scales: int = 1  # scales of the multi-scale depth smoothness
    n_patch_rays: int = 0  # smoothness patch rays, just before the prior rays
    patch: int = 8  # side of a smoothness patch, pixels
    n_prior_rays: int = 0  # prior rays at the end of each batch: depth targets only

    @staticmethod
    def of(config: TrainConfig, beta: float, scale: float, n_patch_rays: int, patch: int,
           n_prior_rays: int = 0) -> LossSettings:
        """The settings of ``config`` for a depth ``beta`` in scene units and the scene's normalisation ``scale``."""
        return LossSettings(PAPER_BETA / (beta * scale), config.loss.distortion_weight, config.corrections.lambda_pose,
                            config.loss.lambda_smooth, config.loss.smooth_scales, n_patch_rays, patch, n_prior_rays)


@dataclass
class VoxNeRFModel:
    """Everything needed to render: the field, the occupancy grid, the octree (voxnerf sampler) and the box.

    ``aabb`` [2, 3]: the scene box in normalised units, inside [-1, 1]^3. ``octree`` is None when the scene
    has no prior or the sampler does not use it. ``appearance`` (config ``appearance='affine'``) corrects the
    training images' colours, and a rendered view's as its nearest training cameras' were; ``pose_refinement``
    (config ``pose_refinement='so3xr3'``) corrects the training images' rays, and a rendered pose by its nearest
    training cameras' corrections (both applied by :func:`voxnerf.inference.render.render_normalized`).
    ``colour_prior`` (config ``render_background='nearest_seen'``, built at set-up) gives rendered rays the colour
    the training images show where the ray meets the prior (:meth:`view_background`).
    """

    config: TrainConfig
    transform: SceneTransform
    aabb: Tensor
    field: RadianceField
    grid: OccupancyGrid
    octree: SparseVoxelOctree | None
    appearance: ImageAppearance | None = None
    pose_refinement: PoseRefinement | None = None
    colour_prior: ColourPrior | None = None
    _compiled: dict = field(default_factory=dict, repr=False)

    @staticmethod
    def create(
        config: TrainConfig,
        transform: SceneTransform,
        aabb: Tensor,
        octree: SparseVoxelOctree | None,
        device: torch.device,
    ) -> VoxNeRFModel:
        """A fresh model of ``config``, which keeps only the model's own settings (:meth:`TrainConfig.for_model`)."""
        cfg = TrainConfig(**config.for_model())
        field = field_for(cfg).to(device)
        grid = OccupancyGrid(cfg.sampling.occgrid_resolution).to(device)
        return VoxNeRFModel(cfg, transform, aabb.to(device), field, grid, octree)

    @property
    def device(self) -> torch.device:
        return self.aabb.device

    @property
    def background(self) -> Tensor:
        """[3] the colour behind every ray. ``'training_mean'`` is resolved to a colour by the trainer
        (:func:`voxnerf.training.stages.model_stage`; checkpoints hold the colour); a model built without
        training images, where it is still the name, shows black."""
        colour = (0.0, 0.0, 0.0) if isinstance(self.config.model.background, str) else self.config.model.background
        return torch.tensor(colour, dtype=torch.float32, device=self.device)

    def view_background(self, rays: RayBundle, sampler) -> tuple[RayBundle, Tensor]:
        """What rendered rays show behind their last sample: ``rays`` with their octree first hits cached (when
        the colour prior needed them, so ``sampler`` does not cast them again) and the colour [R, 3] or [3].

        With ``render_background='nearest_seen'``, a colour prior and the voxnerf ``sampler``: each ray that meets
        the prior gets the :class:`ColourPrior` colour at its window centre, weighted by ``nearest_seen_weight``
        against :attr:`background`; every other ray :attr:`background`."""
        if (self.config.model.render_background != "nearest_seen" or self.colour_prior is None
                or not isinstance(sampler, VoxNeRFSampler)):
            return rays, self.background
        z, hit = sampler.first_hits(rays)
        rays = RayBundle(rays.origins, rays.dirs, rays.near, rays.far, z, hit)
        points = rays.origins + torch.where(hit, z, torch.zeros_like(z))[:, None] * rays.dirs
        colour, found = self.colour_prior.lookup(points)
        weight = self.config.model.nearest_seen_weight
        return rays, torch.where((hit & found)[:, None], weight * colour + (1.0 - weight) * self.background,
                                 self.background)

    def use_sampler(self, name: str) -> None:
        """Sample with ``name`` from now on (sampler ``auto``'s choice at set-up; checkpoints keep it)."""
        self.config = self.config.updated(sampler=name)

    def sampler(self) -> UniformSampler | OccGridSampler | VoxNeRFSampler:
        """The sampler of the config (``auto``, until the set-up resolves it, is the VoxNeRF sampler)."""
        n = self.config.sampling.samples_per_ray
        if self.config.sampling.sampler == "uniform":
            return UniformSampler(n)
        occ = OccGridSampler(self.grid, n)
        if self.config.sampling.sampler == "occgrid" or self.octree is None:
            return occ
        sampling = self.config.sampling
        misses = octree_misses_on(sampling.octree_misses, self.device)
        return VoxNeRFSampler(self.octree, int(sampling.n_importance), int(sampling.n_rest), occ, misses,
                              sampling.window_centre, float(sampling.window_width))

    @property
    def cone_radius(self) -> float | None:
        """A pixel's cone radius per unit of distance (radians) where the field is read over cones, else None
        (points). ``'auto'`` is resolved to a number by the trainer (:func:`voxnerf.training.stages.model_stage`;
        checkpoints hold the number)."""
        cone = self.config.model.cone_radius
        if cone == "auto":
            raise ValueError("VoxNeRFModel: resolve cone_radius 'auto' from the training cameras first")
        return cone or None

    def sample_radii(self, distances: Tensor) -> Tensor | None:
        """Footprint radii (normalised units) of samples at ``distances`` along their rays (normalised units,
        any shape, flattened), or None where the field reads points."""
        cone = self.cone_radius
        return None if cone is None else distances.reshape(-1) * cone

    def grid_density(self, positions: Tensor) -> Tensor:
        """Densities [N] at [N, 3] positions for the occupancy grid's updates: read over a footprint of half a grid
        cell where the field reads cones (a cell's mean, not its finest levels), at points otherwise."""
        if self.cone_radius is None:
            return self.field.density(positions)
        half_cell = 1.0 / self.grid.resolution  # normalised units: the grid spans [-1, 1]
        return self.field.density(positions, positions.new_full(positions.shape[:1], half_cell))

    def ray_bundle(self, origins: Tensor, dirs: Tensor) -> RayBundle:
        """Rays [N, 3] (normalised units, unit dirs) clipped to the scene box. A ray that misses the box gets
        an empty range at its near bound (it renders as background)."""
        t_in, t_out = ray_aabb(origins, dirs, self.aabb)
        near = t_in.clamp_min(NEAR_MIN)
        far = torch.maximum(t_out, near + 1e-6)
        return RayBundle(origins, dirs, near, far)

    def render_samples(self, origins: Tensor, dirs: Tensor, starts: Tensor, ends: Tensor,
                       background: Tensor | None = None) -> dict[str, Tensor]:
        """Evaluate the field on intervals [R, S] of rays origins, dirs [R, 3] and composite them over
        ``background`` ([3] or [R, 3]; default the model's :attr:`background`)."""
        r, s = starts.shape
        mids = 0.5 * (starts + ends)
        positions = origins[:, None, :] + mids[..., None] * dirs[:, None, :]
        density, rgb = self.field(positions.reshape(-1, 3), dirs[:, None, :].expand(r, s, 3).reshape(-1, 3),
                                  self.sample_radii(mids))
        bg = self.background if background is None else background
        return volume_render(density.view(r, s), rgb.view(r, s, 3), starts, ends, bg)

    # The per-image corrections, one place for training (by training image) and rendering (by view pose).

    def corrected_rays(self, origins: Tensor, dirs: Tensor, image: Tensor, corrections: Tensor | None,
                       n_image: int) -> tuple[Tensor, Tensor]:
        """Training rays [R, 3] with the first ``n_image`` (the image rays) moved by their training image's row of
        the pose ``corrections`` [images, 6] (None: as they are); the rest (prior rays) as they are."""
        if corrections is None:
            return origins, dirs
        if n_image == origins.shape[0]:  # no prior rays: nothing to put back
            return moved_rays(corrections, origins, dirs, image)
        moved_o, moved_d = moved_rays(corrections, origins[:n_image], dirs[:n_image], image[:n_image])
        return torch.cat([moved_o, origins[n_image:]]), torch.cat([moved_d, dirs[n_image:]])

    def corrected_colour(self, rgb: Tensor, image: Tensor) -> Tensor:
        """Rendered colours [R, 3] of rays of the training images ``image`` [R] as those images saw them (the
        per-image appearance, where the model learns one)."""
        return rgb if self.appearance is None else self.appearance(rgb, image)

    def view_pose(self, c2w: Tensor) -> Tensor:
        """A view's pose [4, 4] moved by its nearest training cameras' pose corrections (where the model refines
        the training poses)."""
        return c2w if self.pose_refinement is None else self.pose_refinement.correct_views(c2w[None])[0]

    def view_colour(self, rgb: Tensor, c2w: Tensor) -> Tensor:
        """A view's rendered colour [..., 3] corrected as its nearest training cameras' appearance was, in [0, 1]
        (where the model learns per-image appearance)."""
        return rgb if self.appearance is None else self.appearance.view_colour(rgb, c2w).clamp(0.0, 1.0)

    # Training: the outputs of a batch and its loss.

    def outputs(self, batch: Batch, n_prior_rays: int = 0) -> dict[str, Tensor]:
        """The rendered outputs of a training batch: the image rays moved by their pose corrections, the field
        composited over the batch's background (:meth:`render_samples`: ``rgb`` [R, 3], ``depth`` [R] ray
        distance, ``opacity`` [R], ``weights`` [R, S]), and ``image_rgb`` [R - n_prior_rays, 3], the image rays'
        colour as their training images saw it (:meth:`corrected_colour`)."""
        n_image = batch.origins.shape[0] - n_prior_rays
        origins, dirs = self.corrected_rays(batch.origins, batch.dirs, batch.image, batch.pose_corrections, n_image)
        out = dict(self.render_samples(origins, dirs, batch.starts, batch.ends, batch.background))
        out["image_rgb"] = self.corrected_colour(out["rgb"][:n_image], batch.image[:n_image])
        return out

    def loss(self, batch: Batch, settings: LossSettings) -> Losses:
        """The differentiable part of a training step (what ``torch.compile`` compiles): :meth:`outputs` and the
        loss terms (:mod:`voxnerf.model.losses`).

        Colour: the image rays against their pixels (prior rays join with their ``colour_weight``, normalised by
        the image rays). Depth: log-Huber against ``target_t`` where ``target_ok``, in units of ``beta /
        PAPER_BETA`` (a ray's ``target_beta`` scales its beta: sensor depth is trusted less far away), plus the
        multi-scale smoothness of the patch rays, both times ``depth_weight``. Distortion where weighted. With
        ``pose_corrections`` their regulariser joins; detached corrections (a step that leaves the poses alone)
        make the step as cheap as one without refinement, since no gradient then flows into the sample
        positions and directions."""
        out = self.outputs(batch, settings.n_prior_rays)
        rgb = out["image_rgb"]
        n_image = rgb.shape[0]
        if batch.colour_weight is None:
            lc = color_loss(rgb, batch.target_rgb[:n_image])
        else:  # prior rays weighted in (their targets: the mean colour), normalised by the image rays
            per_ray = ((torch.cat([rgb, out["rgb"][n_image:]]) - batch.target_rgb) ** 2).mean(-1)
            lc = (per_ray * batch.colour_weight).sum() / n_image
        total = lc
        if batch.pose_corrections is not None and settings.lambda_pose > 0:
            total = total + pose_penalty(batch.pose_corrections, 0.1 * settings.lambda_pose, settings.lambda_pose)
        ld = lreg = ldist = torch.zeros((), device=batch.origins.device)
        if settings.distortion_weight > 0:
            ldist = distortion_loss(out["weights"], batch.starts, batch.ends)
            total = total + settings.distortion_weight * ldist
        if batch.target_t is not None:
            depth = out["depth"] * settings.depth_units
            ray_beta = PAPER_BETA if batch.target_beta is None else PAPER_BETA * batch.target_beta
            ld = depth_loss(depth, batch.target_t * settings.depth_units, batch.target_ok, ray_beta)
            n_patch, patch = settings.n_patch_rays, settings.patch
            if n_patch:
                d = depth[n_image - n_patch : n_image].view(-1, patch, patch)
                m = batch.target_ok[n_image - n_patch : n_image].view(-1, patch, patch)
                lreg = depth_smoothness_loss(d, m, settings.smooth_scales)
            total = total + batch.depth_weight * (ld + settings.lambda_smooth * lreg)
        ray_error = ((rgb.detach() - batch.target_rgb[:n_image]) ** 2).mean(-1)
        return Losses(total, lc, ld, lreg, ldist, ray_error)

    # Rendering.

    def compiled_render_samples(self):
        """:meth:`render_samples` through ``torch.compile`` (built once per model; callers keep shapes fixed)."""
        if "render_samples" not in self._compiled:
            self._compiled["render_samples"] = torch.compile(self.render_samples, dynamic=False)
        return self._compiled["render_samples"]

    def compiled_density(self):
        """:meth:`grid_density` through ``torch.compile`` (built once per model; callers keep shapes fixed, as
        :meth:`OccupancyGrid.update` does)."""
        if "density" not in self._compiled:
            self._compiled["density"] = torch.compile(self.grid_density, dynamic=False)
        return self._compiled["density"]

    def render_rays(self, rays: RayBundle, sampler, stratified: bool = False, compiled: bool = False) -> dict:
        """Render a ray batch: ``rgb`` [R, 3], ``depth`` [R] (ray distance, normalised), ``opacity`` [R], over
        :meth:`view_background`."""
        rays, background = self.view_background(rays, sampler)
        starts, ends = sampler(rays, stratified)
        fn = self.compiled_render_samples() if compiled else self.render_samples
        return fn(rays.origins, rays.dirs, starts, ends, background)

    def state_dict(self) -> dict:
        return {
            "config": self.config.for_model(),
            "transform": {"center": list(self.transform.center), "scale": self.transform.scale},
            "aabb": self.aabb.cpu(),
            "field": self.field.state_dict(),
            "grid": self.grid.state_dict(),
            "octree": None if self.octree is None else self.octree.state_dict(),
            "appearance": None if self.appearance is None else self.appearance.state_dict(),
            "pose_refinement": None if self.pose_refinement is None else self.pose_refinement.state_dict(),
            "colour_prior": None if self.colour_prior is None else self.colour_prior.state_dict(),
        }

    @staticmethod
    def from_state_dict(state: dict, device: torch.device) -> VoxNeRFModel:
        config = TrainConfig(**state["config"])
        transform = SceneTransform(tuple(state["transform"]["center"]), float(state["transform"]["scale"]))
        octree = None
        if state["octree"] is not None:
            octree = SparseVoxelOctree.from_state_dict(state["octree"]).to(device)
        model = VoxNeRFModel.create(config, transform, state["aabb"], octree, device)
        model.field.load_state_dict(state["field"])
        model.grid.load_state_dict(state["grid"])
        if state.get("appearance") is not None:
            model.appearance = ImageAppearance(int(state["appearance"]["bias"].shape[0])).to(device)
            # a checkpoint from before the cameras were kept: identity cameras, so views take the mean (none)
            model.appearance.load_state_dict({"cameras": model.appearance.cameras} | state["appearance"])
        if state.get("pose_refinement") is not None:
            model.pose_refinement = PoseRefinement(int(state["pose_refinement"]["delta"].shape[0])).to(device)
            model.pose_refinement.load_state_dict(state["pose_refinement"])
        if state.get("colour_prior") is not None:  # a checkpoint from before it has none
            model.colour_prior = ColourPrior.from_state_dict(state["colour_prior"]).to(device)
        return model
