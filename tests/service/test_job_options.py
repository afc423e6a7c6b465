"""Job options and job output (app/schemas.py) against the engine's models they derive from.

``JobOptions`` takes defaults, limits and descriptions from ``TrainConfig``; every ``TrainConfig`` field is
reachable from the REST job options, the worker's settings or the CLI's ``voxnerf train`` flags, or listed
as deliberately internal. ``JobOut`` shows the engine's progress fields, ``EvalRecord`` history and
``StageRecord`` stages, and still reads rows written before it did.
"""

from __future__ import annotations

import argparse
import time

import pytest
from pydantic import ValidationError

from app.core.progress import PROGRESS_FIELDS
from app.schemas import (
    INTERNAL_TRAIN_FIELDS,
    JOB_OPTION_FIELDS,
    MAX_JOB_SECONDS,
    WORKER_SET_FIELDS,
    HistoryPoint,
    JobOptions,
    JobOut,
    StageInfo,
)
from voxnerf.cli import build_parser
from voxnerf.config import FIELD_SECTIONS, TrainConfig, field_info
from voxnerf.training.records import EvalRecord, StageRecord

# `voxnerf train` options whose destination is not a TrainConfig field of the same name.
CLI_ALIASES = {"eval_every": ("eval_every_s",), "samples": ("n_importance", "n_rest")}
# Positional paths and run handling; and --set FIELD=VALUE, which reaches any field by name (the research knob):
# the fields counted here are those with a flag of their own.
CLI_NOT_CONFIG = {"help", "scene", "out", "restart", "set"}


def _train_subparser() -> argparse.ArgumentParser:
    (subparsers,) = [a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)]
    return subparsers.choices["train"]


SETTINGS = {"preset", *FIELD_SECTIONS}  # every TrainConfig setting by its flat name


def cli_train_fields() -> set[str]:
    """The TrainConfig fields ``voxnerf train`` flags set (``--no-compile`` sets ``compile``...)."""
    fields: set[str] = set()
    for action in _train_subparser()._actions:
        dest = action.dest
        if dest in CLI_NOT_CONFIG:
            continue
        names = CLI_ALIASES.get(dest) or (dest.removeprefix("no_"),)
        unknown = [n for n in names if n not in SETTINGS]
        assert not unknown, f"voxnerf train --{dest.replace('_', '-')} maps to no TrainConfig field; update CLI_ALIASES"
        fields.update(names)
    return fields


def test_every_train_config_field_is_reachable_or_deliberately_internal():
    reachable = set(JOB_OPTION_FIELDS) | WORKER_SET_FIELDS | cli_train_fields()
    missing = SETTINGS - reachable - INTERNAL_TRAIN_FIELDS
    assert not missing, (
        f"TrainConfig fields {sorted(missing)} are set by neither the job options, the worker's settings nor "
        "the CLI: expose them (app/schemas.py JOB_OPTION_FIELDS) or add them to INTERNAL_TRAIN_FIELDS with why"
    )
    assert not (INTERNAL_TRAIN_FIELDS & reachable), "a field listed as internal is reachable"
    assert not (set(JOB_OPTION_FIELDS) & WORKER_SET_FIELDS)
    assert (INTERNAL_TRAIN_FIELDS | WORKER_SET_FIELDS | set(JOB_OPTION_FIELDS)) <= SETTINGS


def test_what_the_cli_can_set_a_job_can_set():
    missing = cli_train_fields() - set(JOB_OPTION_FIELDS) - WORKER_SET_FIELDS
    assert not missing, f"voxnerf train sets {sorted(missing)}, which POST /scenes/{{id}}/jobs cannot"


@pytest.mark.parametrize("name", JOB_OPTION_FIELDS)
def test_job_option_defaults_and_limits_are_the_engines(name: str):
    option, engine = JobOptions.model_fields[name], field_info(name)
    assert option.annotation == engine.annotation
    assert option.get_default(call_default_factory=True) == engine.get_default(call_default_factory=True)
    assert option.description == engine.description
    assert all(limit in option.metadata for limit in engine.metadata), "a TrainConfig limit was lost"


