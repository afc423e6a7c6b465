"""voxnerf.devices: device names resolved, unavailable or unknown devices refused with the flag's name; the record of
how a process computes."""

from __future__ import annotations

import os

import pytest
import torch

from voxnerf.devices import compute_environment, resolve_device
from voxnerf.errors import VoxNeRFError
from voxnerf.model import hash_kernel
from voxnerf.prior import octree


def test_auto_picks_cuda_only_when_present():
    expected = "cuda" if torch.cuda.is_available() else "cpu"
    assert resolve_device("auto").type == expected
    assert resolve_device().type == expected


def test_cpu_is_always_available():
    assert resolve_device("cpu") == torch.device("cpu")


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
@pytest.mark.parametrize("name", ["cuda", "cuda:1"])
def test_cuda_without_cuda_is_refused(name):
    with pytest.raises(VoxNeRFError, match=f"--device {name}: CUDA is not available"):
        resolve_device(name)


def test_cuda_auto_uses_cuda_when_the_runtime_reports_it(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert resolve_device("auto") == torch.device("cuda")
    assert resolve_device("cuda:0") == torch.device("cuda:0")


@pytest.mark.parametrize("name", ["gpu", "mps", "", "CPU"])
def test_unknown_names_are_refused(name):
    with pytest.raises(VoxNeRFError, match="expected auto, cpu or cuda"):
        resolve_device(name)


def test_compute_environment_records_threads_openmp_settings_and_kernels(monkeypatch):
    monkeypatch.setenv("OMP_WAIT_POLICY", "PASSIVE")
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    record = compute_environment(torch.device("cpu"))
    assert record["device"] == "cpu" and record["torch"] == torch.__version__
    assert record["threads"] == torch.get_num_threads() and record["interop_threads"] >= 1
    assert 1 <= record["cpus"] <= (os.cpu_count() or 1)
    assert record["omp_wait_policy"] == "PASSIVE" and record["omp_num_threads"] is None
    assert record["hash_kernel"] == hash_kernel.loaded() and record["octree_kernel"] == octree.kernel_loaded()
    hash_kernel.available(), octree.kernel_available()  # load them (built once, cached)
    record = compute_environment(torch.device("cpu"))
    assert record["hash_kernel"] == hash_kernel.available() and record["octree_kernel"] == octree.kernel_available()
    monkeypatch.delenv("OMP_WAIT_POLICY")
    assert compute_environment(torch.device("cpu"))["omp_wait_policy"] is None
