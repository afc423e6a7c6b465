"""The fast inference path: the trained sampler's intervals, evaluated front to back with bounded skipping.

The full path (:meth:`voxnerf.model.voxnerf_model.VoxNeRFModel.render_rays`) evaluates density and colour at every
sample of every ray. This path takes the same intervals from the same sampler and composites them with the same rule
(:mod:`voxnerf.model.volume_rendering`), but walks the samples front to back, one column of the dense ``[R, S]``
packing at a time, and evaluates only what can change the pixel:

- a ray stops once its transmittance is below ``min_transmittance`` (early ray termination): what it leaves
  out weighs less than that in total;
- a sample whose weight is below ``min_weight`` gets no colour evaluation (its colour counts as black): at most
  ``min_weight`` of brightness per sample;
- with ``skip_empty`` (off by default), samples in cells of the occupancy grid marked empty get density 0
  without evaluating the field. Only for a grid that follows the field: the grid the surface-guided sampler
  keeps is seeded from the prior and thresholded, and a field still has density where it says empty;
- the colour MLP's direction input is folded in once per ray (:meth:`RadianceField.direction_features`).

It needs no ``torch.compile`` (a one-pose render pays nothing to compile) and runs alike on CPU and CUDA. All
geometry is in normalised units.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from voxnerf.model.field import spherical_harmonics, trunc_exp
from voxnerf.model.samplers import RayBundle
from voxnerf.model.volume_rendering import MAX_OPTICAL_DEPTH


@dataclass(frozen=True)
class FastSettings:
    """The bounds of the fast path's skipping (see the module doc)."""

    min_transmittance: float = 1e-4
    min_weight: float = 1e-4
    skip_empty: bool = False
    block: int = 16384  # most rays sampled and composited together
    precision: str = "auto"  # of the MLPs: auto (bfloat16 where native), float32 or bfloat16

    def describe(self, device: torch.device | None = None) -> str:
        """One line for reports: the bounds, and the MLPs' precision on ``device`` (when given)."""
        empty = ", empty cells skipped" if self.skip_empty else ""
        precision = f", MLPs in {resolve_precision(self.precision, device)}" if device is not None else ""
        return (f"fast: rays stop below transmittance {self.min_transmittance:g}, no colour below weight "
                f"{self.min_weight:g}{empty}{precision}")


FAST = FastSettings()
PRECISIONS = ("auto", "float32", "bfloat16")


def native_bfloat16(device: torch.device) -> bool:
    """Whether ``device`` multiplies bfloat16 matrices natively (a CUDA GPU that supports it, a CPU with
    AVX512-BF16 or AMX); elsewhere bfloat16 is emulated and slower than float32."""
    if device.type == "cuda":
        return torch.cuda.is_bf16_supported()
    return _cpu_bfloat16()


@functools.cache
def _cpu_bfloat16() -> bool:
    """This CPU's answer, probed once per process."""
    try:
        return bool(torch.cpu._is_avx512_bf16_supported() or torch.cpu._is_amx_tile_supported())
    except AttributeError:  # a torch without these probes
        return False


