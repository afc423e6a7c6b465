"""benchmarks/compare_trees.py: the side-by-side table of two source trees, and a failing tree named."""

from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
compare_trees = importlib.import_module("compare_trees")


def test_table_gives_medians_and_ratios():
    results = {
        "before": [{"samples_per_s": 100.0, "render_s": 2.0}, {"samples_per_s": 300.0, "render_s": 1.0},
                   {"samples_per_s": 200.0, "render_s": 4.0}],
        "after": [{"samples_per_s": 210.0, "render_s": 2.2}, {"samples_per_s": 190.0, "render_s": 1.8},
                  {"samples_per_s": 220.0, "render_s": 1.9}],
    }
    args = argparse.Namespace(before=Path("/b"), after=Path("/a"), scene=None, downscale=1, iters=5, rounds=3)
    text = "\n".join(compare_trees.table(results, args))
    assert "| before (`/b`) | 200 | 2.000 s | 100, 300, 200 |" in text
    assert "| after (`/a`) | 210 | 1.900 s |" in text
    assert "training samples/s 1.050, render time 0.950" in text


def test_a_tree_that_cannot_train_is_named(tmp_path):
    broken = tmp_path / "tree"
    (broken / "voxnerf").mkdir(parents=True)
    (broken / "voxnerf" / "__init__.py").write_text("raise ImportError('broken tree')\n")
    with pytest.raises(SystemExit, match=f"{broken}: measurement failed"):
        compare_trees.measure(broken, tmp_path / "scene", tmp_path / "run", 1, 1)


def test_a_measurement_renders_the_run_it_is_given_not_its_own(tmp_path_factory, tmp_path, monkeypatch):
    from synthetic_fixtures import make_micro_scene

    # the check is on which run is rendered: the measured processes run the step eagerly (torch.compile a no-op,
    # sparing two cold compilations of a graph no other test compiles) and render 64x48 views
    monkeypatch.setenv("TORCHDYNAMO_DISABLE", "1")
    small = (64, 48)

    scene = make_micro_scene(tmp_path_factory, "compare-trees")
    tree = Path(__file__).resolve().parents[1]
    missing = tmp_path / "no-such-run"
    with pytest.raises(SystemExit, match="no checkpoint"):
        compare_trees.measure(tree, scene, tmp_path / "first", 1, 1, render_run=missing, render_size=small)
    assert (tmp_path / "first" / "checkpoint.pt").is_file()  # it trained its own run, then rendered the given one
    # the first run's checkpoint, rendered by a later measurement (main() passes every run the first one's)
    elsewhere = compare_trees.measure(tree, scene, tmp_path / "again", 1, 1, render_run=tmp_path / "first",
                                       render_size=small)
    assert elsewhere["samples_per_s"] > 0 and elsewhere["render_s"] > 0
