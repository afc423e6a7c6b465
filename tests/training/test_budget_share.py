"""Every second of the budget training (issue #46, item 4): a real run on the small room under ``max_seconds``
trains at least 95 % of it, by its own report's accounting (report.json's ``budget``), and that accounting agrees
with the run's stage records and adds up to its wall clock. No assertion on the machine's speed: a loaded machine
trains fewer steps in the same seconds, not fewer seconds."""

from __future__ import annotations

import json

import pytest

from voxnerf.config import TrainConfig
from voxnerf.training.budget import CHARGED
from voxnerf.training.callbacks import FIRST_PROGRESS_EVAL_RAYS, MIN_PROGRESS_EVAL_RAYS, PROGRESS_EVALS_STAGE
from voxnerf.training.run import REPORT, train

pytestmark = pytest.mark.slow
MAX_SECONDS = 20.0
EVAL_EVERY_S = 5.0  # progress evaluations due at 5, 10 and 15 s of training: three within the budget


@pytest.fixture(scope="module")
def budgeted_run(captured_small_room, compiled_captured_step, tmp_path_factory):
    """A ``MAX_SECONDS`` run of the captured-like small room under the default config: the step that
    ``compiled_captured_step`` compiled, loaded from the inductor cache."""
    run_dir = tmp_path_factory.mktemp("budget_share")
    cfg = TrainConfig(max_seconds=MAX_SECONDS, device="cpu", eval_every_s=EVAL_EVERY_S)
    report = train(captured_small_room, run_dir, cfg, progress_bar=False)
    return report, json.loads((run_dir / REPORT).read_text())


def test_a_short_budget_trains_at_least_95_percent_of_max_seconds(budgeted_run):
    report, written = budgeted_run
    budget = written["budget"]
    seconds = budget["seconds"]
    assert report.status == "succeeded" and budget == report.budget and budget["max_seconds"] == MAX_SECONDS
    assert budget["trained_share"] >= 0.95
    assert budget["trained_share"] == pytest.approx(seconds["training"] / MAX_SECONDS, abs=1e-3)
    assert written["train_seconds"] == pytest.approx(seconds["training"], abs=2e-3)
    assert budget["charged"] == CHARGED


def test_the_accounting_adds_up_to_the_wall_clock_and_charges_no_more_than_max_seconds(budgeted_run):
    report, _ = budgeted_run
    seconds = report.budget["seconds"]
    parts = ("set_up", "compile", "training", "progress_evals", "checkpoints", "eval_at", "final_eval", "finish")
    assert all(seconds[p] >= 0 for p in parts)
    assert sum(seconds[p] for p in parts) == pytest.approx(seconds["wall"], abs=0.01)
    assert seconds["wall"] == pytest.approx(report.wall_seconds, abs=0.05)
    charged = seconds["training"] + seconds["progress_evals"] + seconds["checkpoints"]
    steps = report.iteration
    step = seconds["training"] / steps
    # the loop stops at the first step past the budget: a step over it, with an evaluation before it and a save after
    assert MAX_SECONDS <= charged + 1e-3 <= MAX_SECONDS + 3 * step + 1.0
    assert seconds["finish"] < 5.0  # the last checkpoint and the report


def test_each_part_is_the_seconds_of_its_stage_records(budgeted_run):
    report, _ = budgeted_run
    seconds = report.budget["seconds"]
    stage = {s.name: s for s in report.stages}
    set_up_stages = [s for s in report.stages[: [s.name for s in report.stages].index("compile")]
                     if s.name != PROGRESS_EVALS_STAGE]
    assert sum(s.seconds for s in set_up_stages) <= seconds["set_up"] + 1e-3
    assert stage["compile"].ran and stage["compile"].seconds == pytest.approx(seconds["compile"], abs=1e-3)
    assert "density compiled before the first step" in stage["compile"].why
    assert stage[PROGRESS_EVALS_STAGE].seconds == pytest.approx(seconds["progress_evals"], abs=1e-3)
    assert stage["final_eval"].ran and stage["final_eval"].seconds == pytest.approx(seconds["final_eval"], abs=1e-3)


def test_the_progress_evaluations_keep_cheap_points_on_the_curve(budgeted_run):
    """The first scores at most FIRST_PROGRESS_EVAL_RAYS (no cost measured yet); each later one that ran was sized
    to what 2 % of max_seconds had left. 5, 10 and 15 s are due: each one the loop reached was run (for the
    latest due time it had reached), skipped, or gone past by one slow step, and the stage says which. On a loaded
    machine (steps six times slower in a three-process run) the step that reached the end of the budget can
    also pass 15 s, which no step then reaches: the times accounted for are the first of the three, none missing
    between them."""
    report, _ = budgeted_run
    progress = [h for h in report.history if not h.final and not h.full]
    assert progress and progress[0].rays <= FIRST_PROGRESS_EVAL_RAYS
    assert all(h.rays >= MIN_PROGRESS_EVAL_RAYS and set(h.psnr) == {"interpolation", "extrapolation"}
               for h in progress)
    record = next(s for s in report.stages if s.name == PROGRESS_EVALS_STAGE)
    not_run = [float(t) for part in record.why.split("; ") if part.startswith("at ")
               for t in part.split(" s ")[0].removeprefix("at ").split(", ")]  # skipped, or gone past
    ran = [EVAL_EVERY_S * (h.elapsed_s // EVAL_EVERY_S) for h in progress]  # the due time each stood for
    accounted = sorted(ran + not_run)
    assert accounted and accounted == [EVAL_EVERY_S * k for k in range(1, len(accounted) + 1)], record.why
