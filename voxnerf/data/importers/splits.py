"""The paper's evaluation splits (section IV-A) for an imported frame sequence: one rule for every importer.

The paper trains on ~10% of the frames taken uniformly, tests interpolation on the frames midway between two
consecutive training frames, and extrapolation on blocks of frames held out of training, away from every
training frame. :func:`paper_splits` turns that into indices along the capture order:

- training candidates: every ``step``-th frame, ``step = round(1 / train_fraction)`` (0, step, 2 step, ...);
- ``gap_fraction`` of those candidates (at least 2) are removed in ``n_gaps`` evenly spaced blocks of at most
  ``max_gap_slots`` consecutive candidates each (as in the shared redkitchen scene: 1000 frames, every 10th,
  five 60-frame gaps -> 70 training frames);
- interpolation: the frame midway (``a + step // 2``) between consecutive training frames ``a, a + step``;
- extrapolation: inside each gap, the frames midway between removed candidates that are at least
  ``min_distance`` (default ``step``) frames from every training frame.

The splits are disjoint; frames none of them names stay in the scene unused.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import asdict, dataclass


@dataclass(frozen=True)
class PaperSplitRule:
    """The parameters of :func:`paper_splits` (reported in an importer's summary)."""

    train_fraction: float = 0.1
    gap_fraction: float = 0.3
    max_gap_slots: int = 6
    min_distance: int | None = None  # frames; None: one training step

    @property
    def step(self) -> int:
        """Frames between training candidates."""
        return max(2, round(1 / self.train_fraction))

    def describe(self) -> dict:
        """The parameters, ``min_distance`` resolved to frames and the training step added."""
        distance = self.step if self.min_distance is None else self.min_distance
        return {"rule": "paper", **asdict(self), "train_every": self.step, "min_distance": distance}


@dataclass(frozen=True)
class SplitIndices:
    """Frame indices (into the imported frame order) of each split, ascending."""

    train: list[int]
    interpolation: list[int]
    extrapolation: list[int]


class SplitError(ValueError):
    """The sequence is too short for the rule; the message says what is missing."""


def _gap_slots(n_slots: int, rule: PaperSplitRule) -> set[int]:
    """Indices (into the training candidates) removed for the extrapolation gaps."""
    removed = max(2, round(rule.gap_fraction * n_slots))
    n_gaps = max(1, math.ceil(removed / rule.max_gap_slots))
    per_gap = removed // n_gaps
    slots: set[int] = set()
    for k in range(n_gaps):
        centre = (k + 0.5) * n_slots / n_gaps
        first = math.floor(centre - per_gap / 2)
        slots.update(range(max(first, 1), min(first + per_gap, n_slots - 1)))
    return slots


def paper_splits(n_frames: int, rule: PaperSplitRule | None = None) -> SplitIndices:
    """Train / interpolation / extrapolation indices for ``n_frames`` frames in capture order (module doc).

    Raises SplitError when the sequence is too short to give at least two training frames, one interpolation
    and one extrapolation frame.
    """
    rule = rule or PaperSplitRule()
    if not 0 < rule.train_fraction <= 0.5:
        raise SplitError(f"train_fraction must be in (0, 0.5], got {rule.train_fraction}")
    step = rule.step
    min_distance = step if rule.min_distance is None else rule.min_distance
    slots = list(range(0, n_frames, step))
    gaps = _gap_slots(len(slots), rule) if len(slots) >= 4 else set()
    train = [frame for k, frame in enumerate(slots) if k not in gaps]
    interpolation = [a + step // 2 for a, b in itertools.pairwise(train) if b - a == step]
    extrapolation = []
    for a, b in itertools.pairwise(train):
        if b - a > step:
            middles = range(a + step // 2, b, step)
            extrapolation += [j for j in middles if min(j - a, b - j) >= min_distance]
    if len(train) < 2 or not interpolation or not extrapolation:
        raise SplitError(
            f"{n_frames} frames are too few for the paper's splits (training every {step}th frame, "
            f"{rule.gap_fraction:.0%} of them held out in gaps): got {len(train)} training, {len(interpolation)} "
            f"interpolation and {len(extrapolation)} extrapolation frames; need at least {5 * step} frames"
        )
    return SplitIndices(train, interpolation, extrapolation)


def split_keys(file_paths: list[str], rule: PaperSplitRule | None = None) -> tuple[dict, dict]:
    """The transforms.json split keys for frames ``file_paths`` (capture order), and their summary.

    Keys: ``train_filenames`` and ``eval_splits: {"interpolation": [...], "extrapolation": [...]}``.
    """
    rule = rule or PaperSplitRule()
    idx = paper_splits(len(file_paths), rule)

    def names(indices: list[int]) -> list[str]:
        return [file_paths[i] for i in indices]

    keys = {
        "train_filenames": names(idx.train),
        "eval_splits": {"interpolation": names(idx.interpolation), "extrapolation": names(idx.extrapolation)},
    }
    summary = {
        **rule.describe(),
        "train": len(idx.train),
        "interpolation": len(idx.interpolation),
        "extrapolation": len(idx.extrapolation),
    }
    return keys, summary
