"""The render workers' model cache (worker/model_cache.py) while a job trains: an unchanged checkpoint is never
loaded twice, a newer one (renamed over the old, as the trainer saves) is loaded at the next request and replaces
the run's older model, and a load reads the file it identified even when a newer one lands meanwhile."""

from __future__ import annotations

import os
from pathlib import Path

from tiny_run import write_tiny_run

from voxnerf.files import CHECKPOINT
from voxnerf.training.checkpoint import load_checkpoint
from worker.model_cache import ModelCache


def _save_newer(run_dir: Path, iteration: int) -> None:
    """A checkpoint of ``iteration`` renamed over ``run_dir``'s, as the trainer's atomic save does."""
    staged = write_tiny_run(run_dir.parent / f"staged-{iteration}", seed=iteration, iteration=iteration)
    os.replace(staged / CHECKPOINT, run_dir / CHECKPOINT)


def test_an_unchanged_checkpoint_is_loaded_once_and_a_newer_one_replaces_it(tmp_path):
    run = write_tiny_run(tmp_path / "run", iteration=100)
    other = write_tiny_run(tmp_path / "other", iteration=7)
    cache = ModelCache(size=2)
    first = cache.get(run, "cpu")
    for _ in range(5):
        assert cache.get(run, "cpu") is first
    assert cache.loads == 1 and first.iteration == 100
    assert cache.get(other, "cpu").iteration == 7 and cache.loads == 2

    _save_newer(run, 200)
    newer = cache.get(run, "cpu")
    assert newer.iteration == 200 and cache.loads == 3
    assert cache.get(run, "cpu") is newer and cache.loads == 3
    assert cache.held() == 2  # the run's iteration-100 model is gone; the other run's stays
    assert cache.get(other, "cpu").iteration == 7 and cache.loads == 3


def test_a_load_reads_the_file_it_opened_not_one_renamed_over_it_meanwhile(tmp_path):
    run = write_tiny_run(tmp_path / "run", iteration=1)
    with open(run / CHECKPOINT, "rb") as opened:
        _save_newer(run, 2)
        assert load_checkpoint(run / CHECKPOINT, opened=opened)["iteration"] == 1
    assert load_checkpoint(run / CHECKPOINT)["iteration"] == 2
