"""The trainer's time budget: evaluations are not training time; --eval-at evaluations are not charged."""

from __future__ import annotations

from voxnerf.training.budget import Budget


def test_progress_evaluations_pause_training_time_but_still_count_against_the_budget() -> None:
    budget = Budget(max_seconds=100.0, previous_train_seconds=10.0)
    budget.start -= 30.0  # 30 s of wall clock have passed
    budget.paused += 5.0  # 5 of them in a progress evaluation
    assert abs(budget.train_seconds - 35.0) < 0.5
    assert abs(budget.remaining() - 60.0) < 0.5


def test_eval_at_evaluations_are_not_charged_to_max_seconds() -> None:
    budget = Budget(max_seconds=100.0)
    budget.start -= 30.0
    budget.paused += 20.0
    budget.excluded += 20.0  # a full --eval-at evaluation
    assert abs(budget.train_seconds - 10.0) < 0.5
    assert abs(budget.remaining() - 90.0) < 0.5


def test_no_limit_means_infinite_remaining_time() -> None:
    budget = Budget(None)
    budget.start -= 1e6
    assert budget.remaining() == float("inf")
