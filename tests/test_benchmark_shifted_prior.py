"""benchmarks/shifted_prior.py: its cases, the scenes it makes (the prior moved, nothing else), and its table from
two runs' reports; one real pair of micro runs, too short to compare, to show the commands train and read back."""

from __future__ import annotations

import importlib
import json
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh
from synthetic_fixtures import make_micro_scene

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
shifted_prior = importlib.import_module("shifted_prior")


@pytest.mark.parametrize("text", ["den", "den:0.1,0.2", "den:a,b,c", ":0,0,0", "den:0,0,nan"])
def test_a_malformed_case_is_a_one_line_error_naming_it(text):
    with pytest.raises(SystemExit, match=f"case {text!r}: expected SCENE:DX,DY,DZ"):
        shifted_prior.parse_case(text)


def test_a_case_moves_the_prior_and_nothing_else(tmp_path_factory, tmp_path):
    room = make_micro_scene(tmp_path_factory, "shift")
    scene, shift = shifted_prior.parse_case("tiny:0.3,0,-0.1")
    assert scene == "tiny" and shifted_prior.case_name(scene, shift) == "tiny+32cm"
    moved = shifted_prior.make_case(room, shift, tmp_path / "tiny+32cm")
    meta = json.loads((room / "transforms.json").read_text())
    before = np.asarray(trimesh.load(room / meta["prior_file_path"]).vertices)
    after = np.asarray(trimesh.load(moved / meta["prior_file_path"]).vertices)
    np.testing.assert_allclose(after, before + [0.3, 0.0, -0.1], atol=1e-5)
    assert not (moved / "gt_mesh.ply").exists() and "gt_mesh_file_path" not in json.loads(
        (moved / "transforms.json").read_text())
    assert sorted(p.name for p in (moved / "images").iterdir()) == sorted(p.name for p in (room / "images").iterdir())
    assert not list(tmp_path.glob("*.partial"))
    assert shifted_prior.make_case(room, shift * 2, moved) == moved  # made once, then reused as it is


def test_a_scene_the_suite_lacks_is_a_one_line_error(tmp_path):
    with pytest.raises(SystemExit, match="nowhere/transforms.json: no such scene"):
        shifted_prior.main(["--suite-dir", str(tmp_path), "--out", str(tmp_path / "out"), "--cases", "nowhere:0,0,0.1"])
    assert not (tmp_path / "out" / "scenes").exists()


def _report(path: Path, psnr: tuple[float, float], steps: int, wrong: float | None) -> None:
    path.mkdir(parents=True)
    metrics = {split: {"psnr": p} for split, p in zip(("interpolation", "extrapolation"), psnr, strict=True)}
    report = {"status": "succeeded", "metrics": metrics, "iteration": steps}
    if wrong is not None:
        report["window_check"] = {"wrong_first_hit": wrong}
    (path / "report.json").write_text(json.dumps(report))


def test_the_table_reads_both_runs_and_says_what_auto_chooses(tmp_path):
    _report(tmp_path / "runs" / "den+40cm" / "voxnerf", (31.0, 20.7), 3068, 0.491)
    _report(tmp_path / "runs" / "den+40cm" / "occgrid", (33.5, 21.3), 2918, None)
    _report(tmp_path / "runs" / "hall+5cm" / "voxnerf", (35.0, 24.0), 3000, 0.02)
    args = ["--suite-dir", str(tmp_path), "--out", str(tmp_path), "--table-only", "--cases", "den:0.28,0.28,0",
            "hall:0.05,0,0"]
    assert shifted_prior.main(args) == 0
    rows = json.loads((tmp_path / "results.json").read_text())["rows"]
    assert [r["case"] for r in rows] == ["den+40cm"]  # hall+5cm lacks its grid run: left out
    assert rows[0]["auto"] == "occgrid" and rows[0]["wrong_first_hit"] == pytest.approx(0.491)
    table = (tmp_path / "table.md").read_text()
    assert ("| den+40cm | 40 cm | 49.1% | occgrid | 31.00 / 20.70 | 33.50 / 21.30 | +2.50 / +0.60 | 3068 / 2918 |"
            in table)
    assert "shifted_prior.py --suite-dir" in table


def test_a_pair_of_micro_runs_trains_each_sampler_and_tables_them(tmp_path_factory, tmp_path):
    room = make_micro_scene(tmp_path_factory, "shift-runs")
    suite = room.parent
    args = ["--suite-dir", str(suite), "--out", str(tmp_path), "--budget", "60", "--cases", f"{room.name}:0.5,0.5,0",
            "--train-args=--no-compile --max-iters 2 --downscale 2"]
    assert shifted_prior.main(args) == 0
    (row,) = json.loads((tmp_path / "results.json").read_text())["rows"]
    case = tmp_path / "runs" / row["case"]
    assert json.loads((case / "voxnerf" / "report.json").read_text())["config"]["sampler"] == "voxnerf"
    assert json.loads((case / "occgrid" / "report.json").read_text())["config"]["sampler"] == "occgrid"
    assert row["wrong_first_hit"] > 0.06 and row["auto"] == "occgrid"  # half a metre off: the window misses


def test_a_run_that_fails_is_a_one_line_error_naming_its_log(tmp_path_factory, tmp_path):
    room = make_micro_scene(tmp_path_factory, "shift-fails")
    args = ["--suite-dir", str(room.parent), "--out", str(tmp_path), "--cases", f"{room.name}:0.1,0,0",
            "--train-args=--no-such-flag"]
    with pytest.raises(SystemExit, match=r"failed; its output: .*voxnerf\.log"):
        shifted_prior.main(args)
    assert "--no-such-flag" in next(tmp_path.glob("runs/*/voxnerf.log")).read_text()
