"""Stage depth_target: the depth loss's target per training pixel (sensor or prior) and its beta."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from voxnerf.config import TrainConfig
from voxnerf.data.scene import Scene, SceneTransform
from voxnerf.model.losses import PAPER_BETA
from voxnerf.prior.depth_fusion import DepthNoise, FusedPrior, fit_noise
from voxnerf.prior.loading import GeometryPrior
from voxnerf.training.pixels import TrainingPixels, padded_stack, sensor_ray_distance
from voxnerf.training.records import StageRecord
from voxnerf.training.stages.common import stage_record
from voxnerf.training.stages.load_scene import check_sensor_depth
from voxnerf.training.step import DEPTH_BETA_PER_SIGMA


def depth_source(cfg: TrainConfig, scene: Scene, prior: GeometryPrior | None) -> tuple[str, str]:
    """What the depth loss compares with ('sensor', 'prior' or 'none') and why (``TrainConfig.depth_source``).

    Raises SceneError when 'sensor' is asked for and no training frame has a depth map.
    """
    check_sensor_depth(cfg, scene)
    has_sensor = any(scene.depths[i] is not None for i in scene.train_indices)
    if not cfg.loss.depth_loss or cfg.loss.depth_source == "none":
        return "none", "depth loss disabled" if not cfg.loss.depth_loss else "depth_source 'none'"
    if cfg.loss.depth_source == "auto":
        if has_sensor:
            return "sensor", "auto: the training frames have depth maps"
        return ("prior", "auto: no depth maps, the prior's depth") if prior is not None else (
            "none", "auto: no depth maps and no prior")
    if cfg.loss.depth_source == "prior" and prior is None:
        return "none", "depth_source 'prior' but there is no prior"
    return cfg.loss.depth_source, f"depth_source {cfg.loss.depth_source!r}"


@dataclass
class DepthTargetStage:
    """The depth loss's target per training pixel and its log-Huber beta.

    ``target_t`` [N, H, W] normalised ray distances (NaN where none); ``beta_scale`` [N, H, W] each pixel's beta
    over ``beta`` (None: ``beta`` everywhere); ``beta`` in scene units; ``summary`` for the report; ``sensor_t``
    [N, H, W] the sensor's ray distances alone (NaN where it measured nothing; None without sensor depth).
    """

    record: StageRecord
    target_t: torch.Tensor | None = None
    beta_scale: torch.Tensor | None = None
    beta: float | None = None
    summary: dict | None = None
    sensor_t: torch.Tensor | None = None


BETA_SCALE_RANGE = (0.1, 10.0)  # a pixel's beta stays within these factors of the run's


def depth_target_stage(cfg: TrainConfig, scene: Scene, prior: GeometryPrior | None, fused: FusedPrior | None,
                       pixels: TrainingPixels, transform: SceneTransform) -> DepthTargetStage:
    """Sensor depth where it is valid and the prior's depth elsewhere ('sensor'), the prior's ('prior'), or none.

    For sensor depth, beta follows the depth noise: ``DEPTH_BETA_PER_SIGMA x sigma(z)``, sigma measured against
    the fused prior (fused) or the prior's depth along the same rays (a prior file), unless ``depth_beta`` is
    set.
    """
    t0 = time.perf_counter()
    source, why = depth_source(cfg, scene, prior)
    if source == "none":
        return DepthTargetStage(stage_record("depth_target", False, why, t0))
    base_sigma = prior.sigma if prior is not None else None
    if source == "prior":
        beta = cfg.loss.depth_beta or DEPTH_BETA_PER_SIGMA * base_sigma
        valid = pixels.fraction(torch.isfinite(pixels.pseudo_t))
        summary = {"source": "prior", "why": why, "prior_fraction": valid, "beta": beta}
        return DepthTargetStage(stage_record("depth_target", True, f"{why}: the prior's depth on {valid:.1%} of "
                                        "training pixels", t0), pixels.pseudo_t, None, beta, summary)
    z = torch.from_numpy(padded_stack([_depth_or_nan(scene, i) for i in scene.train_indices], np.nan))
    z = z.to(pixels.images.device)
    sensor_t = sensor_ray_distance(pixels, z, transform.scale)
    noise = fused.noise if fused is not None else measure_noise_against(sensor_t, pixels.pseudo_t, z, transform,
                                                                         base_sigma)
    sensor_ok = torch.isfinite(sensor_t)
    target = sensor_t if pixels.pseudo_t is None else torch.where(sensor_ok, sensor_t, pixels.pseudo_t)
    summary = {"source": "sensor", "why": why, "sensor_fraction": pixels.fraction(sensor_ok),
               "prior_fraction": pixels.fraction(~sensor_ok & torch.isfinite(target))}
    text = (f"{why}: sensor depth on {summary['sensor_fraction']:.1%} of training pixels, the prior's on "
            f"{summary['prior_fraction']:.1%}; ")
    if cfg.loss.depth_beta or noise is None:
        beta = cfg.loss.depth_beta or (DEPTH_BETA_PER_SIGMA * base_sigma if base_sigma else PAPER_BETA)
        rule = "given (depth_beta)" if cfg.loss.depth_beta else "no surface to measure the depth noise against"
        summary |= {"beta": beta, "beta_rule": rule}
        return DepthTargetStage(stage_record("depth_target", True, text + f"beta {beta:.4g}: {rule}", t0), target,
                                None, beta, summary, sensor_t)
    base_sigma = base_sigma or noise.at_median
    beta = DEPTH_BETA_PER_SIGMA * base_sigma
    beta_scale = torch.where(sensor_ok, (noise.s0 + noise.s2 * z * z) / base_sigma, torch.ones_like(z))
    summary |= {"noise": noise.as_dict(), "beta": beta, "beta_rule": f"{DEPTH_BETA_PER_SIGMA:g} x sigma(z)"}
    text += f"beta {DEPTH_BETA_PER_SIGMA:g} x sigma(z), {noise.describe()}"
    return DepthTargetStage(stage_record("depth_target", True, text, t0), target,
                            beta_scale.clamp(*BETA_SCALE_RANGE), beta, summary, sensor_t)


def _depth_or_nan(scene: Scene, index: int) -> np.ndarray:
    """Frame ``index``'s depth on its image's pixels (float32 [h, w]), all NaN when it has none."""
    depth = scene.depths[index]
    return np.full(scene.images[index].shape[:2], np.nan, np.float32) if depth is None else depth.astype(np.float32)


def measure_noise_against(sensor_t: torch.Tensor, prior_t: torch.Tensor | None, z: torch.Tensor,
                          transform: SceneTransform, prior_sigma: float | None) -> DepthNoise | None:
    """Depth noise of the sensor against the prior's depth along the same rays (scene units); None without a
    prior or when no pixel has both."""
    if prior_t is None or prior_sigma is None:
        return None
    both = torch.isfinite(sensor_t) & torch.isfinite(prior_t)
    cos = z[both] * transform.scale / sensor_t[both]  # z per unit of ray distance
    residual = ((sensor_t[both] - prior_t[both]) / transform.scale * cos).double().cpu().numpy()
    depth = z[both].double().cpu().numpy()
    keep = np.abs(residual) < DEPTH_BETA_PER_SIGMA * prior_sigma
    return fit_noise(depth[keep], residual[keep], prior_sigma) if keep.any() else None
