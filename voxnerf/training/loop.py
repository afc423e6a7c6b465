"""The training loop: batch -> step -> divergence guard -> callbacks, until a limit says stop.

Everything periodic (learning rate, occupancy grid, evaluations, checkpoints, progress events and bar) is a
:class:`Callback` (``voxnerf/training/callbacks.py``); set-up and the report are ``voxnerf/training/run.py``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from voxnerf.training.budget import Budget
from voxnerf.training.step import Losses, divergence_guard


@dataclass
class LoopState:
    """What the loop shares with its callbacks: steps done (the run's, a resumed run's earlier ones included),
    the last step's loss (NaN before the first) and the learning rate of the last step."""

    iteration: int
    last_loss: float = math.nan
    lr: float = math.nan


class Callback:
    """A periodic duty. ``before_step`` runs before a step's batch is drawn, ``after_step`` after its optimiser
    update (``state.iteration`` counts it already). The loop calls only the hooks a subclass overrides."""

    def before_step(self, state: LoopState) -> None:
        """Nothing by default."""

    def after_step(self, state: LoopState) -> None:
        """Nothing by default."""


class Step(Protocol):
    def batch(self) -> Any: ...

    def losses(self, batch: Any) -> Losses: ...

    def apply(self) -> None: ...


@dataclass
class Limits:
    """When the loop stops: ``max_iters`` steps, the budget's time spent (``Budget.remaining()``), or
    ``should_stop()`` (status "cancelled")."""

    max_iters: int | None
    budget: Budget
    should_stop: Callable[[], bool] | None = None

    def status(self, iteration: int) -> str | None:
        """None to go on, else the run's status."""
        if self.max_iters is not None and iteration >= self.max_iters:
            return "succeeded"
        if self.budget.remaining() <= 0:
            return "succeeded"
        if self.should_stop is not None and self.should_stop():
            return "cancelled"
        return None


def _hooks(callbacks: Sequence[Callback], name: str) -> list[Callable[[LoopState], None]]:
    return [getattr(c, name) for c in callbacks if getattr(type(c), name) is not getattr(Callback, name)]


def run_loop(step: Step, state: LoopState, callbacks: Sequence[Callback], limits: Limits) -> str:
    """Run steps until ``limits`` says stop; returns the status. TrainingDiverged (from the guard or a
    callback) propagates, with ``state`` at the failing iteration."""
    before, after = _hooks(callbacks, "before_step"), _hooks(callbacks, "after_step")
    while (status := limits.status(state.iteration)) is None:
        for hook in before:
            hook(state)
        losses = step.losses(step.batch())
        state.last_loss = divergence_guard(losses, state.iteration)
        step.apply()
        state.iteration += 1
        for hook in after:
            hook(state)
    return status
