"""Prior rays: rays that no training image covers, supervised by the prior's depth alone.

The depth loss of the paper reaches only the training pixels, so space that no training view sees stays as the
field was initialised: nearly transparent. A novel view looking there (the extrapolation views of an
inside-out scan) renders the background through it. The prior covers those surfaces too; a prior ray starts
at a training camera's centre in a direction drawn uniformly on the sphere, and its target is the prior's
depth along it (the pseudo depth of paper III-D, cast the same way). Each step adds ``TrainConfig.prior_rays``
of them to the batch, after the image rays: they enter the depth loss (and the distortion loss), never the
colour loss.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from voxnerf.model.samplers import RayBundle, window_centres
from voxnerf.model.voxnerf_model import VoxNeRFModel
from voxnerf.prior.octree import SparseVoxelOctree
from voxnerf.prior.pseudo_depth import PriorDepthRenderer

BANK_PER_STEP_RAY = 128  # rays cast at set-up per prior ray of a step (the bank they are drawn from)
MAX_BANK = 524_288


@dataclass
class PriorRayBank:
    """Rays cast once at set-up (normalised units; the sampler octree's first hits attached when there is one),
    ``target_t`` [M] the prior's ray distance along each, ``unseen`` [M] bool whether no training view sees the
    ray's surface point (None: not computed)."""

    rays: RayBundle
    target_t: Tensor
    unseen: Tensor | None = None

    def __len__(self) -> int:
        return len(self.rays)

    def draw(self, n: int, gen: torch.Generator) -> tuple[RayBundle, Tensor, Tensor | None]:
        """``n`` rays drawn uniformly (with replacement): the bundle (first hits attached), their targets and
        their ``unseen`` flags."""
        idx = torch.randint(0, len(self), (n,), generator=gen, device=self.target_t.device)
        return self.rays.take(idx), self.target_t[idx], None if self.unseen is None else self.unseen[idx]


def camera_centre_rays(centres: Tensor, n: int, gen: torch.Generator) -> tuple[Tensor, Tensor]:
    """``n`` rays [n, 3]: origins at the camera ``centres`` [C, 3] (drawn uniformly), unit directions uniform on
    the sphere."""
    device = centres.device
    pick = torch.randint(0, centres.shape[0], (n,), generator=gen, device=device)
    dirs = torch.randn(n, 3, generator=gen, device=device)
    dirs = dirs / torch.linalg.vector_norm(dirs, dim=-1, keepdim=True).clamp_min(1e-12)
    return centres[pick].contiguous(), dirs


def prior_ray_bank(centres: Tensor, model: VoxNeRFModel, renderer: PriorDepthRenderer,
                   octree: SparseVoxelOctree | None, n: int, seed: int = 0) -> PriorRayBank:
    """``n`` rays from the camera ``centres`` [C, 3] (normalised) kept where the prior is hit inside the scene
    box; their targets and (with ``octree``) window centres (``samplers.window_centres``). May hold fewer than
    ``n`` rays (none when the prior is never hit). ``unseen`` is left for :func:`seen_by`."""
    gen = torch.Generator(device=centres.device).manual_seed(seed)
    rays = model.ray_bundle(*camera_centre_rays(centres, n, gen))
    t, ok = renderer.ray_distance(rays.origins, rays.dirs, rays.near, rays.far)
    kept = rays.take(ok & torch.isfinite(t))
    target_t = t[ok & torch.isfinite(t)]
    if octree is not None and len(kept):
        kept.hit_t, kept.hit = window_centres(octree, model.config.sampling.window_centre, kept.origins, kept.dirs,
                                              kept.near, kept.far, target_t)
    return PriorRayBank(kept, target_t)


def bank_size(prior_rays: int) -> int:
    return min(prior_rays * BANK_PER_STEP_RAY, MAX_BANK)


def seen_by(points: Tensor, c2w: Tensor, intr: Tensor, depth_t: Tensor, tolerance: float,
            chunk: int = 8, sizes: Tensor | None = None) -> Tensor:
    """[M] bool: whether some training view sees each of ``points`` [M, 3] (normalised): it projects inside
    the view (pinhole model of ``intr`` [N, 4] fl_x fl_y cx cy, ``c2w`` [N, 4, 4] OpenGL), in front of the
    camera, and the view's depth target there (``depth_t`` [N, H, W] ray distances, NaN where none) is within
    ``tolerance`` of the point's distance (a pixel with no target counts as seeing it). ``sizes`` (int64
    [N, 2], each view's height and width when they differ) bounds each view to its own pixels (else the
    [H, W] of ``depth_t``)."""
    n, h, w = depth_t.shape
    seen = torch.zeros(points.shape[0], dtype=torch.bool, device=points.device)
    for i in range(0, n, chunk):
        rot, origin = c2w[i : i + chunk, :3, :3], c2w[i : i + chunk, :3, 3]
        rel = points[None] - origin[:, None]  # [C, M, 3]
        cam = torch.einsum("cmj,cjk->cmk", rel, rot)  # R^T (p - o), camera axes
        z = -cam[..., 2]
        k = intr[i : i + chunk, :, None]
        px = (cam[..., 0] / z.clamp_min(1e-9) * k[:, 0] + k[:, 2] - 0.5).round()
        py = (-cam[..., 1] / z.clamp_min(1e-9) * k[:, 1] + k[:, 3] - 0.5).round()
        hi, wi = (h, w) if sizes is None else (sizes[i : i + chunk, 0, None], sizes[i : i + chunk, 1, None])
        inside = (z > 0) & (px >= 0) & (px < wi) & (py >= 0) & (py < hi)
        view = torch.arange(i, min(i + chunk, n), device=points.device)[:, None].expand_as(px)
        target = depth_t[view, py.clamp(0, h - 1).long(), px.clamp(0, w - 1).long()]
        distance = torch.linalg.vector_norm(rel, dim=-1)
        agrees = ~torch.isfinite(target) | ((distance - target).abs() <= tolerance)
        seen |= (inside & agrees).any(0)
    return seen
