"""The trainer's time budget (voxnerf/training/budget.py), on a fake clock: max_seconds charges the training loop's
steps, progress evaluations and checkpoints; the set-up, compilation, --eval-at and final evaluations and what
follows the loop are not charged; the report's accounting of the parts adds up to the command's wall clock."""

from __future__ import annotations

import math

import pytest

from voxnerf.training.budget import CHARGED_PARTS, EXCLUDED_PARTS, Budget, budget_line


class FakeClock:
    def __init__(self, now: float = 0.0) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now


def _budget(max_seconds: float | None = 100.0, previous: float = 0.0) -> tuple[FakeClock, Budget]:
    clock = FakeClock(1000.0)
    return clock, Budget(max_seconds, previous, clock=clock)


def test_the_set_up_is_neither_training_nor_charged():
    clock, budget = _budget()
    clock.now += 12.0  # loading the scene, the prior, the octree...
    assert budget.train_seconds == 0.0 and budget.charged == 0.0 and budget.remaining() == 100.0
    assert budget.set_up == 12.0
    budget.start_training()
    clock.now += 30.0
    assert budget.set_up == 12.0 and budget.train_seconds == 30.0 and budget.remaining() == 70.0


def test_progress_evaluations_and_checkpoints_pause_training_but_are_charged():
    clock, budget = _budget(previous=10.0)
    budget.start_training()
    clock.now += 30.0
    budget.add("progress_evals", 5.0)  # 5 of the 30 s in a progress evaluation
    budget.add("checkpoints", 1.0)
    assert budget.train_seconds == pytest.approx(10.0 + 24.0)
    assert budget.remaining() == pytest.approx(100.0 - 10.0 - 30.0)


@pytest.mark.parametrize("part", ["compile", "eval_at"])
def test_compilation_and_eval_at_evaluations_are_not_charged(part):
    clock, budget = _budget()
    budget.start_training()
    clock.now += 30.0
    budget.add(part, 20.0)
    assert budget.train_seconds == pytest.approx(10.0) and budget.remaining() == pytest.approx(90.0)


def test_training_stops_counting_when_the_loop_ends():
    clock, budget = _budget()
    budget.start_training()
    clock.now += 40.0
    budget.end_training()
    clock.now += 25.0  # the last checkpoint, the final evaluation, the report
    budget.add("final_eval", 20.0)
    assert budget.train_seconds == 40.0 and budget.remaining() == 60.0


def test_the_accounting_adds_up_to_the_wall_clock_and_gives_the_trained_share():
    clock, budget = _budget(max_seconds=100.0)
    clock.now += 4.0
    budget.start_training()
    clock.now += 101.0
    budget.add("compile", 3.0)
    budget.add("progress_evals", 1.5)
    budget.add("checkpoints", 0.5)
    budget.add("eval_at", 2.0)
    budget.end_training()
    clock.now += 7.0
    budget.add("final_eval", 6.0)
    account = budget.accounting()
    seconds = account["seconds"]
    assert seconds == {"set_up": 4.0, "compile": 3.0, "training": 94.0, "progress_evals": 1.5, "checkpoints": 0.5,
                       "eval_at": 2.0, "final_eval": 6.0, "finish": 1.0, "wall": 112.0}
    assert sum(v for k, v in seconds.items() if k != "wall") == pytest.approx(seconds["wall"])
    assert account["max_seconds"] == 100.0 and account["trained_share"] == 0.94
    assert "progress evaluations" in account["charged"] and "final evaluations" in account["not_charged"]


def test_a_resumed_run_counts_its_earlier_training_in_the_share():
    clock, budget = _budget(max_seconds=100.0, previous=60.0)
    budget.start_training()
    clock.now += 40.0
    budget.end_training()
    assert budget.accounting()["trained_share"] == 1.0 and budget.accounting()["seconds"]["training"] == 40.0


def test_a_run_stopped_in_set_up_accounts_its_time_as_set_up():
    clock, budget = _budget()
    clock.now += 3.0
    account = budget.accounting()
    assert account["seconds"]["set_up"] == 3.0 and account["seconds"]["training"] == 0.0
    assert account["seconds"]["wall"] == 3.0 and account["trained_share"] == 0.0


def test_no_limit_means_infinite_remaining_time_and_no_share():
    clock, budget = _budget(max_seconds=None)
    budget.start_training()
    clock.now += 1e6
    assert budget.remaining() == math.inf and budget.accounting()["trained_share"] is None


@pytest.mark.parametrize(("part", "seconds", "match"), [
    ("lunch", 1.0, "unknown budget part 'lunch'"), ("compile", -1.0, "compile: seconds must be finite and >= 0"),
    ("progress_evals", math.nan, "finite"), ("final_eval", math.inf, "finite"),
])
def test_an_unknown_part_or_bad_seconds_are_refused(part, seconds, match):
    _, budget = _budget()
    with pytest.raises(ValueError, match=match):
        budget.add(part, seconds)
    assert all(budget.parts[p] == 0.0 for p in (*CHARGED_PARTS, *EXCLUDED_PARTS))


def test_the_command_line_says_the_share_trained_and_what_came_on_top():
    clock, budget = _budget(max_seconds=100.0)
    clock.now += 4.0
    budget.start_training()
    clock.now += 100.0
    budget.add("progress_evals", 1.5)
    budget.end_training()
    clock.now += 6.0
    budget.add("final_eval", 6.0)
    assert budget_line(budget.accounting()) == (
        "budget: 98.5% of max_seconds trained (1.5 s of progress evaluations, 0.0 s of checkpoints); on top: set-up "
        "4.0 s, final evaluation 6.0 s; wall 110.0 s")
    assert budget_line(_budget(max_seconds=None)[1].accounting()).startswith("budget: 0.0 s trained (no max_seconds)")
