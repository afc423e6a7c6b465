"""Checkpoint and report files (voxnerf/training/checkpoint.py)."""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from voxnerf.cameras.pose_refinement import PoseRefinement
from voxnerf.errors import TrainingDiverged
from voxnerf.training.budget import Budget
from voxnerf.training.checkpoint import CheckpointWriter, load_previous, write_report
from voxnerf.training.records import EvalRecord, TrainReport


class StubModel(torch.nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.field = torch.nn.Linear(2, 2)
        self.appearance = None
        self.pose_refinement = None


def _writer(tmp_path, model=None) -> CheckpointWriter:
    model = model or StubModel()
    optimizer = torch.optim.SGD(model.field.parameters(), lr=0.1)
    scene = SimpleNamespace(intrinsics=lambda i: SimpleNamespace(as_dict=lambda: {"fl_x": 1.0, "index": i}),
                            train_indices=[4, 5], depth_unit_scale=0.001, root=tmp_path / "scene")
    history = [EvalRecord(elapsed_s=1.0, iteration=3, psnr={"test": 20.0})]
    return CheckpointWriter(tmp_path / "checkpoint.pt", model, optimizer, Budget(None, 5.0), history, scene)


def test_a_checkpoint_holds_what_a_resumed_run_and_the_renderer_read(tmp_path):
    _writer(tmp_path)(12)
    saved = load_previous(tmp_path / "checkpoint.pt", resume=True)
    assert list(saved) == ["model", "optimizer", "iteration", "train_seconds", "history", "default_intrinsics",
                           "depth_unit_scale", "scene_dir"]
    assert saved["iteration"] == 12 and saved["train_seconds"] >= 5.0
    assert saved["history"] == [{"elapsed_s": 1.0, "iteration": 3, "psnr": {"test": 20.0}}]
    assert saved["default_intrinsics"] == {"fl_x": 1.0, "index": 4} and saved["scene_dir"] == "scene"
    assert load_previous(tmp_path / "checkpoint.pt", resume=False) is None
    assert load_previous(tmp_path / "missing.pt", resume=True) is None


def test_a_checkpoint_names_its_scene_relative_to_its_run_and_no_server_path(tmp_path):
    """Issue #42, item 8: the scene as the service lays it out (``runs/<id>``, ``scenes/<id>``) is recorded as
    ``../../scenes/<id>``; the file holds no absolute path; the renderer finds the scene from the run, also
    once the whole data directory has moved."""
    from tiny_run import write_tiny_run

    from voxnerf.inference.render import load_model

    data = tmp_path / "data"
    run, scene = data / "runs" / "a1", data / "scenes" / "b2"
    scene.mkdir(parents=True)
    write_tiny_run(run)
    real = torch.load(run / "checkpoint.pt", weights_only=True)
    writer = _writer(tmp_path)
    writer.path, writer.scene.root = run / "checkpoint.pt", scene
    writer(7)
    assert load_previous(run / "checkpoint.pt", resume=True)["scene_dir"] == "../../scenes/b2"
    assert str(tmp_path).encode() not in (run / "checkpoint.pt").read_bytes()

    state = torch.load(run / "checkpoint.pt", weights_only=True)  # the tiny run's weights, this scene_dir
    torch.save({**real, "scene_dir": state["scene_dir"]}, run / "checkpoint.pt")
    assert load_model(run, "cpu").scene_dir == str(scene.resolve())
    moved = tmp_path / "elsewhere"
    data.rename(moved)
    assert load_model(moved / "runs" / "a1", "cpu").scene_dir == str((moved / "scenes" / "b2").resolve())


def test_a_checkpoint_from_before_keeps_its_absolute_scene_path(tmp_path):
    from tiny_run import write_tiny_run

    from voxnerf.inference.render import load_model

    run = write_tiny_run(tmp_path / "run")
    state = torch.load(run / "checkpoint.pt", weights_only=True)
    torch.save({**state, "scene_dir": "/tmp/oldckpt/scene"}, run / "checkpoint.pt")  # as tests/fixtures/run_v0_1
    assert load_model(run, "cpu").scene_dir == "/tmp/oldckpt/scene"


def test_non_finite_weights_are_never_saved(tmp_path):
    model = StubModel()
    with torch.no_grad():
        model.field.weight[0, 0] = math.nan
    with pytest.raises(TrainingDiverged, match="weights became NaN/inf before iteration 8"):
        _writer(tmp_path, model)(8)
    assert not (tmp_path / "checkpoint.pt").exists()


def test_a_non_finite_pose_correction_is_never_saved(tmp_path):
    model = StubModel()
    model.pose_refinement = PoseRefinement(2)
    with torch.no_grad():
        model.pose_refinement.delta[1, 4] = math.inf
    with pytest.raises(TrainingDiverged, match="weights became NaN/inf before iteration 3"):
        _writer(tmp_path, model)(3)
    assert not (tmp_path / "checkpoint.pt").exists()


def test_the_report_file_is_the_reports_json_form_with_numpy_numbers(tmp_path):
    report = TrainReport(config={"seed": 0}, device="cpu")
    report.scene = {"mean": np.float32(0.5)}
    write_report(report, tmp_path / "report.json")
    data = json.loads((tmp_path / "report.json").read_text())
    assert data == {"status": "running", "config": {"seed": 0}, "device": "cpu", "stages": [], "history": [],
                    "scene": {"mean": 0.5}}
