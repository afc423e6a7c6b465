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