class FieldRunner:
    """The field's MLPs for inference in one dtype: float32, or bfloat16 where the device has it natively.

    The hash encoding stays float32 (the same features as training); its output, the MLPs' weights and
    activations are cast to ``dtype``; density and colour come back as float32.
    """

    def __init__(self, field, dtype: torch.dtype,
                 radii: Callable[[Tensor], Tensor | None] = lambda _distances: None) -> None:
        # radii: samples' footprint radii from their distances (VoxNeRFModel.sample_radii; default: points)
        self.field, self.dtype, self.radii = field, dtype, radii
        self.density_layers = _cast_linears(field.density_mlp, dtype)
        (first_w, first_b), *self.color_layers = _cast_linears(field.color_mlp, dtype)
        n_sh = first_w.shape[1] - field.GEO_FEATURES
        self.color_dir = (first_w[:, :n_sh].contiguous(), first_b)
        self.color_geo_t = first_w[:, n_sh:].t().contiguous()

    def geometry(self, positions: Tensor, radii: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """[N, 3] normalised positions (footprint radii [N], normalised units, or None: points) -> (density [N]
        float32, geometry features [N, 15] in ``dtype``)."""
        x = self.field.features(positions, radii).to(self.dtype)
        h = _mlp(x, self.density_layers)
        return trunc_exp(h[:, 0].float()), h[:, 1:]

    def direction_features(self, dirs: Tensor) -> Tensor:
        """[R, 3] unit directions -> [R, hidden] in ``dtype``: the direction part of the colour MLP's first
        layer, bias included."""
        weight, bias = self.color_dir
        return nn.functional.linear(spherical_harmonics(dirs, self.field.sh_bands).to(self.dtype), weight, bias)

    def color(self, geo: Tensor, direction_features: Tensor) -> Tensor:
        """[N, 3] float32 colour in [0, 1] of samples with geometry features ``geo`` [N, 15] whose rays have
        ``direction_features`` [N, hidden]."""
        x = torch.addmm(direction_features, geo, self.color_geo_t).relu_()
        return torch.sigmoid(_mlp(x, self.color_layers).float())


def _cast_linears(mlp: nn.Sequential, dtype: torch.dtype) -> list[tuple[Tensor, Tensor]]:
    """(weight, bias) of each linear layer of ``mlp``, detached and cast to ``dtype``."""
    return [(m.weight.detach().to(dtype), m.bias.detach().to(dtype)) for m in mlp if isinstance(m, nn.Linear)]


def _mlp(x: Tensor, layers: list[tuple[Tensor, Tensor]]) -> Tensor:
    """Linear layers with ReLU between them (none after the last)."""
    for weight, bias in layers[:-1]:
        x = linear_relu(x, weight, bias)
    return nn.functional.linear(x, *layers[-1])


def linear_relu(x: Tensor, weight: Tensor, bias: Tensor) -> Tensor:
    """``relu(x @ weight.T + bias)``; on the CPU in one oneDNN call (the ReLU fused into the matrix product's
    output) where this torch and this CPU have it for ``x``'s dtype, else two operations."""
    if x.device.type == "cpu" and _fused_linear_relu(x.dtype):
        return torch.ops.mkldnn._linear_pointwise(x, weight, bias, "relu", [None], "")
    return nn.functional.linear(x, weight, bias).relu_()


@functools.cache
def _fused_linear_relu(dtype: torch.dtype = torch.float32) -> bool:
    """Whether oneDNN's fused linear + ReLU runs here in ``dtype`` and agrees with the unfused pair (probed once per
    dtype: oneDNN's bfloat16 product needs a CPU with AVX-512, so an AVX2 CPU has it in float32 only)."""
    try:
        x, w, b = (torch.randn(*shape).to(dtype) for shape in ((4, 8), (3, 8), (3,)))
        fused = torch.ops.mkldnn._linear_pointwise(x, w, b, "relu", [None], "")
        unfused = nn.functional.linear(x.float(), w.float(), b.float()).relu()
        return bool(torch.allclose(fused.float(), unfused, atol=1e-5 if dtype == torch.float32 else 0.1))
    except (AttributeError, RuntimeError, NotImplementedError):
        return False


def resolve_precision(precision: str, device: torch.device) -> str:
    """``"float32"`` or ``"bfloat16"``: ``precision`` itself, or for ``"auto"`` bfloat16 where ``device`` has it
    natively. ValueError for anything else."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {PRECISIONS}, got {precision!r}")
    if precision == "auto":
        return "bfloat16" if native_bfloat16(device) else "float32"
    return precision


def field_runner(model, precision: str = "auto") -> FieldRunner:
    """A :class:`FieldRunner` of the model's field for ``precision`` (auto: bfloat16 where native).

    Built for each batch of rays (the casts cost microseconds): a runner holds copies of the MLP weights, and a
    kept one went stale when training changed the weights between two evaluations (the optimiser's updates do
    not all advance the parameters' version counters).
    """
    return FieldRunner(model.field, getattr(torch, resolve_precision(precision, model.device)),
                       model.sample_radii)


@torch.no_grad()
def render_rays_fast(model, rays: RayBundle, sampler, settings: FastSettings = FAST) -> dict[str, Tensor]:
    """Render a ray batch like ``model.render_rays(rays, sampler)``: ``rgb`` [R, 3], ``depth`` [R] (ray
    distance, normalised units), ``opacity`` [R], float32 on the rays' device.

    The rays are sampled and walked in blocks of ``settings.block`` (each column of a block is a few MB: it stays
    in cache). On the CPU the blocks go to one thread per torch thread, each running its operations
    single-threaded: the operations on a block are too small to share among threads, and blocks are independent.
    """
    runner = field_runner(model, settings.precision)
    workers = _block_workers(rays.origins.device)
    size = _block_size(len(rays), settings.block, workers)

    @torch.no_grad()  # grad mode is per thread
    def block(i: int) -> tuple[Tensor, Tensor, Tensor]:
        part, background = model.view_background(rays.slice(i, i + size), sampler)
        starts, ends = sampler(part, False)
        occupied = _occupied(model, part, 0.5 * (starts + ends)) if settings.skip_empty else None
        dir_features = runner.direction_features(part.dirs)
        acc = _Composite.empty(len(part), starts.device)
        for j in range(starts.shape[1]):
            acc.add_column(runner, part.origins, part.dirs, starts[:, j], ends[:, j], dir_features,
                           None if occupied is None else occupied[:, j], settings)
        return acc.finish(starts[:, 0], ends[:, -1], background)

    parts = _map_blocks(block, range(0, len(rays), size), workers)
    rgb, opacity, depth = (torch.cat(values) for values in zip(*parts, strict=True))
    return {"rgb": rgb, "depth": depth, "opacity": opacity}


def _block_workers(device: torch.device) -> int:
    """Threads the blocks are spread over: the torch threads on the CPU, one elsewhere."""
    return torch.get_num_threads() if device.type == "cpu" else 1


def _block_size(rays: int, most: int, workers: int) -> int:
    """Rays per block: at most ``most``, the blocks as even as can be and their number a multiple of
    ``workers`` (so no thread idles while another finishes a last block)."""
    blocks = workers * max(1, math.ceil(rays / (workers * most)))
    return max(1, math.ceil(rays / blocks))


def _map_blocks(fn, starts: range, workers: int) -> list:
    """``[fn(i) for i in starts]``, spread over ``workers`` threads whose torch operations run single-threaded
    meanwhile (the setting is restored after)."""
    if workers == 1 or len(starts) == 1:
        return [fn(i) for i in starts]
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with ThreadPoolExecutor(workers) as pool:
            return list(pool.map(fn, starts))
    finally:
        torch.set_num_threads(threads)


@dataclass
class _Composite:
    """Running front-to-back sums of a block of rays [B]: optical depth before the next column, colour [B, 3],
    weight and weighted distance."""

    optical: Tensor
    rgb: Tensor
    weight: Tensor
    depth: Tensor

    @staticmethod
    def empty(b: int, device: torch.device) -> _Composite:
        zeros = functools.partial(torch.zeros, device=device)
        return _Composite(zeros(b), zeros(b, 3), zeros(b), zeros(b))

    def add_column(self, runner: FieldRunner, origins: Tensor, dirs: Tensor, start: Tensor, end: Tensor,
                   dir_features: Tensor, occupied: Tensor | None, settings: FastSettings) -> None:
        """Composite one interval per ray (``start``, ``end`` [B]) behind what is already summed, evaluating
        the field only for live rays (not yet opaque, and in an occupied cell when ``occupied`` [B] is given)."""
        live = self.optical < -math.log(settings.min_transmittance)
        if occupied is not None:
            live &= occupied
        idx = _subset(live)
        if idx is not None and idx.numel() == 0:
            return
        t = _take(0.5 * (start + end), idx)
        density, geo = runner.geometry(_take(origins, idx) + t[:, None] * _take(dirs, idx), runner.radii(t))
        tau = torch.nan_to_num(density * _take(end - start, idx).clamp_min(0.0), nan=0.0, posinf=MAX_OPTICAL_DEPTH)
        tau = tau.clamp_(0.0, MAX_OPTICAL_DEPTH)
        weight = torch.exp(-_take(self.optical, idx)) * -torch.expm1(-tau)
        _add(self.optical, idx, tau)
        _add(self.weight, idx, weight)
        _add(self.depth, idx, weight * t)
        lit = _subset(weight >= settings.min_weight)
        if lit is not None and lit.numel() == 0:
            return
        rays_lit = idx if lit is None else lit if idx is None else idx[lit]  # rays of the lit samples
        color = runner.color(_take(geo, lit), _take(dir_features, rays_lit))
        _add(self.rgb, rays_lit, _take(weight, lit)[:, None] * color)

    def finish(self, near: Tensor, far: Tensor, background: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """(rgb [B, 3], opacity [B], depth [B]): the residual light is the background's ([3] or [B, 3]) and lies
        at ``far``, depth clamped to [near, far] (as :func:`voxnerf.model.volume_rendering.volume_render` does)."""
        opacity = self.weight.clamp(0.0, 1.0)
        residual = 1.0 - opacity
        rgb = self.rgb + residual[:, None] * background
        depth = torch.minimum(torch.maximum(self.depth + residual * far, near), far)
        return rgb, opacity, depth


def _subset(mask: Tensor) -> Tensor | None:
    """Indices of ``mask``'s true entries, or None when all are true (then callers use whole tensors)."""
    return None if bool(mask.all()) else mask.nonzero().squeeze(-1)


def _take(values: Tensor, idx: Tensor | None) -> Tensor:
    return values if idx is None else values[idx]


def _add(target: Tensor, idx: Tensor | None, values: Tensor) -> None:
    if idx is None:
        target += values
    else:
        target.index_add_(0, idx, values)


def _occupied(model, rays: RayBundle, mids: Tensor) -> Tensor:
    """[R, S] bool: whether each sample's cell of the occupancy grid is occupied."""
    r, s = mids.shape
    points = rays.origins[:, None, :] + mids[..., None] * rays.dirs[:, None, :]
    return model.grid.is_occupied(points.reshape(-1, 3)).view(r, s)
