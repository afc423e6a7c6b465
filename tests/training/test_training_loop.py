"""The training loop (voxnerf/training/loop.py) with a stub step: order of duties, limits, divergence guard."""

from __future__ import annotations

import math

import pytest
import torch

from voxnerf.errors import TrainingDiverged
from voxnerf.model.voxnerf_model import Losses
from voxnerf.training.budget import Budget
from voxnerf.training.loop import Callback, Limits, LoopState, run_loop


class FakeClock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


class StubStep:
    """Losses from a list (one per step); logs batch / losses / apply calls; each step takes ``seconds``."""

    def __init__(self, totals: list[float], log: list, clock: FakeClock | None = None, seconds: float = 1.0):
        self.totals, self.log, self.clock, self.seconds = iter(totals), log, clock, seconds

    def batch(self) -> str:
        self.log.append("batch")
        return "the batch"

    def losses(self, batch: str) -> Losses:
        assert batch == "the batch"
        self.log.append("losses")
        if self.clock is not None:
            self.clock.now += self.seconds
        t = torch.tensor(next(self.totals))
        return Losses(t, t / 2, torch.tensor(0.0), torch.tensor(0.0), torch.tensor(0.0))

    def apply(self) -> None:
        self.log.append("apply")


class Recorder(Callback):
    def __init__(self, log: list) -> None:
        self.log = log

    def before_step(self, state: LoopState) -> None:
        self.log.append(("before", state.iteration))

    def after_step(self, state: LoopState) -> None:
        self.log.append(("after", state.iteration, state.last_loss))


class AfterOnly(Callback):
    def __init__(self, log: list) -> None:
        self.log = log

    def after_step(self, state: LoopState) -> None:
        self.log.append("after-only")


def _limits(max_iters: int | None = None, max_seconds: float | None = None, clock=None, **kw) -> Limits:
    return Limits(max_iters, Budget(max_seconds, clock=clock or FakeClock()), **kw)


def test_each_step_is_batch_losses_guard_apply_then_callbacks_in_order():
    log: list = []
    state = LoopState(iteration=10)
    status = run_loop(StubStep([0.5, 0.25], log), state, [Recorder(log), AfterOnly(log)], _limits(max_iters=12))
    assert status == "succeeded" and state.iteration == 12 and state.last_loss == 0.25
    step = ["batch", "losses", "apply"]
    assert log == [("before", 10), *step, ("after", 11, 0.5), "after-only",
                   ("before", 11), *step, ("after", 12, 0.25), "after-only"]


def test_a_run_already_at_max_iters_takes_no_step():
    log: list = []
    state = LoopState(iteration=5)
    assert run_loop(StubStep([], log), state, [Recorder(log)], _limits(max_iters=5)) == "succeeded"
    assert log == [] and math.isnan(state.last_loss)


def test_the_time_budget_stops_the_loop_once_max_seconds_of_training_are_spent():
    clock, log = FakeClock(), []
    limits = _limits(max_seconds=10.0, clock=clock)
    clock.now += 30.0  # the set-up: not charged
    limits.budget.start_training()
    state = LoopState(0)
    assert run_loop(StubStep([1.0] * 100, log, clock), state, [], limits) == "succeeded"
    assert state.iteration == 10 and limits.budget.train_seconds == 10.0  # 1 s per step, nothing held back


def test_should_stop_cancels_between_steps():
    log: list = []
    state = LoopState(0)
    limits = _limits(max_iters=100, should_stop=lambda: state.iteration >= 3)
    assert run_loop(StubStep([1.0] * 100, log), state, [], limits) == "cancelled"
    assert state.iteration == 3


@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_a_non_finite_loss_raises_before_the_update_and_the_callbacks(bad):
    log: list = []
    state = LoopState(0)
    with pytest.raises(TrainingDiverged, match=rf"loss became {bad} at iteration 2 \(colour {bad}"):
        run_loop(StubStep([1.0, 1.0, bad], log), state, [Recorder(log)], _limits(max_iters=10))
    assert state.iteration == 2 and state.last_loss == 1.0
    assert log[-3:] == [("before", 2), "batch", "losses"]  # no apply, no after_step


def test_a_callback_raising_stops_the_loop():
    class Diverging(Callback):
        def after_step(self, state: LoopState) -> None:
            raise TrainingDiverged(f"weights became NaN/inf before iteration {state.iteration}")

    state = LoopState(0)
    with pytest.raises(TrainingDiverged, match="before iteration 1"):
        run_loop(StubStep([1.0], []), state, [Diverging()], _limits(max_iters=10))
