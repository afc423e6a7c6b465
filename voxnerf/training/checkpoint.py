"""The checkpoint (``run_dir/checkpoint.pt``, written atomically) and the report file.

A checkpoint holds only tensors, numbers, strings, None, and dicts, lists and tuples of them: saving refuses
anything else (:func:`check_plain`) and loading unpickles with ``weights_only=True`` (:func:`load_checkpoint`),
so a checkpoint written by someone else cannot run code in the process that loads it.
"""

from __future__ import annotations

import io
import json
import os
import pickle
import re
from pathlib import Path
from typing import BinaryIO

import torch

from voxnerf.data.image_io import write_atomic
from voxnerf.data.scene import Scene
from voxnerf.errors import RunError, TrainingDiverged
from voxnerf.model.voxnerf_model import VoxNeRFModel
from voxnerf.training.budget import Budget
from voxnerf.training.records import EvalRecord, TrainReport
from voxnerf.training.weight_average import WeightAverage

PLAIN_LEAVES = (torch.Tensor, bool, int, float, str, type(None))


def check_plain(obj: object, where: str = "checkpoint") -> None:
    """Raise TypeError naming the key path (e.g. ``checkpoint/model/config``) of the first value that is not a
    tensor, number, string or None, or a dict (string or integer keys), list or tuple of those."""
    if isinstance(obj, dict):
        for key, value in obj.items():
            if not isinstance(key, (str, int)):
                raise TypeError(f"{where}: key {key!r} is a {type(key).__name__}, not a string or integer")
            check_plain(value, f"{where}/{key}")
    elif isinstance(obj, (list, tuple)):
        for i, value in enumerate(obj):
            check_plain(value, f"{where}[{i}]")
    elif not isinstance(obj, PLAIN_LEAVES):
        raise TypeError(f"{where}: a {type(obj).__module__}.{type(obj).__name__} cannot go in a checkpoint "
                        "(tensors, numbers, strings, None, dicts and lists only)")


def _refusal(exc: pickle.UnpicklingError) -> str:
    """One line on why ``weights_only`` unpickling stopped (torch's own text advises turning it off: left out).

    A global (a class or function the file names) is how a pickle reaches code: the file is *refused*; any
    other stop (an unknown opcode: not a pickle) leaves it *unreadable*.
    """
    text = str(exc)
    named = re.search(r"GLOBAL ([\w.]+)", text)
    if named:
        return f"refused: it names {named.group(1)}, not only tensors, numbers, strings, dicts and lists; not loaded"
    _, marker, rest = text.partition("WeightsUnpickler error:")
    detail = _one_line(rest.split("Check the documentation")[0]) if marker else "not a checkpoint"
    return f"unreadable checkpoint (UnpicklingError: {detail})"


