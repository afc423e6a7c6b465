"""How strongly the field's parameters decay: ``field_weight_decay`` ``auto``, from the training images' noise.

A hash grid has far more features than a handful of small images have pixels, so given time it fits the noise
of each training image as well as the scene: the views between and beyond them then get worse as training goes
on (docs/engine.md, 'Levers of sparse-view training'; docs/benchmarks.md, 'The tuning suite'). An L2 penalty
on the parameters is the Gaussian prior of a
maximum a posteriori fit; against a mean squared error it weighs ``sigma^2 / tau^2`` for image noise of variance
``sigma^2`` and a prior of variance ``tau^2``. ``auto`` therefore sets the decay to ``NOISE_DECAY * sigma^2``,
sigma measured on the training images (:mod:`voxnerf.data.image_noise`) and ``NOISE_DECAY`` (``1 / tau^2``) chosen on
the tuning suite: the capture-like rooms' sensor noise gets a decay that keeps the features from fitting it.
Clean images (rendered rooms, the real redkitchen after ``--downscale 2``) read 0.3-0.8 of 8-bit levels, which
is the measure's own floor (rounding to 8 bits and fine texture), not noise: below ``NOISE_FLOOR`` the run has
no decay at all. A value other than ``auto`` is used as given.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

from voxnerf.config import TrainConfig
from voxnerf.data.image_noise import images_noise_sigma
from voxnerf.data.scene import Scene
from voxnerf.training.records import StageRecord

# 1 / tau^2 of the docstring: the capture-like rooms' noise (sigma 7 / 255) gets a decay of 3e-7
NOISE_DECAY = 4e-4
# A noise sigma below this (in [0, 1] units) is what a clean image reads: no decay
NOISE_FLOOR = 2.0 / 255.0
# The noise is measured on at most this many training images, evenly spaced: a median over them is one figure
# for the scan, and the measure's cost (charged to max_seconds) stays bounded whatever the scan's size
NOISE_IMAGES = 32


@dataclass
class WeightDecayStage:
    record: StageRecord
    cfg: TrainConfig  # ``cfg`` with a number in field_weight_decay


def weight_decay_stage(cfg: TrainConfig, scene: Scene) -> WeightDecayStage:
    """Resolve ``auto`` in ``cfg.schedule.field_weight_decay`` from the noise of ``scene``'s (loaded) training
    images."""
    t0 = time.perf_counter()
    if cfg.schedule.field_weight_decay == "auto":
        step = max(1, -(-len(scene.train_indices) // NOISE_IMAGES))  # ceil: at most NOISE_IMAGES of them
        images = [scene.images[i] for i in scene.train_indices[::step] if scene.images and scene.images[i] is not None]
        sigma = images_noise_sigma(images)
        clean = sigma < NOISE_FLOOR
        cfg = cfg.updated(field_weight_decay=0.0 if clean else NOISE_DECAY * sigma**2)
        why = (f"auto: the training images' noise sigma {sigma * 255:.2f}/255 (median of {len(images)} images), "
               + (f"below {NOISE_FLOOR * 255:g}/255: clean" if clean else f"decay {NOISE_DECAY:g} x sigma^2"))
    else:
        why = "as configured"
    decay = float(cfg.schedule.field_weight_decay)
    text = f"{decay:.3g} on the field's parameters; {why}" if decay > 0 else f"none; {why}"
    return WeightDecayStage(StageRecord(name="weight_decay", ran=decay > 0, why=text,
                                        seconds=time.perf_counter() - t0), cfg)