def test_eval_every_s_default_is_the_engines_60_s():
    assert JobOptions(max_iters=5).eval_every_s == TrainConfig().evaluation.eval_every_s == 60.0
    assert "30" not in (JobOptions.model_fields["eval_every_s"].description or "")


def test_rest_only_limits():
    with pytest.raises(ValidationError, match="max_seconds or max_iters"):
        JobOptions()
    with pytest.raises(ValidationError, match="max_seconds"):
        JobOptions(max_seconds=MAX_JOB_SECONDS + 1)
    with pytest.raises(ValidationError, match="eval_at"):
        JobOptions(max_iters=5, eval_at=[1.0] * 65)
    with pytest.raises(ValidationError, match="eval_at"):
        JobOptions(max_iters=5, eval_at=[-1.0])
    with pytest.raises(ValidationError, match="eval_every_s"):
        JobOptions(max_iters=5, eval_every_s=float("inf"))
    with pytest.raises(ValidationError, match="greater than or equal to 0.000001"):
        JobOptions(max_iters=5, eval_every_s=1e-300)  # the engine's own bound, carried into the job options
    with pytest.raises(ValidationError, match="lr"):
        JobOptions(max_iters=5, lr=0.1)
    with pytest.raises(ValidationError, match="seed"):
        JobOptions(max_iters=5, seed=-1)
    values = JobOptions(max_iters=5, smooth_patches=8, n_importance=16, n_rest=8).model_dump(exclude_none=True)
    assert TrainConfig(**values).sampling.samples_per_ray == 24  # every option is a TrainConfig field


def test_job_out_fields_come_from_the_progress_event():
    assert set(PROGRESS_FIELDS) <= set(JobOut.model_fields)
    assert issubclass(HistoryPoint, EvalRecord) and issubclass(StageInfo, StageRecord)


def _row(**progress) -> object:
    now = time.time()
    base = dict(
        id="a" * 32, scene_id="b" * 32, state="running", metrics=None, error=None, cancel_requested=False,
        options={"max_iters": 5}, attempt=1, requeues=0, created_at=now, started_at=now, finished_at=None,
        stage="train", iteration=3, elapsed_s=1.5, progress=0.3, eta_s=None, loss=None, history=[], stages=[],
        loss_series=None,  # a column added later: null in the rows written before it (app.core.db adds it)
        created_by=None, cancelled_by=None,  # as loss_series: added with named tokens
        callback_url=None, checkpoint_iteration=None,  # as loss_series: added with webhooks and the live viewer
    )
    return type("Row", (), {**base, **progress})()


def test_job_out_reads_rows_written_before_the_typed_contract():
    legacy_history = [
        {"elapsed_s": 1.0, "wall_s": 2.0, "iteration": 3, "loss": 0.5, "psnr": {"test": 18.0}},
        {"elapsed_s": 4.0, "iteration": 9, "psnr": {"test": None}, "full": True, "ssim": {"test": 0.7},
         "progress_psnr": {"test": 19.0}, "final": True, "note": "an old key"},
    ]
    legacy_stages = [{"name": "prior", "ran": False, "why": "no prior", "seconds": None}]
    out = JobOut.from_row(_row(history=legacy_history, stages=legacy_stages, stage=None, iteration=None))
    data = out.model_dump(mode="json")
    assert data["history"][0]["final"] is False and data["history"][0]["psnr"] == {"test": 18.0}
    assert data["history"][1]["note"] == "an old key" and data["history"][1]["ssim"] == {"test": 0.7}
    assert data["stages"] == [{"name": "prior", "ran": False, "why": "no prior", "seconds": None}]
    assert data["stage"] is None and data["iteration"] == 0  # a null in a non-null column reads as its default


def test_job_out_json_keeps_the_public_keys():
    data = JobOut.from_row(_row()).model_dump(mode="json")
    assert {
        "id", "scene_id", "state", "progress", "eta_s", "stage", "iteration", "elapsed_s", "loss", "history",
        "stages", "metrics", "error", "cancel_requested", "options", "attempt", "requeues", "created_at",
        "started_at", "finished_at",
    } <= set(data)