def load_checkpoint(path: Path, map_location: str | torch.device = "cpu", opened: BinaryIO | None = None) -> dict:
    """The dict saved at ``path``, unpickled with ``weights_only=True``: nothing in the file is called.

    ``opened``: the file already open (read from it instead of opening ``path``, which then only names it in
    messages), so a caller that looked at the open file (its inode, size and time) loads exactly that file even
    when a newer checkpoint is renamed over ``path`` meanwhile. Raises RunError naming ``path`` when the file
    is not a checkpoint: unreadable, truncated, not a dict, or carrying any other object (a pickled callable is
    refused before it runs).
    """
    try:
        state = torch.load(path if opened is None else opened, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as exc:
        raise RunError(f"{path}: {_refusal(exc)}") from None
    # EOFError: an empty file; RuntimeError: not a torch zip; OSError: unreadable; and whatever else a
    # hostile or damaged file makes the (restricted) unpickler raise: IndexError, KeyError, AssertionError...
    except Exception as exc:
        raise RunError(f"{path}: unreadable checkpoint ({type(exc).__name__}: {_one_line(exc)})") from None
    if not isinstance(state, dict):
        raise RunError(f"{path}: unreadable checkpoint (holds a {type(state).__name__}, not a dict)")
    return state


def _one_line(exc: object, limit: int = 200) -> str:
    why = " ".join(str(exc).split())  # load_state_dict lists its mismatches line by line
    return why if len(why) <= limit else f"{why[:limit]}..."


def load_previous(path: Path, resume: bool) -> dict | None:
    """The checkpoint a resumed run continues from (:func:`load_checkpoint`), or None (no resume, or none
    written yet)."""
    return load_checkpoint(path) if resume and path.is_file() else None


def scene_dir_to_store(scene_root: Path, run_dir: Path) -> str | None:
    """The scene directory as a checkpoint in ``run_dir`` records it: relative to the run directory
    (``../../scenes/<id>`` in the service's data directory), so a checkpoint names no server path and a data
    directory moved or mounted elsewhere keeps finding its scenes; None where no relative path exists (another
    drive on Windows)."""
    try:
        return Path(os.path.relpath(Path(scene_root).resolve(), Path(run_dir).resolve())).as_posix()
    except ValueError:
        return None


def stored_scene_dir(value: str | None, run_dir: Path) -> str | None:
    """The scene directory a checkpoint in ``run_dir`` recorded: a relative one (:func:`scene_dir_to_store`)
    resolved against ``run_dir``, an absolute one (checkpoints from before) as it is, None as None."""
    if not value:
        return None
    return str(Path(value) if Path(value).is_absolute() else (Path(run_dir) / value).resolve())


def save_atomic_torch(obj: dict, path: Path) -> None:
    """``torch.save`` of ``obj`` to ``path``, atomically; TypeError (:func:`check_plain`) when ``obj`` holds
    anything ``weights_only`` loading would refuse."""
    check_plain(obj)
    buffer = io.BytesIO()
    torch.save(obj, buffer)
    write_atomic(path, buffer.getvalue())


def write_report(report: TrainReport, path: Path) -> None:
    """``report.json``: :meth:`TrainReport.to_json_dict`, numbers that JSON lacks (numpy) as floats."""
    write_atomic(path, json.dumps(report.to_json_dict(), indent=2, default=float).encode())


def params_finite(model: VoxNeRFModel) -> bool:
    """Whether every trained parameter is finite: the field's and the per-image corrections'."""
    modules = [m for m in (model.field, model.appearance, model.pose_refinement) if m is not None]
    return all(bool(torch.isfinite(p).all()) for m in modules for p in m.parameters())


class CheckpointWriter:
    """Saves model, optimiser, iteration, training seconds and history to ``path``; refuses (TrainingDiverged)
    when the weights are no longer finite, so the last good checkpoint stays."""

    def __init__(self, path: Path, model: VoxNeRFModel, optimizer: torch.optim.Optimizer, budget: Budget,
                 history: list[EvalRecord], scene: Scene, average: WeightAverage | None = None) -> None:
        self.path, self.model, self.optimizer, self.budget = path, model, optimizer, budget
        self.history, self.scene, self.average = history, scene, average

    def __call__(self, iteration: int) -> None:
        if not params_finite(self.model):
            raise TrainingDiverged(f"weights became NaN/inf before iteration {iteration}")
        save_atomic_torch(self.contents(iteration), self.path)

    def contents(self, iteration: int) -> dict:
        """The model renders use (the field's averaged parameters with ``average``, whose live ones then go in
        ``field_live`` for a resumed run), the optimiser, the step, the training time, the history and the scene's
        defaults."""
        first = self.scene.intrinsics(self.scene.train_indices[0])
        model = self.model.state_dict()
        live = {}
        if self.average is not None:
            live = {"field_live": model["field"]}
            model["field"] = self.average.field_state()
        return {
            "model": model,
            **live,
            "optimizer": self.optimizer.state_dict(),
            "iteration": iteration,
            "train_seconds": self.budget.train_seconds,
            "history": [h.to_json_dict() for h in self.history],
            "default_intrinsics": first.as_dict(),
            "depth_unit_scale": self.scene.depth_unit_scale,
            "scene_dir": scene_dir_to_store(self.scene.root, self.path.parent),
        }
