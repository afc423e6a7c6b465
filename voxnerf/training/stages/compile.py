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


def use_inductor_cache_dir() -> None:
    """Point inductor's cache at :func:`inductor_cache_dir` unless the user chose one (``TORCHINDUCTOR_CACHE_DIR``).

    Importing ``torch._dynamo`` sets the variable to inductor's default under the temporary directory, and the
    set-up imports it before this stage (building the model's Adam optimizer does), so a value equal to that
    default counts as unset; inductor reads the variable each time it opens its caches, so pointing it here
    before the first compilation is enough."""
    from torch._inductor.runtime.cache_dir_utils import default_cache_dir

    current = os.environ.get("TORCHINDUCTOR_CACHE_DIR")
    if current is None or os.path.abspath(current) == os.path.abspath(default_cache_dir()):
        os.environ["TORCHINDUCTOR_CACHE_DIR"] = str(inductor_cache_dir())


def compile_stage(cfg: TrainConfig, loss_fn: LossFn) -> CompileStage:
    """The step's loss function through ``torch.compile`` (unless disabled). Inductor's cache goes to
    :func:`inductor_cache_dir` (:func:`use_inductor_cache_dir`), so a later run of the same configuration, from
    the command line or a service's worker of the same user, loads the compiled step instead of compiling it
    again."""
    t0 = time.perf_counter()
    if cfg.run.compile:
        use_inductor_cache_dir()
        return CompileStage(torch.compile(loss_fn, dynamic=False), t0)
    return CompileStage(loss_fn, t0, stage_record("compile", False, "disabled (--no-compile)", t0))
