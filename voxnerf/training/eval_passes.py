"""Evaluations during and after training: the views of the evaluation splits, progress evaluations (some pixels
of a few views per split, or every view for ``--eval-at``) and the final evaluation, each appending an EvalRecord."""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from voxnerf.config import TrainConfig
from voxnerf.data.scene import Scene, SceneTransform
from voxnerf.inference.evaluation import EvaluationStopped, EvalView, evaluate_views, view_names
from voxnerf.inference.metrics import psnr
from voxnerf.inference.render import PixelSet, render_pixel_sets, render_pixels
from voxnerf.model.voxnerf_model import VoxNeRFModel
from voxnerf.training.budget import Budget
from voxnerf.training.records import EvalRecord

EvalViews = dict[str, list[EvalView]]


def eval_views_of(scene: Scene, transform: SceneTransform, names: list[str] | None = None) -> EvalViews:
    """The views of every evaluation split of a loaded scene, posed in normalised units (a split listing the
    same frames as an earlier one is left out), or of the splits ``names``."""
    views: EvalViews = {}
    seen: list[list[int]] = []
    for name in names or scene.eval_split_names:
        if names is None and scene.splits[name] in seen:  # e.g. test_filenames repeating an eval split: evaluate once
            continue
        seen.append(scene.splits[name])
        indices = scene.splits[name]
        unique = view_names([scene.frames[i].file_path for i in indices], indices)
        views[name] = [
            EvalView(
                view_name,
                torch.from_numpy(transform.c2w_to_normalized(scene.frames[i].c2w)).float(),
                scene.intrinsics(i),
                torch.from_numpy(scene.images[i]),
            )
            for i, view_name in zip(indices, unique, strict=True)
        ]
    return views


def view_rays(views: EvalViews) -> int:
    """Rays (pixels) of every view of every split."""
    return sum(v.rays for vs in views.values() for v in vs)


PIXEL_SEED = 0  # the progress evaluations' pixels: the same in every evaluation of a run, and in every run
WARM_UP_RAYS = 1024  # rays a process's first progress evaluation renders untimed before the timed ones


def scored_pixels(view: EvalView, n: int) -> torch.Tensor:
    """``n`` pixels of ``view`` (row-major indices, sorted), drawn at random once per view size: the first ``n``
    of one fixed permutation, so a larger evaluation scores the smaller one's pixels and more; every pixel
    when ``n`` covers the view."""
    if n >= view.rays:
        return torch.arange(view.rays)
    return _pixel_order(view.rays)[:n].sort().values


@functools.lru_cache(maxsize=8)
def _pixel_order(rays: int) -> torch.Tensor:
    """The fixed random permutation of ``rays`` pixel indices :func:`scored_pixels` draws from (one per image size:
    a run's views share a few)."""
    return torch.randperm(rays, generator=torch.Generator().manual_seed(PIXEL_SEED))


def pixels_per_view(views: EvalViews, rays: int) -> list[int]:
    """``rays`` shared out over the views of every split, in order: as evenly as they go, none more than its view
    holds (what a smaller view cannot take goes to the others)."""
    sizes = [v.rays for vs in views.values() for v in vs]
    shares = [0] * len(sizes)
    left, open_views = rays, sorted(range(len(sizes)), key=lambda i: sizes[i])
    while left > 0 and open_views:
        even = left // len(open_views)
        if even == 0:  # fewer rays left than views: one more each for the first ones
            for i in open_views[:left]:
                shares[i] += 1
            break
        for i in list(open_views):
            take = min(even, sizes[i] - shares[i])
            shares[i] += take
            left -= take
            if shares[i] == sizes[i]:
                open_views.remove(i)
    return shares


def pixels_psnr(model: VoxNeRFModel, views: EvalViews, rays: int) -> dict[str, float]:
    """Mean PSNR (dB) per split over ``views``, each scored on its :func:`scored_pixels` (``rays`` shared out
    by :func:`pixels_per_view`; a view given none is left out) rendered as the whole view would render them, all
    views in one pass (:func:`render_pixel_sets`)."""
    shares = iter(pixels_per_view(views, rays))
    scored = [(split, view, scored_pixels(view, n)) for split, split_views in views.items() for view in split_views
              if (n := next(shares))]
    # Centre rays: a progress estimate at a fifth of an antialiased render's cost (the final evaluation antialiases).
    rendered = render_pixel_sets(model, [PixelSet(view.c2w, view.intrinsics, pixels) for _, view, pixels in scored],
                                 antialias=False)
    scores: dict[str, list[float]] = {}
    for (split, view, pixels), out in zip(scored, rendered, strict=True):
        truth = view.image.reshape(-1, 3)[pixels].float() / 255.0
        scores.setdefault(split, []).append(psnr(out["rgb"].float().cpu()[None], truth[None]))
    return {split: float(np.mean(values)) for split, values in scores.items()}


