"""Device selection: CUDA when present, CPU otherwise, overridable by name."""

from __future__ import annotations

import torch

from voxnerf.errors import VoxNeRFError


def resolve_device(name: str = "auto") -> torch.device:
    """``auto`` -> ``cuda`` if available else ``cpu``; ``cpu``/``cuda[:N]`` as given (error if unavailable)."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise VoxNeRFError(f"--device {name}: CUDA is not available on this machine")
    if name != "cpu" and not name.startswith("cuda"):
        raise VoxNeRFError(f"--device {name}: expected auto, cpu or cuda[:N]")
    return torch.device(name)
