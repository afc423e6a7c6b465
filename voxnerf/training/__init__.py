"""Training, as set-up stages and a short loop with callbacks.

``voxnerf.training.records`` (the report, stage, evaluation and progress-event models) imports no torch, and
neither does importing this package: ``train`` and the other engine names below load on first use, e.g.
``from voxnerf.training import train`` (the same as ``from voxnerf.training.run import train``).

Modules: ``records`` (what travels out), ``budget`` (time budget), ``stages`` (set-up stages), ``pixels``
(training pixels and batches), ``step`` (loss, step, divergence guard), ``loop`` (the loop), ``callbacks``
(its periodic duties), ``evals`` (progress and final evaluations), ``checkpoint`` (checkpoint and report
files), ``run`` (``train()``).
"""

from __future__ import annotations

import importlib
from typing import Any

_LAZY = {
    "train": "voxnerf.training.run",
    "REPORT": "voxnerf.training.run",
    "Budget": "voxnerf.training.budget",
    "eval_views_of": "voxnerf.training.evals",
    "TrainingPixels": "voxnerf.training.pixels",
    "run_loop": "voxnerf.training.loop",
}

__all__ = sorted(_LAZY)


def __getattr__(name: str) -> Any:
    if name not in _LAZY:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(_LAZY[name]), name)
