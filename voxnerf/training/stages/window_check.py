"""Stage window_check: the VoxNeRF sampler's window checked against the training frames' depth (issue #46)."""

from __future__ import annotations

import time
from dataclasses import dataclass

import torch

from voxnerf.config import TrainConfig
from voxnerf.model.samplers import VoxNeRFSampler
from voxnerf.model.voxnerf_model import VoxNeRFModel
from voxnerf.prior.loading import GeometryPrior
from voxnerf.training.pixels import TrainingPixels
from voxnerf.training.records import StageRecord
from voxnerf.training.stages.common import stage_record
from voxnerf.training.window_check import choose_sampler, first_hit_check, samples_near, share_outside

CHECK_PIXELS = 262_144  # training pixels with depth whose first hits are checked (a fixed random subset)
SAMPLED_RAYS = 8_192  # of those, rays both samplers sample at set-up


@dataclass
class WindowCheckStage:
    record: StageRecord
    summary: dict | None = None  # report.json's window_check
    sampler: str | None = None  # sampler 'auto''s choice ('voxnerf' or 'occgrid'); None for a sampler the config names


def window_check_stage(cfg: TrainConfig, model: VoxNeRFModel, pixels: TrainingPixels, depth_t: torch.Tensor | None,
                       prior_n: GeometryPrior | None, scale: float) -> WindowCheckStage:
    """The first hits cached for training (``pixels.hit_t``) against the depth maps' ray distances ``depth_t``
    [N, H, W] (normalised, NaN where none: the depth target stage's ``sensor_t``) on a fixed random subset of the
    pixels, and where the VoxNeRF sampler and the occupancy grid as it stands at set-up (seeded from the prior
    unless ``occgrid_seed`` is off) put their samples on a smaller one (:mod:`voxnerf.training.window_check`).
    Runs only for the VoxNeRF sampler with an octree and a sensor depth target (depth maps and the depth loss on);
    ``scale`` is normalised units per metre. For sampler ``auto`` the stage also makes its choice
    (:func:`~voxnerf.training.window_check.choose_sampler`), says it in its ``why`` and in the summary's
    ``sampler``."""
    t0 = time.perf_counter()
    sampler = model.sampler()
    if not isinstance(sampler, VoxNeRFSampler) or pixels.hit_t is None:
        why = "no octree" if cfg.sampling.may_use_window else f"sampler {cfg.sampling.sampler!r} has no window"
        return _with_choice(cfg, WindowCheckStage(stage_record("window_check", False, why, t0)), has_octree=False)
    if depth_t is None or not bool(torch.isfinite(depth_t).any()):
        return _with_choice(cfg, WindowCheckStage(stage_record(
            "window_check", False, "no sensor depth to check the window against", t0)), has_octree=True)
    with torch.no_grad():
        summary = _check(cfg, model, sampler, pixels, depth_t, prior_n, scale)
    near = summary["samples"]["near_surface"]
    why = (f"window centred on the {sampler.centre}: {summary['rays']} training rays with depth: first hit misses "
           f"every leaf on {summary['miss']:.1%}, "
           f"stops short on {summary['stop_short']:.1%}, passes the surface on {summary['pass_through']:.1%}; "
           f"half-window {100 * summary['half_window_m']:.1f} cm"
           + (f" against the prior's measured noise {100 * summary['prior_noise_m']:.1f} cm"
              if summary["prior_noise_m"] else "")
           + f"; samples near the surface: voxnerf {near['voxnerf']:.1%}, occupancy grid {near['occupancy_grid']:.1%}")
    return _with_choice(cfg, WindowCheckStage(stage_record("window_check", True, why, t0), summary), has_octree=True)


def _with_choice(cfg: TrainConfig, checked: WindowCheckStage, has_octree: bool) -> WindowCheckStage:
    """``checked`` with sampler ``auto``'s choice made from its summary (unchanged for a sampler the config names)."""
    if cfg.sampling.sampler != "auto":
        return checked
    name, why = choose_sampler(checked.summary, has_octree)
    checked.record = checked.record.model_copy(update={"why": f"{checked.record.why}; sampler 'auto': {name}, {why}"})
    if checked.summary is not None:
        checked.summary["sampler"] = {"chosen": name, "why": why}
    checked.sampler = name
    return checked


def _check(cfg: TrainConfig, model: VoxNeRFModel, sampler: VoxNeRFSampler, pixels: TrainingPixels,
           depth_t: torch.Tensor, prior_n: GeometryPrior | None, scale: float) -> dict:
    with_depth = torch.nonzero(torch.isfinite(depth_t).reshape(-1)).reshape(-1)
    gen = torch.Generator(device="cpu").manual_seed(0)
    order = torch.randperm(len(with_depth), generator=gen)[:CHECK_PIXELS].to(with_depth.device)
    pick = with_depth[order]

    def at(values: torch.Tensor | None):
        return None if values is None else values.reshape(-1)[pick].float().cpu().numpy()

    true_t = at(depth_t)
    summary = first_hit_check(at(pixels.hit_t), at(pixels.hit), true_t, sampler.half_window, scale,
                              at(pixels.pseudo_t), None if prior_n is None else prior_n.sigma)
    rays_idx = pick[:SAMPLED_RAYS]
    rays = model.ray_bundle(*pixels.rays(*pixels.index_of(rays_idx)))
    rays.hit_t, rays.hit = pixels.hit_t.reshape(-1)[rays_idx], pixels.hit.reshape(-1)[rays_idx]
    starts, ends = sampler(rays, False)
    voxnerf_mid = (0.5 * (starts + ends)).cpu().numpy()
    starts, ends = sampler.fallback(rays, False)
    grid_mid = (0.5 * (starts + ends)).cpu().numpy()
    sampled_true = true_t[:SAMPLED_RAYS]
    band = sampler.half_window
    summary["window"] = {"centre": sampler.centre, "width": sampler.width}  # the rule checked (config's sampling)
    summary["samples"] = {
        "rays": len(rays_idx),
        "band_m": float(band / scale),
        "outside_window": share_outside(voxnerf_mid, rays.hit_t.cpu().numpy(), rays.hit.cpu().numpy(), band),
        "near_surface": {"voxnerf": samples_near(voxnerf_mid, sampled_true, band),
                         "occupancy_grid": samples_near(grid_mid, sampled_true, band)},
        "grid": "seeded from the prior" if cfg.sampling.occgrid_seed else "all occupied (occgrid_seed off)",
    }
    return summary
