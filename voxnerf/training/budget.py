"""The run's time budget: what ``max_seconds`` bounds, the training seconds, and where the command's time went.

``max_seconds`` is a budget of training: the training loop's steps, and the progress evaluations and checkpoints
that interrupt it (:data:`CHARGED_PARTS`). The command's other parts are not charged to it (:data:`EXCLUDED_PARTS`):
the set-up before the loop (loading the scene, the prior, the octree, the pseudo depth: preparing the training
data, cached per scene), the compilation of the step (once per machine and configuration, cached), the
``--eval-at`` evaluations and the final evaluation (the run's measurements), and what follows the loop (the last
checkpoint, the report). Each is timed and reported (:meth:`Budget.accounting`, report.json's ``budget``), so the
command's wall clock is the sum of its parts.

Torch-free; the clock is injectable so that tests can drive it.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

Clock = Callable[[], float]

# Parts of the command that pause training: those charged to ``max_seconds`` and those that are not.
CHARGED_PARTS = ("progress_evals", "checkpoints")
EXCLUDED_PARTS = ("compile", "eval_at", "final_eval")
CHARGED = "the training loop's steps, progress evaluations and checkpoints"
EXCLUDED = ("the set-up before the loop, the step's compilation, the --eval-at and final evaluations, and what follows "
            "the loop (the last checkpoint, the report)")


class Budget:
    """The command's clock in three phases: set-up (until :meth:`start_training`), the training loop (until
    :meth:`end_training`) and what follows. During the loop the parts added (:meth:`add`) pause training;
    ``train_seconds`` is what is left of the loop's time, earlier commands of a resumed run included
    (``previous``). ``remaining()`` is ``max_seconds`` less the training seconds and the charged parts.
    """

    def __init__(self, max_seconds: float | None, previous_train_seconds: float = 0.0,
                 clock: Clock = time.perf_counter) -> None:
        self.clock = clock
        self.start = clock()
        self.max_seconds = max_seconds
        self.previous = previous_train_seconds
        self.parts: dict[str, float] = dict.fromkeys((*CHARGED_PARTS, *EXCLUDED_PARTS), 0.0)
        self.loop_start: float | None = None
        self.loop_end: float | None = None

    def start_training(self) -> None:
        """The set-up is over: the training loop's time starts now (the step's build and compilation included)."""
        if self.loop_start is None:
            self.loop_start = self.clock()

    def end_training(self) -> None:
        """The training loop is over: the training seconds stop here."""
        self.start_training()
        if self.loop_end is None:
            self.loop_end = self.clock()

    def add(self, part: str, seconds: float) -> None:
        """``seconds`` spent in ``part`` (one of :data:`CHARGED_PARTS` or :data:`EXCLUDED_PARTS`); during the loop
        they are not training time. ValueError for an unknown part or seconds that are negative or not finite."""
        if part not in self.parts:
            raise ValueError(f"unknown budget part {part!r}; choose from {sorted(self.parts)}")
        if not (math.isfinite(seconds) and seconds >= 0):
            raise ValueError(f"budget part {part}: seconds must be finite and >= 0, got {seconds!r}")
        self.parts[part] += seconds

    @property
    def wall(self) -> float:
        """Seconds since this budget started (this command only; a resumed run's earlier time is ``previous``)."""
        return self.clock() - self.start

    @property
    def set_up(self) -> float:
        """Seconds before the training loop (all of them while it has not started)."""
        return (self.clock() if self.loop_start is None else self.loop_start) - self.start

    @property
    def loop_wall(self) -> float:
        """Wall-clock seconds of the training loop so far."""
        if self.loop_start is None:
            return 0.0
        return (self.clock() if self.loop_end is None else self.loop_end) - self.loop_start

    @property
    def paused(self) -> float:
        """Seconds of the loop that were not training (evaluations, checkpoints, compilation)."""
        return sum(self.parts[p] for p in (*CHARGED_PARTS, "compile", "eval_at"))

    @property
    def this_command_training(self) -> float:
        """This command's training seconds."""
        return self.loop_wall - self.paused

    @property
    def train_seconds(self) -> float:
        """Training seconds of the whole run, earlier commands of a resumed run included."""
        return self.previous + self.this_command_training

    @property
    def charged(self) -> float:
        """This command's seconds charged to ``max_seconds``: training and the charged parts."""
        return self.this_command_training + sum(self.parts[p] for p in CHARGED_PARTS)

    def remaining(self) -> float:
        return math.inf if self.max_seconds is None else self.max_seconds - self.previous - self.charged

    def accounting(self) -> dict[str, Any]:
        """report.json's ``budget``: ``max_seconds``, ``trained_share`` (the run's training seconds over
        ``max_seconds``; None without it), what is charged and what is not, and this command's seconds by part
        (``set_up``, ``compile``, ``training``, ``progress_evals``, ``checkpoints``, ``eval_at``, ``final_eval``,
        ``finish``: what followed the loop besides the final evaluation) with their sum, ``wall``."""
        wall = self.wall
        seconds = {"set_up": self.set_up, "compile": self.parts["compile"], "training": self.this_command_training,
                   "progress_evals": self.parts["progress_evals"], "checkpoints": self.parts["checkpoints"],
                   "eval_at": self.parts["eval_at"], "final_eval": self.parts["final_eval"]}
        after_loop = 0.0 if self.loop_end is None else self.clock() - self.loop_end
        seconds["finish"] = max(after_loop - self.parts["final_eval"], 0.0)
        seconds["wall"] = wall
        share = None if not self.max_seconds else round(self.train_seconds / self.max_seconds, 4)
        return {"max_seconds": self.max_seconds, "trained_share": share, "charged": CHARGED, "not_charged": EXCLUDED,
                "seconds": {name: round(value, 3) for name, value in seconds.items()}}


class TrainingProgress:
    """How far the training loop is through its limits, as a fraction in [0, 1]: the larger of steps over
    ``max_iters`` and training seconds over the training seconds the budget allows (those so far plus
    ``remaining()``: ``max_seconds`` less what the charged parts took).

    ``fraction(iteration)`` is None when neither limit bounds the run.
    """

    def __init__(self, budget: Budget, max_iters: int | None) -> None:
        self.budget, self.max_iters = budget, max_iters

    def fraction(self, iteration: int) -> float | None:
        fractions = []
        if self.max_iters:
            fractions.append(iteration / self.max_iters)
        if self.budget.max_seconds is not None:
            done = self.budget.train_seconds
            left = max(self.budget.remaining(), 0.0)
            fractions.append(done / (done + left) if done + left > 0 else 1.0)
        return min(max(fractions), 1.0) if fractions else None


def budget_line(accounting: dict[str, Any]) -> str:
    """One line of :meth:`Budget.accounting` for the command line: the share of ``max_seconds`` that trained, the
    charged parts, what came on top, and the wall clock."""
    seconds = accounting["seconds"]
    on_top = ", ".join(f"{name.replace('_', ' ')} {seconds[key]:.1f} s" for key, name in (
        ("set_up", "set-up"), ("compile", "compilation"), ("eval_at", "eval_at evaluations"),
        ("final_eval", "final evaluation"), ("finish", "saving")) if seconds[key] >= 0.05)
    share = accounting["trained_share"]
    trained = (f"{share:.1%} of max_seconds trained" if share is not None
               else f"{seconds['training']:.1f} s trained (no max_seconds)")
    return (f"budget: {trained} ({seconds['progress_evals']:.1f} s of progress evaluations, "
            f"{seconds['checkpoints']:.1f} s of checkpoints); on top: {on_top or 'nothing'}; "
            f"wall {seconds['wall']:.1f} s")
