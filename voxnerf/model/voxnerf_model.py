"""The trained model: field + samplers + the scene box, and rendering of ray batches with it.

All geometry here is in normalised units (see :class:`voxnerf.data.scene.SceneTransform`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

from voxnerf.cameras.pose_refinement import PoseRefinement
from voxnerf.config import TrainConfig
from voxnerf.data.scene import SceneTransform
from voxnerf.model import hash_kernel
from voxnerf.model.appearance import ImageAppearance
from voxnerf.model.field import RadianceField
from voxnerf.model.samplers import OccGridSampler, OccupancyGrid, RayBundle, UniformSampler, VoxNeRFSampler
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
    field = RadianceField(cfg.hash_levels, cfg.hash_features, cfg.hash_log2_size, cfg.hash_max_resolution,
                          cfg.hidden_dim, cfg.sh_bands)
    field.encoding.use_kernel = cfg.hash_kernel and hash_kernel.available()
    return field


@dataclass
class VoxNeRFModel:
    """Everything needed to render: the field, the occupancy grid, the octree (voxnerf sampler) and the box.

    ``aabb`` [2, 3]: the scene box in normalised units, inside [-1, 1]^3. ``octree`` is None when the scene
    has no prior or the sampler does not use it. ``appearance`` (config ``appearance='affine'``) corrects the
    training images' colours, and a rendered view's as its nearest training cameras' were; ``pose_refinement``
    (config ``pose_refinement='so3xr3'``) corrects the training images' rays, and a rendered pose by its nearest
    training cameras' corrections (both applied by :func:`voxnerf.inference.render.render_normalized`).
    """

    config: TrainConfig
    transform: SceneTransform
    aabb: Tensor
    field: RadianceField
    grid: OccupancyGrid
    octree: SparseVoxelOctree | None
    appearance: ImageAppearance | None = None
    pose_refinement: PoseRefinement | None = None
    _compiled: dict = field(default_factory=dict, repr=False)

    @staticmethod
    def create(
        config: TrainConfig,
        transform: SceneTransform,
        aabb: Tensor,
        octree: SparseVoxelOctree | None,
        device: torch.device,
    ) -> VoxNeRFModel:
        cfg = config.resolved()
        field = field_for(cfg).to(device)
        grid = OccupancyGrid(cfg.occgrid_resolution).to(device)
        return VoxNeRFModel(cfg, transform, aabb.to(device), field, grid, octree)

    @property
    def device(self) -> torch.device:
        return self.aabb.device

    @property
    def background(self) -> Tensor:
        """[3] the colour behind every ray. ``'training_mean'`` is resolved to a colour by the trainer
        (:func:`voxnerf.training.stages.model_stage`; checkpoints hold the colour); a model built without
        training images, where it is still the name, shows black."""
        colour = (0.0, 0.0, 0.0) if isinstance(self.config.background, str) else self.config.background
        return torch.tensor(colour, dtype=torch.float32, device=self.device)

    def sampler(self) -> UniformSampler | OccGridSampler | VoxNeRFSampler:
        n = self.config.samples_per_ray
        if self.config.sampler == "uniform":
            return UniformSampler(n)
        occ = OccGridSampler(self.grid, n)
        if self.config.sampler == "occgrid" or self.octree is None:
            return occ
        return VoxNeRFSampler(self.octree, int(self.config.n_importance), int(self.config.n_rest), occ)

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
        density, rgb = self.field(positions.reshape(-1, 3), dirs[:, None, :].expand(r, s, 3).reshape(-1, 3))
        bg = self.background if background is None else background
        return volume_render(density.view(r, s), rgb.view(r, s, 3), starts, ends, bg)

    def compiled_render_samples(self):
        """:meth:`render_samples` through ``torch.compile`` (built once per model; callers keep shapes fixed)."""
        if "render_samples" not in self._compiled:
            self._compiled["render_samples"] = torch.compile(self.render_samples, dynamic=False)
        return self._compiled["render_samples"]

    def compiled_density(self):
        """``field.density`` through ``torch.compile`` (built once per model; callers keep shapes fixed, as
        :meth:`OccupancyGrid.update` does)."""
        if "density" not in self._compiled:
            self._compiled["density"] = torch.compile(self.field.density, dynamic=False)
        return self._compiled["density"]

    def render_rays(self, rays: RayBundle, sampler, stratified: bool = False, compiled: bool = False) -> dict:
        """Render a ray batch: ``rgb`` [R, 3], ``depth`` [R] (ray distance, normalised), ``opacity`` [R]."""
        starts, ends = sampler(rays, stratified)
        fn = self.compiled_render_samples() if compiled else self.render_samples
        return fn(rays.origins, rays.dirs, starts, ends)

    def state_dict(self) -> dict:
        return {
            "config": self.config.model_dump(),
            "transform": {"center": list(self.transform.center), "scale": self.transform.scale},
            "aabb": self.aabb.cpu(),
            "field": self.field.state_dict(),
            "grid": self.grid.state_dict(),
            "octree": None if self.octree is None else self.octree.state_dict(),
            "appearance": None if self.appearance is None else self.appearance.state_dict(),
            "pose_refinement": None if self.pose_refinement is None else self.pose_refinement.state_dict(),
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
        return model
