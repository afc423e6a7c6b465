"""An exponential moving average of the field's parameters (Polyak averaging, ``schedule.weight_average``).

The optimiser steps the live parameters as before; every :data:`WEIGHT_AVERAGE_EVERY` steps the average moves
towards them, ``average += rate * (live - average)`` with ``rate = 1 - decay^every``, so it follows the live
parameters with a lag of about ``1 / (1 - decay)`` steps. Early in a run the rate is larger
(:meth:`WeightAverage.rate_at`, TensorFlow's ``ExponentialMovingAverage`` warm-up): the average then follows
about the last tenth of the steps made, so a short run's average is not held back by the field's random start.
What a run gives its users is the average: the checkpoint's model (renders, the viewer, exports), the progress
evaluations and the final evaluation. The live parameters go into the checkpoint too (``field_live``), so a
resumed run goes on from them and from the average both.
"""

from __future__ import annotations

import copy
from collections.abc import Iterator
from contextlib import contextmanager

import torch
from torch import nn

from voxnerf.training.loop import Callback, LoopState

WEIGHT_AVERAGE_EVERY = 4  # steps between updates of the average: its cost per step is a quarter of one pass


class WeightAverage(Callback):
    """The average of ``field``'s parameters with ``decay`` per step, from ``start`` (a state dict of the field:
    a resumed run's average) or from the field's parameters as they are now."""

    def __init__(self, field: nn.Module, decay: float, start: dict | None = None,
                 every: int = WEIGHT_AVERAGE_EVERY) -> None:
        if not 0.0 < decay < 1.0:
            raise ValueError(f"weight_average: the decay per step must lie in (0, 1), got {decay}")
        if every < 1:
            raise ValueError(f"weight_average: update every >= 1 steps, got {every}")
        self.field, self.every = field, every
        self.rate = 1.0 - decay**every  # the share of the gap to the live parameters closed by one update
        averaged = copy.deepcopy(field).requires_grad_(False)
        if start is not None:
            averaged.load_state_dict(start)
        self.names = [name for name, _ in field.named_parameters()]
        self.live = [p for _, p in field.named_parameters()]
        self.average = [p for _, p in averaged.named_parameters()]

    @classmethod
    def of(cls, field: nn.Module, decay: float, start: dict | None = None) -> WeightAverage | None:
        """The average a run with ``schedule.weight_average = decay`` keeps, None for 0 (off)."""
        return cls(field, decay, start) if decay > 0 else None

    def after_step(self, state: LoopState) -> None:
        if state.iteration % self.every == 0:
            self.update(self.rate_at(state.iteration // self.every))

    def rate_at(self, update: int) -> float:
        """The share of the gap closed by the run's ``update``-th update (1, 2, ...; counted from the iteration,
        so a resumed run goes on with its own): ``9 / (10 + update)`` while that is larger than ``1 - decay^every``
        (up to update 443 at decay 0.995, step 1,772), which then holds."""
        return max(self.rate, 9.0 / (10.0 + max(update, 0)))

    @torch.no_grad()
    def update(self, rate: float | None = None) -> None:
        """One move of the average towards the live parameters, closing ``rate`` of the gap (``1 - decay^every``
        unless given)."""
        rate = self.rate if rate is None else rate
        for average, live in zip(self.average, self.live, strict=True):
            average.lerp_(live, rate)

    def field_state(self) -> dict:
        """The field's state dict with the averaged parameters in place of the live ones (buffers as they are)."""
        state = self.field.state_dict()
        for name, average in zip(self.names, self.average, strict=True):
            state[name] = average.detach().clone()
        return state

    @torch.no_grad()
    def apply(self) -> None:
        """Put the averaged parameters into the field, for good (the run's end: its final evaluation)."""
        for live, average in zip(self.live, self.average, strict=True):
            live.copy_(average)

    @contextmanager
    def applied(self) -> Iterator[None]:
        """The field holds the averaged parameters inside the block and its live ones again after it, whatever
        the block raised."""
        with torch.no_grad():
            kept = [p.detach().clone() for p in self.live]
            self.apply()
        try:
            yield
        finally:
            with torch.no_grad():
                for live, value in zip(self.live, kept, strict=True):
                    live.copy_(value)
