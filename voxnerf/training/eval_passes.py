"""Evaluations during and after training: the views of the evaluation splits, progress evaluations (a few
views per split, or every view for ``--eval-at``) and the final evaluation, each appending an EvalRecord."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from voxnerf.config import TrainConfig
from voxnerf.data.scene import Scene, SceneTransform
from voxnerf.inference.evaluation import EvaluationStopped, EvalView, evaluate_views, view_names
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


def progress_eval(
    model: VoxNeRFModel,
    views: EvalViews,
    cfg: TrainConfig,
    history: list[EvalRecord],
    budget: Budget,
    iteration: int,
    loss: float,
    full: bool,
    warm_up: bool = False,
) -> tuple[float, float]:
    """Evaluate a few views per split (all of them when ``full``) and append the record to ``history``;
    returns (seconds spent, seconds per ray).

    ``warm_up`` (the run's first evaluation) renders one view before the timed ones: what a process pays once
    (compiling the render, a GPU's first kernels) is in the seconds spent but not in the seconds per ray, which
    sizes the final evaluation's reserve of the budget."""
    t0 = time.perf_counter()
    elapsed, wall = budget.train_seconds, budget.wall
    subset = {name: (v if full else spread(v, cfg.evaluation.eval_views)) for name, v in views.items()}
    if warm_up:
        split, split_views = next(iter(subset.items()))
        evaluate_views(model, {split: split_views[:1]}, cfg, out_dir=None, lpips=False)
    t_timed = time.perf_counter()
    metrics = evaluate_views(model, subset, cfg, out_dir=None, lpips=full, half_image=full)
    t_end = time.perf_counter()
    spent, per_ray = t_end - t0, (t_end - t_timed) / max(view_rays(subset), 1)
    entry = EvalRecord(
        elapsed_s=round(elapsed, 3), wall_s=round(wall, 3), iteration=iteration,
        loss=loss if math.isfinite(loss) else None, psnr={k: m["psnr"] for k, m in metrics.items()},
    )
    if full:
        entry.full = True
        entry.ssim = {k: m["ssim"] for k, m in metrics.items()}
        entry.lpips = {k: m["lpips"] for k, m in metrics.items()}
        entry.half = {k: m["half"] for k, m in metrics.items()}
        entry.progress_psnr = progress_views_psnr(metrics, views, cfg.evaluation.eval_views)
    history.append(entry)
    return spent, per_ray


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
