"""The run's time budget: wall clock of the whole command, training seconds, what ``max_seconds`` leaves.

Torch-free; the clock is injectable so that tests can drive it.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

Clock = Callable[[], float]


class Budget:
    """Wall clock of the whole command; ``train_seconds`` excludes time spent in evaluations (``paused``).

    ``remaining()`` charges everything to ``max_seconds`` except the ``--eval-at`` evaluations (``excluded``):
    those are a benchmark's measuring instrument, and charging them would shorten the run being measured.
    """

    def __init__(self, max_seconds: float | None, previous_train_seconds: float = 0.0,
                 clock: Clock = time.perf_counter) -> None:
        self.clock = clock
        self.start = clock()
        self.max_seconds = max_seconds
        self.previous = previous_train_seconds
        self.paused = 0.0
        self.excluded = 0.0

    @property
    def wall(self) -> float:
        """Seconds since this budget started (this command only; a resumed run's earlier time is ``previous``)."""
        return self.clock() - self.start

    @property
    def train_seconds(self) -> float:
        """Training seconds of the whole run, earlier commands of a resumed run included."""
        return self.previous + self.wall - self.paused

    def remaining(self) -> float:
        return math.inf if self.max_seconds is None else self.max_seconds - self.previous - self.wall + self.excluded


class TrainingProgress:
    """How far the training loop is through its limits, as a fraction in [0, 1]: the larger of steps over
    ``max_iters`` and training seconds over the seconds the budget leaves for training (``max_seconds`` less the
    set-up before the loop and ``reserve()``, the final evaluation's share). Built when the loop starts.

    ``fraction(iteration)`` is None when neither limit bounds the run.
    """

    def __init__(self, budget: Budget, max_iters: int | None, reserve: Callable[[], float]) -> None:
        self.budget, self.max_iters, self.reserve = budget, max_iters, reserve
        self.set_up = budget.train_seconds - budget.previous  # this command's seconds before the loop

    def fraction(self, iteration: int) -> float | None:
        fractions = []
        if self.max_iters:
            fractions.append(iteration / self.max_iters)
        if self.budget.max_seconds is not None:
            done = self.budget.train_seconds - self.set_up
            left = max(self.budget.remaining() - self.reserve(), 0.0)
            fractions.append(done / (done + left) if done + left > 0 else 1.0)
        return min(max(fractions), 1.0) if fractions else None