def progress_eval(
    model: VoxNeRFModel,
    views: EvalViews,
    cfg: TrainConfig,
    history: list[EvalRecord],
    budget: Budget,
    iteration: int,
    loss: float,
    rays: int | None,
    warm_up: bool = False,
) -> tuple[float, float]:
    """A progress evaluation of ``rays`` rays (pixels) spread over a few views per split (:func:`progress_views`),
    or, ``rays`` None, a full evaluation of every view (``--eval-at``: SSIM, LPIPS, the half-image protocol);
    appends the record to ``history`` and returns (seconds spent, seconds per ray).

    ``warm_up`` (the run's first evaluation) renders :data:`WARM_UP_RAYS` pixels of one view before the timed
    ones: what a process pays once (compiling the render, a GPU's first kernels) is in the seconds spent but not
    in the seconds per ray, which sizes the later progress evaluations."""
    t0 = time.perf_counter()
    elapsed, wall = budget.train_seconds, budget.wall
    full = rays is None
    subset = views if full else progress_views(views, cfg.evaluation.eval_views)
    if warm_up:
        first = next(iter(subset.values()))[0]
        render_pixels(model, first.c2w, first.intrinsics, scored_pixels(first, WARM_UP_RAYS), antialias=False)
    t_timed = time.perf_counter()
    if full:
        metrics = evaluate_views(model, subset, cfg, out_dir=None, lpips=True, half_image=True)
        psnr_per_split, scored = {k: m["psnr"] for k, m in metrics.items()}, view_rays(subset)
    else:
        scored = min(rays, view_rays(subset))
        psnr_per_split = pixels_psnr(model, subset, scored)
    t_end = time.perf_counter()
    spent, per_ray = t_end - t0, (t_end - t_timed) / max(scored, 1)
    entry = EvalRecord(
        elapsed_s=round(elapsed, 3), wall_s=round(wall, 3), iteration=iteration,
        loss=loss if math.isfinite(loss) else None, psnr=psnr_per_split,
    )
    if full:
        entry.full = True
        entry.ssim = {k: m["ssim"] for k, m in metrics.items()}
        entry.lpips = {k: m["lpips"] for k, m in metrics.items()}
        entry.half = {k: m["half"] for k, m in metrics.items()}
        entry.progress_psnr = progress_views_psnr(metrics, views, cfg.evaluation.eval_views)
    else:
        entry.rays = scored
    history.append(entry)
    return spent, per_ray


def progress_views(views: EvalViews, n: int) -> EvalViews:
    """The views a progress evaluation scores: ``n`` per split, spread over it (:func:`spread`)."""
    return {name: spread(v, n) for name, v in views.items()}


def final_eval(model: VoxNeRFModel, views: EvalViews, cfg: TrainConfig, out_dir: Path, budget: Budget,
               train_seconds: float, iteration: int, loss: float,
               should_stop: Callable[[], bool] | None = None) -> tuple[dict, EvalRecord] | None:
    """Every view of every split, renders written under ``out_dir``: (metrics per split, the history record
    at ``train_seconds``, the training time when the loop ended); None when ``should_stop()`` (asked before
    each view) interrupted it."""
    try:
        metrics = evaluate_views(model, views, cfg, out_dir=out_dir, should_stop=should_stop, half_image=True)
    except EvaluationStopped:
        return None
    record = EvalRecord(
        elapsed_s=round(train_seconds, 3), wall_s=round(budget.wall, 3), iteration=iteration, loss=loss,
        final=True, psnr={k: v["psnr"] for k, v in metrics.items()},
        progress_psnr=progress_views_psnr(metrics, views, cfg.evaluation.eval_views),
    )
    return metrics, record


def progress_views_psnr(metrics: dict, views: EvalViews, n: int) -> dict[str, float]:
    """Mean PSNR (dB) per split over the views a progress evaluation uses, from a full evaluation's per-view
    ``metrics``: so that one curve over the same views runs through progress and full evaluations alike."""
    return {
        split: float(np.mean([m["views"][i]["psnr"] for i in spread(list(range(len(views[split]))), n)]))
        for split, m in metrics.items()
    }


def spread(views: list, n: int) -> list:
    """``n`` items spread evenly over ``views`` (first and last included), or all of them."""
    if len(views) <= n:
        return views
    idx = np.linspace(0, len(views) - 1, n).round().astype(int)
    return [views[i] for i in idx]
