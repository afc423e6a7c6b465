"""The colour focal length checked against the prior (voxnerf/prior/focal_check.py, voxnerf/training/stages/focal.py)
and the scene seen through a corrected one (voxnerf/data/scene.py's with_focal_scale, voxnerf/inference/render.py's
scene_as_trained)."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pydantic
import pytest
import trimesh
from synthetic_fixtures import micro_config

from voxnerf.config import TrainConfig
from voxnerf.data.scene import depth_on_image, load_scene, read_depth_map, with_focal_scale
from voxnerf.inference.render import load_model, scene_as_trained
from voxnerf.prior.focal_check import check_focal, image_pairs
from voxnerf.prior.loading import load_prior
from voxnerf.prior.pseudo_depth import MeshCaster
from voxnerf.synthetic import RoomSpec, make_room_scene
from voxnerf.training.run import train
from voxnerf.training.stages.focal import focal_stage

# 96x72 pixels, 12 training frames, a mesh prior: enough texture and parallax to see a focal length by.
ROOM = RoomSpec(width=96, height=72, n_frames=48, train_every=4, n_gaps=0, gap_len=0, prior_kind="mesh")
WRONG = 1.1  # the stated focal length of a "captured" copy is this times the true one


@pytest.fixture(scope="module")
def room(tmp_path_factory) -> Path:
    return make_room_scene(tmp_path_factory.mktemp("focal") / "room", ROOM)


@pytest.fixture(scope="module")
def captured(room: Path, tmp_path_factory) -> Path:
    """``room`` as a capture would state it: not marked synthetic, its colour focal length stated WRONG x too
    long, the depth maps given through the true camera (``depth_intrinsics``)."""
    copy = tmp_path_factory.mktemp("focal-captured") / "room"
    shutil.copytree(room, copy)
    meta = json.loads((copy / "transforms.json").read_text())
    meta.pop("synthetic", None)
    true_camera = {k: meta[k] for k in ("fl_x", "fl_y", "cx", "cy", "w", "h")}
    meta["depth_intrinsics"] = true_camera
    meta["fl_x"], meta["fl_y"] = meta["fl_x"] * WRONG, meta["fl_y"] * WRONG
    (copy / "transforms.json").write_text(json.dumps(meta))
    return copy


def _mesh_caster(scene_dir: Path) -> MeshCaster:
    mesh = trimesh.load(scene_dir / "gt_mesh.ply", process=False)
    return MeshCaster(np.asarray(mesh.vertices), np.asarray(mesh.faces))


def _check(scene_dir: Path):
    scene = load_scene(scene_dir)
    train_ = scene.train_indices
    return check_focal(_mesh_caster(scene_dir), [scene.images[i] for i in train_],
                       np.stack([scene.frames[i].c2w for i in train_]), scene.intrinsics(train_[0]))


def test_the_check_finds_the_true_focal_length_and_a_wrongly_stated_one(room: Path, captured: Path):
    exact = _check(room)
    assert abs(exact.best - 1.0) < 0.02 and exact.gain < 0.05  # nothing to correct
    wrong = _check(captured)
    assert wrong.best == pytest.approx(1 / WRONG, abs=0.02) and wrong.interior
    assert wrong.gain > 0.2 and wrong.points > 1000 and wrong.pairs >= 6
    assert 1.0 in wrong.errors and all(np.isfinite(e) for e in wrong.errors.values())


def test_pairs_are_neighbours_each_once_and_at_most_the_cap():
    c2ws = np.repeat(np.eye(4)[None], 30, axis=0)
    c2ws[:, 0, 3] = np.arange(30) * 0.1  # cameras on a line: each one's nearest is beside it
    pairs = image_pairs(c2ws, most=100)
    assert all(b - a == 1 for a, b in pairs) and len(pairs) == len(set(pairs))
    assert len(image_pairs(c2ws, most=5)) == 5 and image_pairs(c2ws[:1]) == []


def test_the_check_refuses_too_few_images_and_images_that_share_nothing(room: Path):
    caster = _mesh_caster(room)
    scene = load_scene(room)
    intr = scene.intrinsics(scene.train_indices[0])
    image = scene.images[scene.train_indices[0]]
    with pytest.raises(ValueError, match="at least two training images"):
        check_focal(caster, [image], np.eye(4)[None], intr)
    away = np.repeat(np.eye(4)[None], 2, axis=0)
    away[:, :3, 3] = [[100.0, 0, 0], [100.5, 0, 0]]  # far outside the room, looking away from it
    with pytest.raises(ValueError, match="no surface point"):
        check_focal(caster, [image, image], away, intr)


def test_the_stage_corrects_a_captured_scan_and_leaves_a_synthetic_one(room: Path, captured: Path):
    prior = load_prior(captured / "prior.ply", 0.02)
    synthetic = focal_stage(micro_config(), load_scene(room), prior)
    assert synthetic.cfg.corrections.focal_scale == 1.0
    assert not synthetic.record.ran and "synthetic" in synthetic.record.why
    scene = load_scene(captured)
    stage = focal_stage(micro_config(), scene, prior)
    assert stage.record.ran and stage.record.name == "focal"
    assert stage.cfg.corrections.focal_scale == pytest.approx(1 / WRONG, abs=0.02)
    assert "agree best through the prior" in stage.record.why and "px at full size" in stage.record.why
    i = scene.train_indices[0]
    stated_fl = scene.frames[i].intrinsics.fl_x
    assert stage.scene.frames[i].intrinsics.fl_x == pytest.approx(stated_fl * stage.cfg.corrections.focal_scale)
    given = focal_stage(micro_config(focal_scale=0.95), scene, prior)
    assert given.cfg.corrections.focal_scale == 0.95 and given.record.why.endswith("as configured")


@pytest.mark.parametrize("prior_kind", ["points", "none"])
def test_the_stage_needs_a_mesh_prior(captured: Path, prior_kind: str):
    scene = load_scene(captured)
    prior = None if prior_kind == "none" else SimpleNamespace(mesh=None)
    stage = focal_stage(micro_config(), scene, prior)
    assert stage.cfg.corrections.focal_scale == 1.0
    assert stage.scene is scene and "needs the prior as a mesh" in stage.record.why


def test_the_stage_leaves_lens_models_and_several_cameras_alone(captured: Path):
    scene = load_scene(captured)
    prior = SimpleNamespace(mesh=trimesh.creation.box())
    first = scene.train_indices[0]
    two_cameras = replace(scene, frames=list(scene.frames))
    moved = replace(scene.frames[first].intrinsics, cx=10.0)
    two_cameras.frames[first] = replace(scene.frames[first], intrinsics=moved)
    assert "from 2 cameras" in focal_stage(micro_config(), two_cameras, prior).record.why
    from voxnerf.cameras.rules import Lens

    lens = Lens("OPENCV", k1=0.01)
    with_lens = replace(scene, frames=[replace(f, intrinsics=replace(f.intrinsics, lens=lens)) for f in scene.frames])
    assert "lens model" in focal_stage(micro_config(), with_lens, prior).record.why


def test_a_corrected_scene_keeps_its_depth_on_the_stated_camera(room: Path):
    scene = load_scene(room)
    assert with_focal_scale(scene, 1.0) is scene
    corrected = with_focal_scale(scene, 0.9)
    i = scene.train_indices[0]
    assert corrected.frames[i].stated_intrinsics == scene.frames[i].intrinsics
    assert corrected.frames[i].intrinsics.fl_y == pytest.approx(0.9 * scene.frames[i].intrinsics.fl_y)
    depth, camera = read_depth_map(corrected.frames[i], scene.depth_unit_scale, scene.depth_max)
    assert camera == scene.frames[i].intrinsics  # measured through the stated camera
    # A shorter focal length sees more: the corrected image's centre pixel keeps its depth, its border pixels
    # look beyond the stated camera's view and have none.
    registered = corrected.depths[i]
    np.testing.assert_array_equal(registered, depth_on_image(corrected.frames[i], scene.depth_unit_scale, 1))
    h, w = registered.shape
    assert registered[h // 2, w // 2] == pytest.approx(depth[h // 2, w // 2], rel=1e-6)
    assert np.isnan(registered[:, 0]).all() and np.isfinite(scene.depths[i][:, 0]).any()
    assert with_focal_scale(corrected, 1 / 0.9).frames[i].stated_intrinsics == scene.frames[i].intrinsics


def test_focal_scale_is_checked_by_the_config():
    assert TrainConfig().corrections.focal_scale == "auto"
    for bad in (0.3, 3.0, "half"):
        with pytest.raises(pydantic.ValidationError, match="focal_scale"):
            TrainConfig(focal_scale=bad)


def test_a_run_trains_and_renders_its_views_through_the_measured_focal_length(captured: Path, tmp_path: Path):
    run = tmp_path / "run"
    report = train(captured, run, micro_config(max_iters=2))
    focal = next(s for s in report.stages if s.name == "focal")
    scale = report.config["focal_scale"]
    assert focal.ran and scale == pytest.approx(1 / WRONG, abs=0.02)
    trained = load_model(run, "cpu")
    assert trained.model.config.corrections.focal_scale == scale
    stated = load_scene(captured, load_images=False)
    as_trained = scene_as_trained(stated, trained.model)
    i = stated.train_indices[0]
    assert as_trained.frames[i].intrinsics.fl_x == pytest.approx(stated.frames[i].intrinsics.fl_x * scale)
    assert trained.default_intrinsics.fl_x == pytest.approx(stated.intrinsics(i).fl_x * scale)
    # a checkpoint from before the check
    old = SimpleNamespace(config=SimpleNamespace(corrections=SimpleNamespace(focal_scale="auto")))
    assert scene_as_trained(stated, old) is stated


def test_the_cli_takes_auto_or_a_number_and_refuses_anything_else(captured: Path, tmp_path: Path, capsys):
    from voxnerf.cli import build_parser, main

    parse = build_parser().parse_args
    base = ["train", str(captured), "--out", str(tmp_path / "r"), "--max-iters", "1"]
    assert parse(base).focal_scale == "auto" and parse([*base, "--focal-scale", "0.9"]).focal_scale == 0.9
    with pytest.raises(SystemExit):
        parse([*base, "--focal-scale", "half"])
    assert "expected auto or a number, got 'half'" in capsys.readouterr().err
    assert main([*base, "--focal-scale", "5"]) == 2  # out of TrainConfig's range: a one-line error
    assert "focal_scale" in capsys.readouterr().err and not (tmp_path / "r").exists()
