"""Training pixels on the training device: images, poses and per-pixel caches, and the random batches."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

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


def direction_table(intr: torch.Tensor, lens: LensBatch | None, h: int, w: int,
                    sizes: torch.Tensor | None = None) -> DirectionTable | None:
    """The table of frames with intrinsics ``intr`` [N, 4] and lenses ``lens`` on an ``h`` x ``w`` grid; None
    without a lens or when it would exceed :data:`MAX_DIRECTION_TABLE_BYTES`. With ``sizes`` (int64 [N, 2], each
    frame's height and width, when they differ) a camera's size is part of what makes it distinct, and only its
    own pixels get directions (the padding beyond them stays zero and is never looked up)."""
    if lens is None:
        return None
    keys = torch.cat([intr, lens.coeffs.to(intr.dtype), lens.codes[:, None].to(intr.dtype)], dim=1)
    if sizes is not None:
        keys = torch.cat([keys, sizes.to(intr.dtype)], dim=1)
    unique, camera = torch.unique(keys, dim=0, return_inverse=True)
    if unique.shape[0] * h * w * 3 * 4 > MAX_DIRECTION_TABLE_BYTES:
        return None
    eye = torch.eye(4, device=intr.device)
    tables = []
    for c in range(unique.shape[0]):
        frame = int(torch.nonzero(camera == c)[0, 0])
        ch, cw = (h, w) if sizes is None else (int(sizes[frame, 0]), int(sizes[frame, 1]))
        py, px = torch.meshgrid(torch.arange(ch, device=intr.device), torch.arange(cw, device=intr.device),
                                indexing="ij")
        k = intr[frame]
        one = lens.select(torch.tensor([frame], device=intr.device))
        _, dirs, _ = camera_rays(eye, k[0], k[1], k[2], k[3], px.reshape(-1), py.reshape(-1), one)
        table = torch.zeros(h, w, 3, device=intr.device, dtype=dirs.dtype)
        table[:ch, :cw] = dirs.view(ch, cw, 3)
        tables.append(table)
    return DirectionTable(torch.stack(tables), camera)


@dataclass
class TrainingPixels:
    """Training images and per-pixel caches on the training device.

    images uint8 [N, H, W, 3]; c2w float32 [N, 4, 4] normalised; intr float32 [N, 4] (fl_x, fl_y, cx, cy);
    lens: the frames' lenses (coefficients float32 [N, 6], model codes int64 [N]), None when every frame is a
    pinhole (the rays then cost what they always did);
    pseudo_t / hit_t float32 [N, H, W] ray distances (normalised; NaN where invalid), hit bool [N, H, W].

    Images of different sizes (per-image cameras, portrait beside landscape) share one grid: ``H`` x ``W`` is the
    largest height by the largest width, each image sits in the top-left corner of its slice, and ``sizes``
    (int64 [N, 2], each image's height and width) says where it ends. The padding is never sampled
    (:meth:`random_pixels`, :func:`sample_batch`) and every per-pixel cache is NaN / False there. ``sizes`` is
    None when every image has the grid's size: the batches are then drawn as they always were.
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
    sizes: torch.Tensor | None = None  # int64 [N, 2] each image's (height, width) when they differ, else None
    # What the batches of images of different sizes need, computed once (no host sync per step): pixels of all
    # images, the smallest height and width, and where each image's pixels end when counted image by image.
    pixel_count: int = field(init=False)
    smallest_side: tuple[int, int] = field(init=False)
    _pixel_ends: torch.Tensor | None = field(init=False, default=None, repr=False)

    def __post_init__(self) -> None:
        n, h, w = self.shape
        if self.sizes is None:
            self.pixel_count, self.smallest_side = n * h * w, (h, w)
            return
        per_image = self.sizes.prod(dim=1)
        self._pixel_ends = torch.cumsum(per_image, 0)
        self.pixel_count = int(per_image.sum())
        self.smallest_side = int(self.sizes[:, 0].min()), int(self.sizes[:, 1].min())

    @property
    def shape(self) -> tuple[int, int, int]:
        """(N, H, W) of the grid every per-pixel tensor has (the largest height and width)."""
        n, h, w, _ = self.images.shape
        return n, h, w

    def inside(self) -> torch.Tensor | None:
        """bool [N, H, W]: which grid pixels belong to their image; None when every one does."""
        if self.sizes is None:
            return None
        n, h, w = self.shape
        device = self.images.device
        rows = torch.arange(h, device=device)[None, :, None] < self.sizes[:, 0, None, None]
        cols = torch.arange(w, device=device)[None, None, :] < self.sizes[:, 1, None, None]
        return rows & cols

    def real_pixels(self) -> torch.Tensor:
        """int64 [P] flat indices into [N, H, W] of every image pixel (the padding left out), in order."""
        n, h, w = self.shape
        inside = self.inside()
        if inside is None:
            return torch.arange(n * h * w, device=self.images.device)
        return torch.nonzero(inside.view(-1)).view(-1)

    def random_pixels(self, count: int, gen: torch.Generator) -> torch.Tensor:
        """int64 [count] flat indices into [N, H, W] drawn uniformly over every image pixel (each pixel of each
        image equally likely, the padding never)."""
        n, h, w = self.shape
        device = self.images.device
        if self.sizes is None:
            return torch.randint(0, n * h * w, (count,), generator=gen, device=device)
        return self._flat_of_ordinal(torch.randint(0, self.pixel_count, (count,), generator=gen, device=device))

    def index_of(self, flat: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(image, row, column) int64 [R] of flat indices ``flat`` [R] into the [N, H, W] grid."""
        _, h, w = self.shape
        return flat // (h * w), flat % (h * w) // w, flat % w

    def _flat_of_ordinal(self, ordinal: torch.Tensor) -> torch.Tensor:
        """Flat grid indices of the pixels numbered ``ordinal`` when the images' pixels are counted image by
        image, row by row (the padding skipped)."""
        n, h, w = self.shape
        img = torch.searchsorted(self._pixel_ends, ordinal, right=True)
        width = self.sizes[img, 1]
        rem = ordinal - (self._pixel_ends[img] - self.sizes[img, 0] * width)
        return img * (h * w) + (rem // width) * w + rem % width

    def fraction(self, mask: torch.Tensor) -> float:
        """The fraction of the image pixels where ``mask`` (bool [N, H, W], False on the padding) holds."""
        return float(mask.sum()) / max(self.pixel_count, 1)

    def mean_colour(self) -> torch.Tensor:
        """float32 [3] the mean colour (in [0, 1]) of every training pixel."""
        if self.sizes is None:
            return self.images.float().mean((0, 1, 2)) / 255.0
        total = self.images.float().sum((0, 1, 2))  # the padding is black: it adds nothing
        return total / (255.0 * self.pixel_count)

    def rays(self, img: torch.Tensor, py: torch.Tensor, px: torch.Tensor,
             offset: torch.Tensor | None = None) -> tuple[torch.Tensor, ...]:
        """Rays of the given pixels (through their frame's lens): origins, dirs [R, 3], normalised units.

        ``offset`` (float32 [R, 2], pixels, each in [-0.5, 0.5): row then column) moves each ray from its pixel's
        centre to that point of the pixel; None: through the centres. Through a lens's direction table the
        direction at such a point is the bilinear mix of the four nearest pixel centres' (clamped to the image)."""
        if self.directions is not None:
            d_cam = (self.directions.dirs[self.directions.camera[img], py, px] if offset is None
                     else self._table_between(img, py, px, offset))
            dirs = torch.einsum("nij,nj->ni", self.c2w[img, :3, :3], d_cam)
            return self.c2w[img, :3, 3].contiguous(), dirs / torch.linalg.vector_norm(dirs, dim=-1, keepdim=True)
        k = self.intr[img]
        lens = None if self.lens is None else self.lens.select(img)
        if offset is not None:
            py, px = py.to(torch.float32) + offset[:, 0], px.to(torch.float32) + offset[:, 1]
        origins, dirs, _ = camera_rays(self.c2w[img], k[:, 0], k[:, 1], k[:, 2], k[:, 3], px, py, lens)
        return origins, dirs

    def _table_between(self, img: torch.Tensor, py: torch.Tensor, px: torch.Tensor,
                       offset: torch.Tensor) -> torch.Tensor:
        """float32 [R, 3] the direction table's bilinear mix at ``(py, px) + offset`` (pixels), its four pixel
        centres clamped to each image's own pixels."""
        n, h, w = self.shape
        if self.sizes is None:
            last_y, last_x = torch.full_like(py, h - 1), torch.full_like(px, w - 1)
        else:
            last_y, last_x = self.sizes[img, 0] - 1, self.sizes[img, 1] - 1
        y, x = py.to(torch.float32) + offset[:, 0], px.to(torch.float32) + offset[:, 1]
        y0, x0 = y.floor(), x.floor()
        fy, fx = (y - y0)[:, None], (x - x0)[:, None]
        y0, x0 = y0.long(), x0.long()
        y0, y1 = (v.clamp(min=0).minimum(last_y) for v in (y0, y0 + 1))
        x0, x1 = (v.clamp(min=0).minimum(last_x) for v in (x0, x0 + 1))
        table = self.directions.dirs
        camera = self.directions.camera[img]
        top = table[camera, y0, x0] * (1 - fx) + table[camera, y0, x1] * fx
        bottom = table[camera, y1, x0] * (1 - fx) + table[camera, y1, x1] * fx
        return top * (1 - fy) + bottom * fy


def padded_stack(arrays: list[np.ndarray], fill) -> np.ndarray:
    """``arrays`` ([h_i, w_i, ...] each) stacked on a grid of the largest height and width, each in the top-left
    corner of its slice and ``fill`` beyond it (a plain stack when they all have one size)."""
    if len({a.shape for a in arrays}) == 1:
        return np.stack(arrays)
    h, w = max(a.shape[0] for a in arrays), max(a.shape[1] for a in arrays)
    out = np.full((len(arrays), h, w, *arrays[0].shape[2:]), fill, dtype=arrays[0].dtype)
    for i, a in enumerate(arrays):
        out[i, : a.shape[0], : a.shape[1]] = a
    return out


def training_pixels(scene: Scene, transform: SceneTransform, device: torch.device) -> TrainingPixels:
    """The scene's training images and normalised poses on ``device``; images of different sizes share the grid
    of the largest (:class:`TrainingPixels`)."""
    idx = scene.train_indices
    shapes = [scene.images[i].shape[:2] for i in idx]
    images = torch.from_numpy(padded_stack([scene.images[i] for i in idx], 0)).to(device)
    sizes = None if len(set(shapes)) == 1 else torch.tensor(shapes, dtype=torch.int64, device=device)
    c2w = np.stack([transform.c2w_to_normalized(scene.frames[i].c2w) for i in idx])
    intr = [scene.intrinsics(i) for i in idx]
    intr_t = torch.tensor([[k.fl_x, k.fl_y, k.cx, k.cy] for k in intr], dtype=torch.float32, device=device)
    lens = LensBatch.of([k.lens for k in intr], device)
    return TrainingPixels(images, torch.from_numpy(c2w).float().to(device), intr_t, lens,
                          directions=direction_table(intr_t, lens, *images.shape[1:3], sizes), sizes=sizes)


def per_pixel(
    pixels: TrainingPixels,
    model: VoxNeRFModel,
    fn: Callable[[RayBundle, torch.Tensor], tuple[torch.Tensor, torch.Tensor]],
    chunk: int = 262_144,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Evaluate ``fn`` ((rays, flat pixel indices [R]) -> (t [R], valid [R])) on every training pixel -> [N, H, W]
    each; t NaN if invalid (and on the padding of a smaller image, where valid is False)."""
    n, h, w = pixels.shape
    device = pixels.images.device
    t_all = torch.full((n * h * w,), float("nan"), device=device)
    ok_all = torch.zeros(n * h * w, dtype=torch.bool, device=device)
    for f, _, origins, dirs in rays_in_chunks(pixels, pixels.real_pixels(), chunk):
        t, ok = fn(model.ray_bundle(origins, dirs), f)
        t_all[f] = torch.where(ok, t, torch.full_like(t, float("nan")))
        ok_all[f] = ok
    return t_all.view(n, h, w), ok_all.view(n, h, w)


def rays_in_chunks(pixels: TrainingPixels, flat: torch.Tensor, chunk: int = 262_144):
    """Rays of the training pixels ``flat`` (int64 [P], flat indices into [N, H, W]), ``chunk`` at a time:
    yields (flat indices [R], image indices [R], origins [R, 3], unit dirs [R, 3]), normalised units."""
    for i in range(0, len(flat), chunk):
        f = flat[i : i + chunk]
        img, py, px = pixels.index_of(f)
        origins, dirs = pixels.rays(img, py, px)
        yield f, img, origins, dirs


def sample_batch(pixels: TrainingPixels, cfg: TrainConfig, use_patches: bool, gen: torch.Generator,
                 flat: torch.Tensor | None = None) -> PixelIndex:
    """Random pixels plus (optionally) s x s patches: index tensors img, py, px [R] (patches last). Every pixel
    of every image is equally likely, unless ``flat`` (int64 [rays_per_batch] flat indices into [N, H, W]) names
    the rays' pixels; a patch lies inside one image (a side no larger than the smallest image's)."""
    n, h, w = pixels.shape
    device = pixels.images.device
    r = int(cfg.schedule.rays_per_batch)
    if flat is None and pixels.sizes is None:
        img = torch.randint(0, n, (r,), generator=gen, device=device)
        py = torch.randint(0, h, (r,), generator=gen, device=device)
        px = torch.randint(0, w, (r,), generator=gen, device=device)
    else:
        flat = pixels.random_pixels(r, gen) if flat is None else flat
        img, py, px = pixels.index_of(flat)
    if not use_patches:
        return img, py, px
    pi, y0, x0, s = _patch_corners(pixels, cfg, gen)
    dy, dx = torch.meshgrid(torch.arange(s, device=device), torch.arange(s, device=device), indexing="ij")
    img = torch.cat([img, pi[:, None].expand(len(pi), s * s).reshape(-1)])
    py = torch.cat([py, (y0[:, None] + dy.reshape(1, -1)).reshape(-1)])
    px = torch.cat([px, (x0[:, None] + dx.reshape(1, -1)).reshape(-1)])
    return img, py, px


def _patch_corners(pixels: TrainingPixels, cfg: TrainConfig,
                   gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, int]:
    """The smoothness patches' images, top rows and left columns [P] and their side: each patch inside its image."""
    n, h, w = pixels.shape
    device = pixels.images.device
    p = cfg.loss.smooth_patches
    if pixels.sizes is None:
        s = min(cfg.loss.patch_size, h, w)
        pi = torch.randint(0, n, (p,), generator=gen, device=device)
        y0 = torch.randint(0, h - s + 1, (p,), generator=gen, device=device)
        x0 = torch.randint(0, w - s + 1, (p,), generator=gen, device=device)
        return pi, y0, x0, s
    s = min(cfg.loss.patch_size, *pixels.smallest_side)
    pi = torch.randint(0, n, (p,), generator=gen, device=device)
    room = pixels.sizes[pi] - s + 1  # [p, 2] the top-left corners that keep the patch inside its image
    corner = (torch.rand(p, 2, generator=gen, device=device) * room).long().minimum(room - 1)
    return pi, corner[:, 0], corner[:, 1], s


def sensor_ray_distance(pixels: TrainingPixels, z: torch.Tensor, scale: float, chunk: int = 262_144) -> torch.Tensor:
    """Ray distances [N, H, W] (normalised units) of the z-depths ``z`` [N, H, W] (scene units, along each
    camera's -Z axis; NaN where invalid) of the training pixels: ``t = z * scale / cos``, ``cos`` the angle
    between the pixel's ray and the camera's axis (NaN on the padding of a smaller image)."""
    n, h, w = pixels.shape
    z_flat = z.reshape(-1)
    t_all = torch.full((n * h * w,), float("nan"), device=z.device)
    for f, img, _, dirs in rays_in_chunks(pixels, pixels.real_pixels(), chunk):
        cos = (dirs * -pixels.c2w[img, :3, 2]).sum(-1) / torch.linalg.vector_norm(dirs, dim=-1)
        t_all[f] = z_flat[f] * scale / cos.clamp_min(1e-6)
    return t_all.view(n, h, w)
