"""benchmarks/unseen_pixels.py: a run's evaluation error split by how many training views see each pixel's true
surface point, on a real micro run; its refusals."""

from __future__ import annotations

import importlib
import json
import shutil
import sys
from dataclasses import replace
from pathlib import Path

import pytest
from synthetic_fixtures import MICRO, make_micro_scene, micro_config

from voxnerf.synthetic import make_room_scene
from voxnerf.training.run import train

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
unseen_pixels = importlib.import_module("unseen_pixels")


@pytest.fixture(scope="module")
def micro_run(tmp_path_factory) -> tuple[Path, Path]:
    room = make_micro_scene(tmp_path_factory, "unseen-pixels")
    run = tmp_path_factory.mktemp("unseen-pixels-run") / "run"
    train(room, run, micro_config(max_iters=2), progress_bar=False)
    return room, run


def test_every_pixel_is_counted_once_and_the_groups_add_up(micro_run, tmp_path):
    room, run = micro_run
    assert unseen_pixels.main([str(run), str(room), "--json", str(tmp_path / "out.json")]) == 0
    result = json.loads((tmp_path / "out.json").read_text())
    report = json.loads((run / "report.json").read_text())
    assert set(result) == set(report["metrics"])
    for split in result.values():
        groups = split["groups"]
        assert sum(g["pixels"] for g in groups.values()) == pytest.approx(1.0)
        assert sum(g["error"] for g in groups.values()) == pytest.approx(1.0)
        assert set(groups) <= {*unseen_pixels.GROUPS, "no depth"}


def test_a_training_view_sees_what_it_looked_at(micro_run):
    room, run = micro_run
    from voxnerf.data.scene import load_scene

    scene = load_scene(room)
    first = scene.train_indices[0]
    points, valid = unseen_pixels.surface_points(scene, first)
    count = unseen_pixels.seen_count(scene, points, 0.03)
    assert (count[valid] >= 1).mean() > 0.99  # its own view, at least


def test_a_run_without_its_renders_is_a_one_line_error(micro_run, tmp_path, capsys):
    room, run = micro_run
    bare = tmp_path / "bare"
    shutil.copytree(run, bare, ignore=shutil.ignore_patterns("eval"))
    assert unseen_pixels.main([str(bare), str(room)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("unseen_pixels: ") and "no render" in err and "\n" not in err


def test_a_scene_without_depth_maps_is_a_one_line_error(tmp_path_factory, micro_run, capsys):
    _, run = micro_run
    no_depth = make_room_scene(tmp_path_factory.mktemp("unseen-no-depth") / "room", replace(MICRO, write_depth=False))
    assert unseen_pixels.main([str(run), str(no_depth)]) == 2
    err = capsys.readouterr().err.strip()
    assert "no depth map" in err and "\n" not in err
