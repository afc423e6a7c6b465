"""The importers' ``--splits paper`` rule: ~10% uniform training frames, interpolation frames midway between
consecutive training frames, extrapolation frames in gaps away from every training frame, disjoint splits."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from voxnerf.data.importers.splits import PaperSplitRule, SplitError, paper_splits, split_keys


def check_properties(n: int, rule: PaperSplitRule) -> None:
    idx = paper_splits(n, rule)
    step = max(2, round(1 / rule.train_fraction))
    distance = step if rule.min_distance is None else rule.min_distance
    train, interp, extrap = idx.train, idx.interpolation, idx.extrapolation
    for split in (train, interp, extrap):
        assert split == sorted(set(split)) and all(0 <= i < n for i in split)
    assert not (set(train) & set(interp) or set(train) & set(extrap) or set(interp) & set(extrap))
    # uniform: training frames on one grid of `step`, about train_fraction of the frames
    assert all(i % step == 0 for i in train) and train[0] == 0
    slots = len(range(0, n, step))
    assert len(train) <= slots and len(train) >= slots - max(2, round(rule.gap_fraction * slots)) - 1
    assert len(train) / n <= rule.train_fraction * 1.1 + 1 / n
    # interpolation: midway between two consecutive training frames
    train_set = set(train)
    for j in interp:
        a = j - step // 2
        assert a in train_set and a + step in train_set
    # extrapolation: at least `distance` frames from every training frame
    assert extrap and all(min(abs(j - t) for t in train) >= distance for j in extrap)


@settings(max_examples=200, deadline=None)
@given(n=st.integers(50, 6000))
def test_paper_split_properties(n):
    check_properties(n, PaperSplitRule())


@settings(max_examples=100, deadline=None)
@given(
    n=st.integers(200, 3000),
    fraction=st.sampled_from([0.05, 0.1, 0.125, 0.2]),
    gaps=st.sampled_from([0.2, 0.3, 0.4]),
    max_slots=st.integers(3, 8),
)
def test_split_properties_for_other_parameters(n, fraction, gaps, max_slots):
    check_properties(n, PaperSplitRule(train_fraction=fraction, gap_fraction=gaps, max_gap_slots=max_slots))


def test_redkitchen_numbers():
    """1000 frames: every 10th frame, five gaps of six training slots -> 70 training frames, as the shared
    redkitchen scene has; extrapolation blocks inside the five gaps."""
    idx = paper_splits(1000)
    assert len(idx.train) == 70
    assert idx.train[:8] == [0, 10, 20, 30, 40, 50, 60, 130]
    blocks = [j for j in idx.extrapolation if 60 < j < 130]
    assert blocks == [75, 85, 95, 105, 115] and len(idx.extrapolation) == 25
    assert idx.interpolation[:6] == [5, 15, 25, 35, 45, 55]


def test_too_few_frames_is_an_error():
    with pytest.raises(SplitError, match="10 frames are too few for the paper's splits.*at least 50 frames"):
        paper_splits(10)
    with pytest.raises(SplitError, match="train_fraction"):
        paper_splits(100, PaperSplitRule(train_fraction=0.9))


def test_split_keys_name_the_frames_and_report_the_rule():
    names = [f"images/{i:04d}.jpg" for i in range(100)]
    keys, summary = split_keys(names)
    idx = paper_splits(100)
    assert keys == {
        "train_filenames": [names[i] for i in idx.train],
        "eval_splits": {
            "interpolation": [names[i] for i in idx.interpolation],
            "extrapolation": [names[i] for i in idx.extrapolation],
        },
    }
    assert summary == {
        "rule": "paper", "train_fraction": 0.1, "gap_fraction": 0.3, "max_gap_slots": 6, "min_distance": 10,
        "train_every": 10, "train": 7, "interpolation": 5, "extrapolation": 2,
    }
