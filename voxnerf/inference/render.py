"""Rendering API: load a trained run and render any camera pose, chunked so memory stays bounded."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import BinaryIO

import numpy as np
import torch
from torch import Tensor

from voxnerf.cameras.lens import LensBatch
from voxnerf.cameras.rays import Intrinsics, camera_rays, image_rays
from voxnerf.cameras.rules import CameraError, validate_pose
from voxnerf.data.scene import Scene, with_focal_scale
from voxnerf.devices import resolve_device
from voxnerf.errors import RenderStopped, RunError
from voxnerf.files import CHECKPOINT
from voxnerf.inference.encoding import OUTPUT_NAMES
from voxnerf.inference.fast_path import FAST, render_rays_fast
from voxnerf.model.voxnerf_model import VoxNeRFModel
from voxnerf.training.checkpoint import load_checkpoint, stored_scene_dir

OUTPUTS = OUTPUT_NAMES
RENDER_PATHS = ("auto", "fast", "full")
FAST_CHUNK = 1 << 20  # rays per call of the fast path (it samples and composites them in cache-sized blocks)
STOPPABLE_FAST_CHUNK = 1 << 18  # the same for a render that may be stopped: it stops within one such pass
# An antialiased colour render (``antialias``): each pixel's colour is the weighted mean of the rays through these
# points of it, (dx, dy) in pixels from its centre with their weights (summing to 1): the centre and the centres of
# its four quarters, the centre weighing twice a quarter (chosen on the tuning suite's halves, docs/benchmarks.md,
# "Antialiased renders").
PIXEL_RAYS: tuple[tuple[float, float, float], ...] = (
    (0.0, 0.0, 1 / 3), (-0.25, -0.25, 1 / 6), (0.25, -0.25, 1 / 6), (-0.25, 0.25, 1 / 6), (0.25, 0.25, 1 / 6))
CENTRE_RAY = ((0.0, 0.0, 1.0),)


@dataclass
class TrainedModel:
    """A model loaded for rendering, with the scene's default camera and depth unit.

    ``default_intrinsics`` is the first training camera as trained, its lens included (a checkpoint from before
    lenses has none). A render that names no lens is the *undistorted* pinhole view of it: see :func:`render`
    and :func:`voxnerf.cameras.rules.resolve_intrinsics` (the rule of the CLI's pose file and ``POST /render``).
    """

    model: VoxNeRFModel
    default_intrinsics: Intrinsics
    depth_unit_scale: float
    iteration: int
    scene_dir: str | None = None


def load_model(run_dir: str | Path, device: str = "auto", opened: BinaryIO | None = None) -> TrainedModel:
    """Load ``run_dir/checkpoint.pt`` for rendering (from ``opened``, that file already open, when given: see
    :func:`~voxnerf.training.checkpoint.load_checkpoint`). Raises RunError when it is missing or unreadable."""
    path = Path(run_dir) / CHECKPOINT
    if opened is None and not path.is_file():
        raise RunError(f"{path}: no checkpoint (has the run trained yet?)")
    dev = resolve_device(device)
    state = load_checkpoint(path, dev, opened)  # weights_only: a checkpoint carrying code is refused, not run
    try:
        model = VoxNeRFModel.from_state_dict(state["model"], dev)
        trained = TrainedModel(
            model,
            Intrinsics(**state["default_intrinsics"]),  # a "lens" dict becomes a Lens
            float(state["depth_unit_scale"]),
            int(state["iteration"]),
            stored_scene_dir(state.get("scene_dir"), Path(run_dir)),
        )
    # TypeError, KeyError, AttributeError: not a checkpoint's dict; RuntimeError: weights of another shape
    except (RuntimeError, KeyError, ValueError, TypeError, AttributeError) as exc:
        why = " ".join(str(exc).split())  # one line: load_state_dict lists its mismatches line by line
        why = why if len(why) <= 200 else f"{why[:200]}..."
        raise RunError(f"{path}: unreadable checkpoint ({type(exc).__name__}: {why})") from None
    model.field.eval()
    return trained


def scene_as_trained(scene: Scene, model: VoxNeRFModel) -> Scene:
    """``scene`` seen through the cameras ``model`` trained with: the colour focal lengths times the run's
    ``focal_scale`` (:mod:`voxnerf.training.stages.focal`; 1 for a checkpoint from before it). Every caller that renders
    or scores a scene's own views loads the scene through this."""
    scale = model.config.corrections.focal_scale
    return with_focal_scale(scene, scale if isinstance(scale, float) else 1.0)


@torch.no_grad()
def render_normalized(
    model: VoxNeRFModel,
    c2w: Tensor,
    intrinsics: Intrinsics,
    outputs: Sequence[str] = OUTPUTS,
    chunk: int | None = None,
    path: str = "auto",
    should_stop: Callable[[], bool] | None = None,
    antialias: bool | None = None,
) -> dict[str, Tensor]:
    """Render one view whose pose is already in normalised units (a model that refined the training poses moves
    it by its nearest training cameras' corrections first, :mod:`voxnerf.cameras.pose_refinement`; one that learnt
    per-image appearance gives it their colour correction, :mod:`voxnerf.model.appearance`).

    Args:
        c2w: [4, 4] camera-to-world (OpenGL axes), normalised units.
        intrinsics: the camera; with a lens, each pixel's ray goes through its inverse distortion (the image
            a distorted camera sees, as evaluation compares with distorted ground truth).
        outputs: subset of ("rgb", "depth", "opacity"); "depth" is z-depth in normalised units.
        chunk: rays per forward pass (default: :data:`FAST_CHUNK` on the fast path, on the full one the
            config's eval_chunk, or the model's device's where it is not set:
            :meth:`voxnerf.config.EvaluationConfig.chunk_on`).
        path: ``"fast"`` (:mod:`voxnerf.inference.fast_path`: front to back, rays stop when opaque, no compiling),
            ``"full"`` (every sample of every ray, compiled when the config says so: the training-time path) or
            ``"auto"`` (:func:`resolved_render_path`).
        should_stop: asked before each pass over ``chunk`` rays (at most :data:`STOPPABLE_FAST_CHUNK` on the fast
            path); True stops the render there with RenderStopped (its caller gave up on it).
        antialias: the colour as the weighted mean of :data:`PIXEL_RAYS` per pixel (five times the rays) instead of
            the centre ray's; None: the model's ``antialias`` setting. Depth and opacity are the centre ray's.
    Returns:
        the requested outputs, rgb [H, W, 3] and depth/opacity [H, W], float32 on the model's device.
    """
    _check_outputs(outputs)
    c2w = c2w.to(model.device, torch.float32)

    offsets = pixel_rays(model, outputs, antialias)
    pose = model.view_pose(c2w)  # once: every ray of the pixel shares the corrected pose

    def render_at(k: int, wanted: Sequence[str]) -> dict[str, Tensor]:
        # The rays through (px + 0.5 + dx, py + 0.5 + dy): the principal point moved the other way.
        dx, dy, _ = offsets[k]
        origins, dirs, z_per_t = image_rays(pose, replace(intrinsics, cx=intrinsics.cx - dx, cy=intrinsics.cy - dy))
        parts = _render_chunks(model, origins, dirs, wanted, chunk, path, should_stop)
        return _view_outputs(model, c2w, intrinsics, parts, z_per_t)

    return _mean_over_pixel([weight for _, _, weight in offsets], outputs, render_at)


def _mean_over_pixel(weights: Sequence[float], outputs: Sequence[str],
                     render_at: Callable[[int, Sequence[str]], dict[str, Tensor]]) -> dict[str, Tensor]:
    """``outputs`` rendered through the points of each pixel that :func:`pixel_rays` gives (the centre first) with
    their ``weights``: every output of the centre ray, the colour as the weighted mean over all of them.
    ``render_at(k, wanted)`` renders the outputs ``wanted`` through the k-th point."""
    result = dict(render_at(0, outputs))
    if "rgb" in result:
        result["rgb"] = result["rgb"] * weights[0]
        for k in range(1, len(weights)):
            result["rgb"] = result["rgb"] + render_at(k, ("rgb",))["rgb"] * weights[k]
    return result


def pixel_rays(model: VoxNeRFModel, outputs: Sequence[str], antialias: bool | None = None
               ) -> tuple[tuple[float, float, float], ...]:
    """The points of a pixel a render of ``outputs`` casts rays through, (dx, dy, weight) with the centre first:
    :data:`PIXEL_RAYS` for a colour render when ``antialias`` (None: the model's setting) says so, else the centre
    alone."""
    wanted = model.config.model.antialias if antialias is None else antialias
    return PIXEL_RAYS if wanted and "rgb" in outputs else CENTRE_RAY


@dataclass
class PixelSet:
    """Some pixels of one view: its pose [4, 4] (normalised units), camera, and ``pixels`` [N], row-major indices
    into the camera's image."""

    c2w: Tensor
    intrinsics: Intrinsics
    pixels: Tensor


@torch.no_grad()
def render_pixels(model: VoxNeRFModel, c2w: Tensor, intrinsics: Intrinsics, pixels: Tensor,
                  outputs: Sequence[str] = ("rgb",), path: str = "auto", antialias: bool | None = None
                  ) -> dict[str, Tensor]:
    """Render some pixels of one view, as :func:`render_normalized` renders them in the whole image (the same
    rays, antialiasing, pose and colour corrections): ``pixels`` [N] are row-major indices into the
    ``intrinsics``' image.

    Returns the requested outputs, rgb [N, 3] and depth/opacity [N] (z-depth in normalised units), float32 on
    the model's device. RunError for an index outside the image.
    """
    return render_pixel_sets(model, [PixelSet(c2w, intrinsics, pixels)], outputs, path, antialias)[0]


@torch.no_grad()
def render_pixel_sets(model: VoxNeRFModel, sets: Sequence[PixelSet], outputs: Sequence[str] = ("rgb",),
                      path: str = "auto", antialias: bool | None = None) -> list[dict[str, Tensor]]:
    """:func:`render_pixels` of several views in one pass over all their rays (a pass has a fixed cost: a few
    hundred pixels of each of many views cost little more than their rays); one dict per set, in order."""
    _check_outputs(outputs)
    offsets = pixel_rays(model, outputs, antialias)
    rays, poses = [], []
    for one in sets:
        intr, pixels = one.intrinsics, one.pixels.to(model.device)
        n_pixels = intr.width * intr.height
        if pixels.numel() and (int(pixels.min()) < 0 or int(pixels.max()) >= n_pixels):
            raise RunError(f"pixel indices must lie in [0, {n_pixels}) for a {intr.width}x{intr.height} image, got "
                           f"{int(pixels.min())}..{int(pixels.max())}")
        c2w = one.c2w.to(model.device, torch.float32)
        lens = None if intr.lens is None else LensBatch.of([intr.lens], model.device)
        px, py = (pixels % intr.width).float(), (pixels // intr.width).float()
        pose = model.view_pose(c2w)
        rays.append([camera_rays(pose, intr.fl_x, intr.fl_y, intr.cx, intr.cy, px + dx, py + dy, lens)
                     for dx, dy, _ in offsets])
        poses.append(c2w)
    total = sum(r[0][0].shape[0] for r in rays)

    def render_at(k: int, wanted: Sequence[str]) -> dict[str, Tensor]:
        if not total:
            return {name: torch.zeros((0, 3) if name == "rgb" else (0,), device=model.device) for name in wanted}
        parts = _render_chunks(model, torch.cat([r[k][0] for r in rays]), torch.cat([r[k][1] for r in rays]),
                               wanted, None, path, None)
        return {name: torch.cat(values)[:total] for name, values in parts.items()}

    every = _mean_over_pixel([weight for _, _, weight in offsets], outputs, render_at)
    results, start = [], 0
    for ray_sets, c2w in zip(rays, poses, strict=True):
        z_per_t = ray_sets[0][2]
        end = start + z_per_t.shape[0]
        result = {name: values[start:end] for name, values in every.items()}
        if "depth" in result:
            result["depth"] = result["depth"] * z_per_t
        if "rgb" in result:
            result["rgb"] = model.view_colour(result["rgb"], c2w)
        results.append(result)
        start = end
    return results


def _check_outputs(outputs: Sequence[str]) -> None:
    unknown = set(outputs) - set(OUTPUTS)
    if unknown:
        raise RunError(f"unknown outputs {sorted(unknown)}; choose from {list(OUTPUTS)}")


def _render_chunks(model: VoxNeRFModel, origins: Tensor, dirs: Tensor, outputs: Sequence[str], chunk: int | None,
                   path: str, should_stop: Callable[[], bool] | None) -> dict[str, list[Tensor]]:
    """The rays rendered ``chunk`` at a time on the render ``path`` (see :func:`render_normalized`): each output's
    chunks, in order (a compiled full path pads the last chunk, so the chunks may hold more rows than rays)."""
    fast = resolved_render_path(path, model.device) == "fast"
    chunk = chunk or (FAST_CHUNK if fast else model.config.evaluation.chunk_on(model.device.type))
    if fast and should_stop is not None:
        chunk = min(chunk, STOPPABLE_FAST_CHUNK)
    n = origins.shape[0]
    compiled = bool(model.config.run.compile) and not fast
    if compiled and n % chunk:  # pad with copies of the last ray so every chunk has the compiled shape
        pad = chunk - n % chunk
        origins = torch.cat([origins, origins[-1:].expand(pad, 3)])
        dirs = torch.cat([dirs, dirs[-1:].expand(pad, 3)])
    sampler = model.sampler()
    parts: dict[str, list[Tensor]] = {name: [] for name in outputs}
    for i in range(0, n, chunk):
        if should_stop is not None and should_stop():
            raise RenderStopped(f"stopped after {i} of {n} rays: its caller no longer waits for it")
        rays = model.ray_bundle(origins[i : i + chunk], dirs[i : i + chunk])
        if fast:
            out = render_rays_fast(model, rays, sampler, FAST)
        else:
            out = model.render_rays(rays, sampler, compiled=compiled)
        for name, values in parts.items():
            values.append(out[name])
    return parts


def resolved_render_path(path: str, device: torch.device) -> str:
    """``path`` ("auto", "fast" or "full") as rendered on ``device``: "auto" is "fast" on the CPU and "full"
    elsewhere. The fast path walks each block of rays one sample column at a time, skipping the rays already
    opaque: on a CPU that saves field evaluations and keeps each column in cache, while on a GPU every column
    costs kernel launches and a host sync, and the full path's one batched, compiled pass is the quick one.
    RunError for any other ``path``."""
    if path not in RENDER_PATHS:
        raise RunError(f"unknown render path {path!r}; choose from {list(RENDER_PATHS)}")
    if path != "auto":
        return path
    return "fast" if torch.device(device).type == "cpu" else "full"


def _view_outputs(model: VoxNeRFModel, c2w: Tensor, intrinsics: Intrinsics, parts: dict[str, list[Tensor]],
                  z_per_t: Tensor) -> dict[str, Tensor]:
    """The chunks ``parts`` of each output put together as images (depth as z-depth), the colour corrected by
    the model's per-image appearance where it has one."""
    h, w = intrinsics.height, intrinsics.width
    result = {}
    for name, values in parts.items():
        tensor = torch.cat(values)[: h * w]
        if name == "depth":
            tensor = tensor * z_per_t
        result[name] = tensor.view(h, w, 3) if name == "rgb" else tensor.view(h, w)
    if "rgb" in result:
        result["rgb"] = model.view_colour(result["rgb"], c2w)
    return result


def render(
    trained: TrainedModel,
    c2w: np.ndarray | Tensor,
    intrinsics: Intrinsics | None = None,
    outputs: Sequence[str] = OUTPUTS,
    path: str = "auto",
    should_stop: Callable[[], bool] | None = None,
    antialias: bool | None = None,
) -> dict[str, np.ndarray]:
    """Render a pose given in scene units.

    Args:
        c2w: [4, 4] camera-to-world, OpenGL axes (as in transforms.json), scene units; checked by
            :func:`voxnerf.cameras.rules.validate_pose` (the rule of the CLI and the REST API): RunError
            ``c2w: <why>`` when it is refused, re-orthonormalised when slightly off.
        intrinsics: default: the scene's first training camera at the trained resolution, undistorted (a
            pinhole with its focal lengths and principal point, even when it was trained through a lens);
            give an :class:`Intrinsics` with a ``lens`` to render through one.
        outputs: subset of ("rgb", "depth", "opacity"); only these are computed.
        path: ``"fast"`` or ``"full"``, see :func:`render_normalized`.
        should_stop: asked between passes over the rays; True stops the render with RenderStopped (see
            :func:`render_normalized`).
        antialias: see :func:`render_normalized` (None: the model's setting).
    Returns:
        rgb float32 [H, W, 3] in [0, 1] (sRGB-encoded, as the images it was trained on), depth float32 [H, W]
        z-depth in scene units, opacity float32 [H, W].
    """
    try:
        pose = validate_pose(c2w.detach().cpu().numpy() if isinstance(c2w, Tensor) else c2w)
    except CameraError as err:
        raise RunError(f"c2w: {err}") from None
    model = trained.model
    pose_n = torch.from_numpy(model.transform.c2w_to_normalized(pose)).float()
    out = render_normalized(model, pose_n, intrinsics or trained.default_intrinsics.undistorted(), outputs, path=path,
                            should_stop=should_stop, antialias=antialias)
    result = {name: value.float().cpu().numpy() for name, value in out.items()}
    if "depth" in result:
        result["depth"] = result["depth"] / model.transform.scale
    return result
