"""The ``voxnerf_device`` remote-control command (:data:`app.core.celery_app.DEVICE_REPORT`): a worker answers the
device its tasks run on and, for a GPU, the memory in use on it, which ``GET /metrics`` exposes.

The memory is read from ``nvidia-smi`` (the driver's view: every process on the GPU), never through torch: this
runs in the worker's main process, which forks the pool's processes, and a CUDA context made there would be unusable
in them. A worker whose device is the CPU, or that has no ``nvidia-smi``, reports its device alone.
"""

from __future__ import annotations

import shutil
import subprocess

from celery.worker.control import inspect_command

from app.core.celery_app import DEVICE_REPORT
from app.core.settings import get_settings

MiB = 1024 * 1024
SMI_TIMEOUT_S = 5.0


def gpu_index(device: str) -> int | None:
    """The CUDA device index a ``VOXNERF_DEVICE`` names (``cuda:1`` -> 1; ``cuda`` and ``auto`` -> 0), None for
    the CPU."""
    if device == "cpu":
        return None
    _, _, index = device.partition(":")
    return int(index) if index.isdigit() else 0


def parse_smi_memory(text: str) -> tuple[int, int]:
    """``(used, total)`` bytes from ``nvidia-smi --query-gpu=memory.used,memory.total --format=csv,noheader,
    nounits`` (one line of MiB, e.g. ``"1234, 143771"``); ValueError for anything else."""
    used, total = (int(part.strip()) for part in text.strip().splitlines()[0].split(","))
    return used * MiB, total * MiB


def device_report(device: str) -> dict:
    """``{"device": ...}``, with ``memory_used_bytes`` and ``memory_total_bytes`` for a GPU ``nvidia-smi`` can
    read."""
    index = gpu_index(device)
    smi = shutil.which("nvidia-smi")
    if index is None or smi is None:
        return {"device": "cpu" if index is None or device == "auto" else device}
    try:
        result = subprocess.run([smi, f"--id={index}", "--query-gpu=memory.used,memory.total",
                                 "--format=csv,noheader,nounits"], capture_output=True, text=True,
                                timeout=SMI_TIMEOUT_S, check=True)
        used, total = parse_smi_memory(result.stdout)
    except (OSError, subprocess.SubprocessError, ValueError):
        return {"device": f"cuda:{index}"}
    return {"device": f"cuda:{index}", "memory_used_bytes": used, "memory_total_bytes": total}


@inspect_command(name=DEVICE_REPORT)
def _device_report_command(_state) -> dict:
    return device_report(get_settings().device)
