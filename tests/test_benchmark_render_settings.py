"""benchmarks/render_settings.py: one trained field scored under both choices of a render-time setting (the render
background, antialiasing), from a suite's run directory; its refusals."""

from __future__ import annotations

import importlib
import json
import sys
from pathlib import Path

import pytest
from synthetic_fixtures import make_micro_scene, micro_config

from voxnerf.training.run import train

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
render_settings = importlib.import_module("render_settings")


def test_a_suite_run_is_scored_both_ways_on_the_same_field(tmp_path_factory, tmp_path):
    room = make_micro_scene(tmp_path_factory, "render-background")
    runs = tmp_path / "suite"
    train(room, runs / "runs" / room.name / "defaults", micro_config(max_iters=2), progress_bar=False)
    out = tmp_path / "out"
    args = ["--runs", str(runs), "--suite-dir", str(room.parent), "--out", str(out)]
    assert render_settings.main(args) == 0
    result = json.loads((out / "results.json").read_text())[room.name]
    assert "training pixels (100.0%) at their depth targets" in result["colour_prior"]
    splits = list(result["colour"])
    assert splits and list(result["nearest_seen"]) == splits
    for choice in render_settings.SETTINGS["render_background"]:
        for split in splits:
            metrics = result[choice][split]
            assert metrics["psnr"] > 0 and metrics["half"]["psnr"] > 0
    # The run's own report scored the same field under the choice it trained with.
    report = json.loads((runs / "runs" / room.name / "defaults" / "report.json").read_text())
    trained_with = report["config"]["render_background"]
    assert trained_with == "nearest_seen"  # the default
    for split in splits:
        assert result[trained_with][split]["psnr"] == pytest.approx(report["metrics"][split]["psnr"], abs=1e-6)
    table = (out / "table.md").read_text()
    assert f"| {room.name} | " in table and "render_settings.py --runs" in table
    before = (out / "results.json").stat().st_mtime_ns
    assert render_settings.main(args) == 0  # scored once: the next call reuses it
    assert (out / "results.json").stat().st_mtime_ns == before


def test_antialiasing_is_scored_on_the_same_field_against_the_centre_ray(tmp_path_factory, tmp_path):
    room = make_micro_scene(tmp_path_factory, "render-antialias")
    runs = tmp_path / "suite"
    train(room, runs / "runs" / room.name / "defaults", micro_config(max_iters=2), progress_bar=False)
    out = tmp_path / "out"
    assert render_settings.main(["--setting", "antialias", "--runs", str(runs), "--suite-dir", str(room.parent),
                                 "--out", str(out)]) == 0
    result = json.loads((out / "results.json").read_text())[room.name]
    assert result["setting"] == "antialias"
    report = json.loads((runs / "runs" / room.name / "defaults" / "report.json").read_text())
    assert report["config"]["antialias"] is True  # the default: the run's own report is the antialiased render
    for split, metrics in report["metrics"].items():
        assert result["antialiased"][split]["psnr"] == pytest.approx(metrics["psnr"], abs=1e-6)
        assert result["centre_ray"][split]["psnr"] != pytest.approx(metrics["psnr"], abs=1e-6)
    table = (out / "table.md").read_text()
    assert "`antialiased` - `centre_ray`" in table and "--setting antialias" in table


def test_each_choice_renders_over_today_s_render_defaults_whatever_the_run_trained_with(tmp_path_factory, tmp_path,
                                                                                         monkeypatch):
    room = make_micro_scene(tmp_path_factory, "render-defaults")
    run = tmp_path / "suite" / "runs" / room.name / "defaults"
    train(room, run, micro_config(max_iters=2, render_background="colour", antialias=False, nearest_seen_weight=0.5,
                                  final_eval=False), progress_bar=False)
    seen = []

    def recording(model, views, cfg, **kwargs):
        seen.append({name: getattr(cfg.model, name) for name in render_settings.SETTINGS})
        return {}

    monkeypatch.setattr(render_settings, "evaluate_views", recording)
    render_settings.score_run(run, room, "cpu", "antialias")
    defaults = {"render_background": "nearest_seen", "nearest_seen_weight": 1.0}
    assert seen == [{**defaults, "antialias": False}, {**defaults, "antialias": True}]


def test_a_scene_without_a_run_is_refused_before_anything_is_written(tmp_path):
    (tmp_path / "runs" / "den" / "defaults").mkdir(parents=True)  # no checkpoint in it
    with pytest.raises(SystemExit):
        render_settings.main(["--runs", str(tmp_path), "--suite-dir", str(tmp_path), "--out", str(tmp_path / "o"),
                                "--scenes", "den"])
    assert not (tmp_path / "o").exists()


def test_redkitchen_needs_its_directory():
    with pytest.raises(SystemExit, match="redkitchen's run needs --redkitchen"):
        render_settings.scene_dir_of("redkitchen", Path("/scenes"), None)
    assert render_settings.scene_dir_of("den", Path("/scenes"), None) == Path("/scenes/den")


def _scored(interpolation: float, extrapolation: float) -> dict:
    return {split: {"psnr": psnr, "ssim": 0.9, "lpips": 0.1, "half": {"psnr": psnr}}
            for split, psnr in (("interpolation", interpolation), ("extrapolation", extrapolation))}


@pytest.mark.parametrize(("loft_after", "expected"), [((33.0, 24.2), "adopt"), ((33.0, 23.5), "keep")])
def test_the_verdict_is_the_suite_protocol_s(loft_after, expected):
    results = {"studio": {"colour": _scored(33.0, 24.0), "nearest_seen": _scored(33.0, 24.5)},
               "loft": {"colour": _scored(33.0, 24.0), "nearest_seen": _scored(*loft_after)}}
    verdict = render_settings.protocol_verdict(results, "render_background")
    assert verdict["verdict"] == expected
    assert verdict["tuning"]["extrapolation"] == pytest.approx(0.5)
    table = render_settings.table(results, "cmd", "render_background")
    assert "| nearest_seen | 1 | +0.00 | +0.50 | 1 |" in table and f"**{expected}**" in table
