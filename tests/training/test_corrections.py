"""Which real-scan corrections a run learns (voxnerf/training/stages/corrections.py): ``auto`` per scene, through a
run's report, and the ``synthetic`` key that decides it."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch
from synthetic_fixtures import make_micro_scene, meta_of, micro_config

from voxnerf.config import TrainConfig
from voxnerf.data.scene import load_scene
from voxnerf.errors import SceneError
from voxnerf.files import REFINED_POSES
from voxnerf.training.run import train
from voxnerf.training.stages import model_stage
from voxnerf.training.stages.corrections import corrections_stage


@pytest.fixture(scope="module")
def synthetic_room(tmp_path_factory) -> Path:
    return make_micro_scene(tmp_path_factory, "corrections")


@pytest.fixture(scope="module")
def captured_room(synthetic_room: Path, tmp_path_factory) -> Path:
    """The micro room's files under a transforms.json without ``synthetic``: what a captured scan looks like."""
    room = tmp_path_factory.mktemp("captured") / "room"
    shutil.copytree(synthetic_room, room)
    meta = meta_of(synthetic_room)
    del meta["synthetic"]
    (room / "transforms.json").write_text(json.dumps(meta))
    return room


def _scene(room: Path):
    return load_scene(room, load_images=False)


def test_the_generator_marks_its_scenes_synthetic(synthetic_room: Path, captured_room: Path):
    assert meta_of(synthetic_room)["synthetic"] is True
    assert _scene(synthetic_room).synthetic and _scene(synthetic_room).summary()["synthetic"] is True
    assert not _scene(captured_room).synthetic


def test_auto_learns_both_corrections_on_a_captured_scan(captured_room: Path):
    stage = corrections_stage(TrainConfig(), _scene(captured_room), None)
    assert (stage.cfg.corrections.appearance, stage.cfg.corrections.pose_refinement) == ("affine", "so3xr3")
    assert stage.record.name == "corrections" and stage.record.ran
    assert stage.record.why.startswith("appearance affine, pose_refinement so3xr3; auto: a captured scan")


def test_auto_leaves_both_out_on_a_synthetic_scene(synthetic_room: Path):
    stage = corrections_stage(TrainConfig(), _scene(synthetic_room), None)
    assert (stage.cfg.corrections.appearance, stage.cfg.corrections.pose_refinement) == ("none", "none")
    assert not stage.record.ran and "synthetic" in stage.record.why


def test_values_other_than_auto_are_used_as_given(synthetic_room: Path, captured_room: Path):
    given = corrections_stage(TrainConfig(appearance="affine", pose_refinement="so3xr3"), _scene(synthetic_room), None)
    assert (given.cfg.corrections.appearance, given.cfg.corrections.pose_refinement) == ("affine", "so3xr3")
    assert given.record.why.endswith("; as configured")
    mixed = corrections_stage(TrainConfig(appearance="none"), _scene(captured_room), None)
    assert (mixed.cfg.corrections.appearance, mixed.cfg.corrections.pose_refinement) == ("none", "so3xr3")
    assert mixed.record.why.startswith("pose_refinement so3xr3; auto: a captured scan")


def test_a_resumed_run_keeps_what_its_checkpoint_learnt(captured_room: Path):
    previous = {"model": {"field": {}, "appearance": None, "pose_refinement": {"delta": None}}}
    stage = corrections_stage(TrainConfig(), _scene(captured_room), previous)
    assert (stage.cfg.corrections.appearance, stage.cfg.corrections.pose_refinement) == ("none", "so3xr3")
    assert "resumed checkpoint" in stage.record.why
    older = corrections_stage(TrainConfig(), _scene(captured_room), {"model": {"field": {}}})  # before corrections
    assert (older.cfg.corrections.appearance, older.cfg.corrections.pose_refinement) == ("none", "none")


def test_a_single_training_image_has_nothing_to_correct(captured_room: Path):
    scene = _scene(captured_room)
    scene.splits["train"] = scene.splits["train"][:1]
    stage = corrections_stage(TrainConfig(), scene, None)
    assert (stage.cfg.corrections.appearance, stage.cfg.corrections.pose_refinement) == ("none", "none")
    assert "fewer than 2 training images" in stage.record.why


@pytest.mark.parametrize("value", ["yes", 1, None, [True]])
def test_a_synthetic_key_that_is_not_a_boolean_names_the_file_and_key(captured_room: Path, tmp_path: Path, value):
    room = tmp_path / "room"
    shutil.copytree(captured_room, room)
    (room / "transforms.json").write_text(json.dumps(meta_of(captured_room) | {"synthetic": value}))
    with pytest.raises(SceneError, match=r"transforms\.json.*synthetic.*must be true or false"):
        load_scene(room, load_images=False)


def test_a_run_on_a_captured_scan_learns_and_reports_the_corrections(captured_room: Path, tmp_path: Path):
    report = train(captured_room, tmp_path / "run", micro_config(max_iters=3), progress_bar=False)
    assert (report.config["appearance"], report.config["pose_refinement"]) == ("affine", "so3xr3")
    record = next(s for s in report.stages if s.name == "corrections")
    assert record.ran and "captured scan" in record.why
    assert report.appearance["images"] == 10 and report.pose_refinement["images"] == 10
    assert (tmp_path / "run" / REFINED_POSES).is_file()
    written = json.loads((tmp_path / "run" / "report.json").read_text())
    assert written["config"]["pose_refinement"] == "so3xr3"
    resumed = train(captured_room, tmp_path / "run", micro_config(max_iters=5, appearance="auto"), progress_bar=False)
    assert resumed.iteration == 5 and resumed.config["appearance"] == "affine"


def test_a_run_on_a_synthetic_scene_learns_none(synthetic_room: Path, tmp_path: Path):
    report = train(synthetic_room, tmp_path / "run", micro_config(max_iters=2), progress_bar=False)
    assert (report.config["appearance"], report.config["pose_refinement"]) == ("none", "none")
    record = next(s for s in report.stages if s.name == "corrections")
    assert not record.ran and "synthetic" in record.why
    assert report.appearance is None and report.pose_refinement is None
    assert not (tmp_path / "run" / REFINED_POSES).exists()


def test_the_model_stage_refuses_an_unresolved_auto(synthetic_room: Path):
    scene = load_scene(synthetic_room)
    with pytest.raises(ValueError, match="resolve 'auto'"):
        model_stage(micro_config(field_weight_decay=0.0), scene, None, torch.device("cpu"), None)
