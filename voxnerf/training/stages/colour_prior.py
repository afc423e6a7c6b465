"""Stage colour_prior: the training pixels' colours pooled at their depth targets (:mod:`voxnerf.model.colour_prior`),
what a rendered ray shows where it meets the prior but the field leaves it transparent (``render_background``
'nearest_seen')."""

from __future__ import annotations

import time
from dataclasses import dataclass

import torch

from voxnerf.config import TrainConfig
from voxnerf.model.colour_prior import ColourPrior
from voxnerf.training.pixels import TrainingPixels, rays_in_chunks
from voxnerf.training.records import StageRecord
from voxnerf.training.stages.common import stage_record


@dataclass
class ColourPriorStage:
    record: StageRecord
    prior: ColourPrior | None = None


def colour_prior_stage(cfg: TrainConfig, has_octree: bool, pixels: TrainingPixels) -> ColourPriorStage:
    """The colour prior of ``pixels`` where ``cfg`` renders over it: ``render_background`` 'nearest_seen', the
    voxnerf sampler (``cfg``'s sampler resolved, ``has_octree``: its octree built) and a depth target."""
    t0 = time.perf_counter()
    sampler = cfg.sampling.sampler
    if cfg.model.render_background != "nearest_seen":
        why = f"render_background {cfg.model.render_background!r}: rendered rays show the background colour"
    elif sampler != "voxnerf" or not has_octree:
        why = f"the run samples without the prior's octree (sampler {sampler}): a rendered ray has no prior hit"
    elif pixels.depth_t is None:
        why = "no depth target: the training pixels have no place in the scene"
    else:
        return _pooled(pixels, t0)
    return ColourPriorStage(stage_record("colour_prior", False, why, t0))


def _pooled(pixels: TrainingPixels, t0: float) -> ColourPriorStage:
    points, colours = [], []
    flat_t = pixels.depth_t.reshape(-1)
    flat_rgb = pixels.images.reshape(-1, 3)  # not always contiguous (an imported scan's images)
    real = pixels.real_pixels()
    placed = real[torch.isfinite(flat_t[real])]
    for f, _, origins, dirs in rays_in_chunks(pixels, placed):
        points.append(origins + flat_t[f, None] * dirs)
        colours.append(flat_rgb[f].float() / 255.0)
    if not points:
        return ColourPriorStage(stage_record("colour_prior", False, "no training pixel has a depth target", t0))
    prior = ColourPrior.pool(torch.cat(points), torch.cat(colours))
    summary = prior.summary()
    share = len(placed) / max(len(real), 1)
    why = (f"{summary['pixels']} training pixels ({share:.1%}) at their depth targets, pooled "
           f"in {summary['levels']} levels from {summary['finest_cells']} cells across the box: the colour behind "
           f"a rendered ray where it meets the prior")
    return ColourPriorStage(stage_record("colour_prior", True, why, t0), prior)
