"""Stage hash_kernel: whether the hash encoding runs in its C kernel."""

from __future__ import annotations

import time

import torch

from voxnerf.config import TrainConfig
from voxnerf.model import hash_kernel
from voxnerf.training.records import StageRecord
from voxnerf.training.stages.common import stage_record


def hash_kernel_stage(cfg: TrainConfig, device: torch.device) -> StageRecord:
    t0 = time.perf_counter()
    if device.type != "cpu":
        return stage_record("hash_kernel", False, f"on {device.type} the hash encoding stays in PyTorch", t0)
    if not cfg.run.hash_kernel:
        return stage_record("hash_kernel", False, "disabled (--no-hash-kernel): the hash encoding stays in PyTorch", t0)
    if hash_kernel.available():
        return stage_record("hash_kernel", True,
                       "the hash encoding runs in its C kernel (voxnerf/model/hashgrid.c; built once, cached)", t0)
    return stage_record("hash_kernel", False, f"C kernel unavailable ({hash_kernel.unavailable_reason()}): the hash "
                   "encoding stays in PyTorch", t0)
