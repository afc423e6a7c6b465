"""Training pixels on the training device: images, poses and per-pixel caches, and the random batches."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from voxnerf.cameras.lens import LensBatch
from voxnerf.cameras.rays import camera_rays
from voxnerf.config import TrainConfig
from voxnerf.data.scene import Scene, SceneTransform
from voxnerf.model.samplers import RayBundle
from voxnerf.model.voxnerf_model import VoxNeRFModel

PixelIndex = tuple[torch.Tensor, torch.Tensor, torch.Tensor]  # img, py, px [R] each
MAX_DIRECTION_TABLE_BYTES = 256 * 2**20  # beyond this the lens's inverse runs per batch instead


@dataclass
class DirectionTable:
    """Unit ray directions in camera axes (OpenGL) of every pixel of each distinct camera of the training frames:
    ``dirs`` float32 [C, H, W, 3], ``camera`` int64 [N] (each frame's). Looking them up replaces the lens's
    Newton iterations in every batch."""

    dirs: torch.Tensor
    camera: torch.Tensor


def direction_table(intr: torch.Tensor, lens: LensBatch | None, h: int, w: int) -> DirectionTable | None:
    """The table of frames with intrinsics ``intr`` [N, 4] and lenses ``lens``; None without a lens or when it
    would exceed :data:`MAX_DIRECTION_TABLE_BYTES`."""
    if lens is None:
        return None
    keys = torch.cat([intr, lens.coeffs.to(intr.dtype), lens.codes[:, None].to(intr.dtype)], dim=1)
    unique, camera = torch.unique(keys, dim=0, return_inverse=True)
    if unique.shape[0] * h * w * 3 * 4 > MAX_DIRECTION_TABLE_BYTES:
        return None
    py, px = torch.meshgrid(torch.arange(h, device=intr.device), torch.arange(w, device=intr.device), indexing="ij")
    py, px = py.reshape(-1), px.reshape(-1)
    eye = torch.eye(4, device=intr.device)
    tables = []
    for c in range(unique.shape[0]):
        frame = int(torch.nonzero(camera == c)[0, 0])
        k = intr[frame]
        one = lens.select(torch.tensor([frame], device=intr.device))
        _, dirs, _ = camera_rays(eye, k[0], k[1], k[2], k[3], px, py, one)
        tables.append(dirs.view(h, w, 3))
    return DirectionTable(torch.stack(tables), camera)


@dataclass
class TrainingPixels:
    """Training images and per-pixel caches on the training device.

    images uint8 [N, H, W, 3]; c2w float32 [N, 4, 4] normalised; intr float32 [N, 4] (fl_x, fl_y, cx, cy);
    lens: the frames' lenses (coefficients float32 [N, 6], model codes int64 [N]), None when every frame is a
    pinhole (the rays then cost what they always did);
    pseudo_t / hit_t float32 [N, H, W] ray distances (normalised; NaN where invalid), hit bool [N, H, W].
    """

    images: torch.Tensor
    c2w: torch.Tensor
    intr: torch.Tensor
    lens: LensBatch | None = None
    pseudo_t: torch.Tensor | None = None
    hit_t: torch.Tensor | None = None
    hit: torch.Tensor | None = None
    depth_t: torch.Tensor | None = None  # [N, H, W] the depth loss's target (normalised ray distance, NaN: none)
    depth_beta_scale: torch.Tensor | None = None  # [N, H, W] each pixel's log-Huber beta over the run's
    directions: DirectionTable | None = None  # the lens rays of every pixel, when the frames have lenses

    @property
    def shape(self) -> tuple[int, int, int]:
        n, h, w, _ = self.images.shape
        return n, h, w

    def rays(self, img: torch.Tensor, py: torch.Tensor, px: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """Rays of the given pixels (through their frame's lens): origins, dirs [R, 3], normalised units."""
        if self.directions is not None:
            d_cam = self.directions.dirs[self.directions.camera[img], py, px]
            dirs = torch.einsum("nij,nj->ni", self.c2w[img, :3, :3], d_cam)
            return self.c2w[img, :3, 3].contiguous(), dirs / torch.linalg.vector_norm(dirs, dim=-1, keepdim=True)
        k = self.intr[img]
        lens = None if self.lens is None else self.lens.select(img)
        origins, dirs, _ = camera_rays(self.c2w[img], k[:, 0], k[:, 1], k[:, 2], k[:, 3], px, py, lens)
        return origins, dirs


def training_pixels(scene: Scene, transform: SceneTransform, device: torch.device) -> TrainingPixels:
    """The scene's training images and normalised poses on ``device``; one image size per scene."""
    idx = scene.train_indices
    sizes = {scene.images[i].shape for i in idx}
    if len(sizes) != 1:
        raise ValueError(f"training images differ in size ({sorted(sizes)}); one size per scene is supported")
    images = torch.from_numpy(np.stack([scene.images[i] for i in idx])).to(device)
    c2w = np.stack([transform.c2w_to_normalized(scene.frames[i].c2w) for i in idx])
    intr = [scene.intrinsics(i) for i in idx]
    intr_t = torch.tensor([[k.fl_x, k.fl_y, k.cx, k.cy] for k in intr], dtype=torch.float32, device=device)
    lens = LensBatch.of([k.lens for k in intr], device)
    return TrainingPixels(images, torch.from_numpy(c2w).float().to(device), intr_t, lens,
                          directions=direction_table(intr_t, lens, *images.shape[1:3]))


def per_pixel(
    pixels: TrainingPixels,
    model: VoxNeRFModel,
    fn: Callable[[RayBundle, torch.Tensor], tuple[torch.Tensor, torch.Tensor]],
    chunk: int = 262_144,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Evaluate ``fn`` ((rays, flat pixel indices [R]) -> (t [R], valid [R])) on every training pixel -> [N, H, W]
    each; t NaN if invalid."""
    n, h, w = pixels.shape
    device = pixels.images.device
    t_all = torch.empty(n * h * w, device=device)
    ok_all = torch.empty(n * h * w, dtype=torch.bool, device=device)
    for f, _, origins, dirs in rays_in_chunks(pixels, torch.arange(n * h * w, device=device), chunk):
        t, ok = fn(model.ray_bundle(origins, dirs), f)
        t_all[f] = torch.where(ok, t, torch.full_like(t, float("nan")))
        ok_all[f] = ok
    return t_all.view(n, h, w), ok_all.view(n, h, w)


def rays_in_chunks(pixels: TrainingPixels, flat: torch.Tensor, chunk: int = 262_144):
    """Rays of the training pixels ``flat`` (int64 [P], flat indices into [N, H, W]), ``chunk`` at a time:
    yields (flat indices [R], image indices [R], origins [R, 3], unit dirs [R, 3]), normalised units."""
    n, h, w = pixels.shape
    for i in range(0, len(flat), chunk):
        f = flat[i : i + chunk]
        img, rem = f // (h * w), f % (h * w)
        origins, dirs = pixels.rays(img, rem // w, rem % w)
        yield f, img, origins, dirs


def sample_batch(pixels: TrainingPixels, cfg: TrainConfig, use_patches: bool, gen: torch.Generator) -> PixelIndex:
    """Random pixels plus (optionally) s x s patches: index tensors img, py, px [R] (patches last)."""
    n, h, w = pixels.shape
    device = pixels.images.device
    r = int(cfg.schedule.rays_per_batch)
    img = torch.randint(0, n, (r,), generator=gen, device=device)
    py = torch.randint(0, h, (r,), generator=gen, device=device)
    px = torch.randint(0, w, (r,), generator=gen, device=device)
    if use_patches:
        s, p = min(cfg.loss.patch_size, h, w), cfg.loss.smooth_patches
        pi = torch.randint(0, n, (p,), generator=gen, device=device)
        y0 = torch.randint(0, h - s + 1, (p,), generator=gen, device=device)
        x0 = torch.randint(0, w - s + 1, (p,), generator=gen, device=device)
        dy, dx = torch.meshgrid(torch.arange(s, device=device), torch.arange(s, device=device), indexing="ij")
        img = torch.cat([img, pi[:, None].expand(p, s * s).reshape(-1)])
        py = torch.cat([py, (y0[:, None] + dy.reshape(1, -1)).reshape(-1)])
        px = torch.cat([px, (x0[:, None] + dx.reshape(1, -1)).reshape(-1)])
    return img, py, px


def sensor_ray_distance(pixels: TrainingPixels, z: torch.Tensor, scale: float, chunk: int = 262_144) -> torch.Tensor:
    """Ray distances [N, H, W] (normalised units) of the z-depths ``z`` [N, H, W] (scene units, along each
    camera's -Z axis; NaN where invalid) of the training pixels: ``t = z * scale / cos``, ``cos`` the angle
    between the pixel's ray and the camera's axis."""
    n, h, w = pixels.shape
    z_flat = z.reshape(-1)
    t_all = torch.empty(n * h * w, device=z.device)
    for f, img, _, dirs in rays_in_chunks(pixels, torch.arange(n * h * w, device=z.device), chunk):
        cos = (dirs * -pixels.c2w[img, :3, 2]).sum(-1) / torch.linalg.vector_norm(dirs, dim=-1)
        t_all[f] = z_flat[f] * scale / cos.clamp_min(1e-6)
    return t_all.view(n, h, w)
