"""The set-up as a list of stages with one protocol (voxnerf/training/setup.py): the runner, and the stages of a
real run in their order."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from synthetic_fixtures import make_micro_scene, micro_config

from voxnerf.config import TrainConfig
from voxnerf.training.records import StageRecord, TrainReport
from voxnerf.training.run import StoppedInSetUp, train
from voxnerf.training.setup import SETUP_STAGES, SetupContext, Stage, run_setup


def _context(cfg: TrainConfig) -> SetupContext:
    return SetupContext(cfg, Path("scene"), Path("run"), torch.device("cpu"), TrainReport(config=cfg.model_dump(),
                        device="cpu"), None, lambda: None)


def _record(name: str) -> StageRecord:
    return StageRecord(name=name, ran=True, why="because", seconds=0.0)


def test_the_runner_emits_each_record_keeps_the_report_s_config_and_asks_to_stop_after_each_stage():
    log = []

    def resolve(ctx):
        ctx.cfg = ctx.cfg.updated(field_weight_decay=0.005)
        return _record("resolve")

    def build(ctx):
        log.append(("build", ctx.report.config["field_weight_decay"]))
        return None  # builds only: no event

    ctx = _context(TrainConfig(max_iters=1, field_weight_decay="auto"))
    run_setup(ctx, lambda record, iteration: log.append(("emit", record.name, iteration)),
              lambda: log.append("stop?"), (Stage("resolve", resolve), Stage("build", build)))
    assert log == [("emit", "resolve", 0), "stop?", ("build", 0.005), "stop?"]
    assert ctx.report.config["field_weight_decay"] == 0.005 and ctx.cfg.schedule.field_weight_decay == 0.005


def test_a_stop_between_stages_leaves_the_later_stages_unrun():
    ran = []

    def stage(name):
        return Stage(name, lambda ctx: ran.append(name) or _record(name))

    def stop():
        if ran == ["a"]:
            raise StoppedInSetUp()

    with pytest.raises(StoppedInSetUp):
        run_setup(_context(TrainConfig(max_iters=1)), lambda record, iteration: None, stop,
                  (stage("a"), stage("b")))
    assert ran == ["a"]


def test_a_run_reports_the_set_up_stages_in_the_order_of_the_list(tmp_path_factory, tmp_path):
    room = make_micro_scene(tmp_path_factory, "setup-order")
    report = train(room, tmp_path / "run", micro_config(max_iters=2, final_eval=False), progress_bar=False)
    names = [s["name"] for s in json.loads((tmp_path / "run" / "report.json").read_text())["stages"]]
    listed = [stage.name for stage in SETUP_STAGES if stage.name != "model"]  # the model stage builds only
    assert names[: len(listed)] == listed
    assert report.status == "succeeded"
