"""The records that travel out of training (voxnerf/training/records.py): report.json's form, torch-free."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

from voxnerf.training.records import EvalRecord, StageRecord, TrainReport

ROOT = Path(__file__).resolve().parents[2]


def test_the_records_module_and_the_package_load_without_torch():
    code = ("import json, sys\nimport voxnerf.training, voxnerf.training.records\n"
            "print(json.dumps('torch' in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert json.loads(out.stdout) is False


def test_report_json_holds_the_keys_a_run_set_in_their_usual_order():
    report = TrainReport(config={"a": 1}, device="cpu")
    report.stages.append(StageRecord(name="load_scene", ran=True, why="2 frames", seconds=0.5))
    report.scene = {"frames": 2}
    report.depth_beta = None  # set, even to None: kept
    report.history.append(EvalRecord(elapsed_s=1.0, iteration=2, psnr={"test": 20.0}))
    report.status, report.iteration, report.throughput = "succeeded", 2, {"rays_per_step": 1024, "rays_per_s": 1.5}
    data = report.to_json_dict()
    assert list(data) == ["status", "config", "device", "stages", "history", "scene", "depth_beta", "iteration",
                          "throughput"]
    assert data["history"] == [{"elapsed_s": 1.0, "iteration": 2, "psnr": {"test": 20.0}}]
    assert data["stages"] == [{"name": "load_scene", "ran": True, "why": "2 frames", "seconds": 0.5}]
    again = TrainReport.from_json_dict(json.loads(json.dumps(data)))
    assert again.to_json_dict() == data and isinstance(again.throughput["rays_per_step"], int)


def test_warnings_appear_only_when_there_are_some():
    report = TrainReport(config={}, device="cpu")
    assert "warnings" not in report.to_json_dict()
    report.warnings.append("few pixels see the prior")
    assert report.to_json_dict()["warnings"] == ["few pixels see the prior"]


def test_a_final_record_may_carry_a_nan_loss():
    data = EvalRecord(elapsed_s=1.0, iteration=0, loss=math.nan, final=True).to_json_dict()
    assert math.isnan(data["loss"]) and data["final"] and "full" not in data
