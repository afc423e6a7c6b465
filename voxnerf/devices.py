"""Device selection: CUDA when present, CPU otherwise, overridable by name; and the record of how a process
computes (threads, OpenMP settings, C kernels) that report.json keeps."""

from __future__ import annotations

import os

import torch

from voxnerf.errors import VoxNeRFError
from voxnerf.model import hash_kernel
from voxnerf.prior import octree


def resolve_device(name: str = "auto") -> torch.device:
    """``auto`` -> ``cuda`` if available else ``cpu``; ``cpu``/``cuda[:N]`` as given (error if unavailable)."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise VoxNeRFError(f"--device {name}: CUDA is not available on this machine")
    if name != "cpu" and not name.startswith("cuda"):
        raise VoxNeRFError(f"--device {name}: expected auto, cpu or cuda[:N]")
    return torch.device(name)


def compute_environment(device: torch.device) -> dict[str, str | int | bool | None]:
    """How this process computes, as report.json's ``runtime`` records it: the device, torch's intra-op and
    inter-op threads, the cores the process may run on, the OpenMP settings it loaded with (the environment's
    ``OMP_WAIT_POLICY`` and ``OMP_NUM_THREADS``, None where unset: the runtime's default) and whether the
    process has loaded the plain-C kernels (hash encoding, octree tracing); asking builds nothing. A run trained
    by a service worker and one trained by ``voxnerf train`` on the same machine record the same values
    (``tests/service/test_service_runtime.py``)."""
    return {
        "device": str(device),
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "interop_threads": torch.get_num_interop_threads(),
        "cpus": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
        "omp_num_threads": os.environ.get("OMP_NUM_THREADS"),
        "hash_kernel": hash_kernel.loaded(),
        "octree_kernel": octree.kernel_loaded(),
    }
