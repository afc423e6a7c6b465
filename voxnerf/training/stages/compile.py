"""Stage compile: the step's loss function through torch.compile, with a persistent inductor cache."""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from voxnerf import native
from voxnerf.config import TrainConfig
from voxnerf.training.records import StageRecord
from voxnerf.training.stages.common import stage_record
from voxnerf.training.step import LossFn


def inductor_cache_dir() -> Path:
    """``$VOXNERF_CACHE/inductor`` (beside the C kernels, :func:`voxnerf.native.cache_dir`): unlike inductor's
    default under the temporary directory, it outlives a reboot."""
    return native.cache_dir() / "inductor"


@dataclass
class CompileStage:
    """The step's loss function, compiled or not. A compiled one's record comes after the first step (its
    compile time is that step's): ``record`` is None until then, timed from ``started``."""

    loss_fn: LossFn
    started: float
    record: StageRecord | None = None


def compile_stage(cfg: TrainConfig, loss_fn: LossFn) -> CompileStage:
    """The step's loss function through ``torch.compile`` (unless disabled). Inductor's cache goes to
    :func:`inductor_cache_dir` unless ``TORCHINDUCTOR_CACHE_DIR`` says otherwise, so a later run of the same
    configuration loads the compiled step instead of compiling it again."""
    t0 = time.perf_counter()
    if cfg.run.compile:
        os.environ.setdefault("TORCHINDUCTOR_CACHE_DIR", str(inductor_cache_dir()))
        return CompileStage(torch.compile(loss_fn, dynamic=False), t0)
    return CompileStage(loss_fn, t0, stage_record("compile", False, "disabled (--no-compile)", t0))
