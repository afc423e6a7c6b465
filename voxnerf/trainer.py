"""Backward-compatible facade of :mod:`voxnerf.training` (``from voxnerf.trainer import train`` keeps working).

The engine lives in ``voxnerf/training/``: set-up stages (``setup.py``, ``stages/``), the loop (``loop.py``) and its
callbacks (``callbacks.py``), and ``train()`` in ``run.py``, which returns a
:class:`~voxnerf.training.records.TrainReport` and sends :class:`~voxnerf.training.records.ProgressEvent`
objects to ``on_progress``.
"""

from __future__ import annotations

from voxnerf.errors import TrainingDiverged
from voxnerf.model.losses import PAPER_BETA
from voxnerf.training.budget import Budget
from voxnerf.training.callbacks import DEFAULT_EVAL_SECONDS_PER_RAY, ProgressCallback
from voxnerf.training.eval_passes import eval_views_of
from voxnerf.training.pixels import TrainingPixels
from voxnerf.training.records import EvalRecord, ProgressEvent, StageRecord, TrainReport
from voxnerf.training.run import REPORT, train
from voxnerf.training.stages import COVERAGE_RAYS, MIN_PRIOR_COVERAGE
from voxnerf.training.step import DEPTH_BETA_PER_SIGMA

__all__ = [
    "COVERAGE_RAYS", "DEFAULT_EVAL_SECONDS_PER_RAY", "DEPTH_BETA_PER_SIGMA", "MIN_PRIOR_COVERAGE", "PAPER_BETA",
    "REPORT", "Budget", "EvalRecord", "ProgressCallback", "ProgressEvent", "StageRecord", "TrainReport",
    "TrainingDiverged", "TrainingPixels", "eval_views_of", "train",
]
