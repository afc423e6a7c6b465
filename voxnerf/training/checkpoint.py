"""The checkpoint (``run_dir/checkpoint.pt``, written atomically) and the report file."""

from __future__ import annotations

import io
import json
from pathlib import Path

import torch

from voxnerf.errors import TrainingDiverged
from voxnerf.image_io import write_atomic
from voxnerf.model import VoxNeRFModel
from voxnerf.scene import Scene
from voxnerf.training.budget import Budget
from voxnerf.training.records import EvalRecord, TrainReport


def load_previous(path: Path, resume: bool) -> dict | None:
    """The checkpoint a resumed run continues from, or None (no resume, or none written yet)."""
    return torch.load(path, map_location="cpu", weights_only=False) if resume and path.is_file() else None


def save_atomic_torch(obj: dict, path: Path) -> None:
    buffer = io.BytesIO()
    torch.save(obj, buffer)
    write_atomic(path, buffer.getvalue())


def write_report(report: TrainReport, path: Path) -> None:
    """``report.json``: :meth:`TrainReport.to_json_dict`, numbers that JSON lacks (numpy) as floats."""
    write_atomic(path, json.dumps(report.to_json_dict(), indent=2, default=float).encode())


def params_finite(model: VoxNeRFModel) -> bool:
    return all(bool(torch.isfinite(p).all()) for p in model.field.parameters())


class CheckpointWriter:
    """Saves model, optimiser, iteration, training seconds and history to ``path``; refuses (TrainingDiverged)
    when the weights are no longer finite, so the last good checkpoint stays."""

    def __init__(self, path: Path, model: VoxNeRFModel, optimizer: torch.optim.Optimizer, budget: Budget,
                 history: list[EvalRecord], scene: Scene) -> None:
        self.path, self.model, self.optimizer, self.budget = path, model, optimizer, budget
        self.history, self.scene = history, scene

    def __call__(self, iteration: int) -> None:
        if not params_finite(self.model):
            raise TrainingDiverged(f"weights became NaN/inf before iteration {iteration}")
        save_atomic_torch(self.contents(iteration), self.path)

    def contents(self, iteration: int) -> dict:
        first = self.scene.intrinsics(self.scene.train_indices[0])
        return {
            "model": self.model.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "iteration": iteration,
            "train_seconds": self.budget.train_seconds,
            "history": [h.to_json_dict() for h in self.history],
            "default_intrinsics": first.as_dict(),
            "depth_unit_scale": self.scene.depth_unit_scale,
            "scene_dir": str(self.scene.root),
        }
