"""The render workers' model cache (worker/model_cache.py) while a job trains: an unchanged checkpoint is never
loaded twice, a newer one (renamed over the old, as the trainer saves) is loaded at the next request and replaces
the run's older model, and a load reads the file it identified even when a newer one lands meanwhile; with an
object store, a render machine follows the checkpoints the trainer uploads."""

from __future__ import annotations

import os
from pathlib import Path

from tiny_run import write_tiny_run

from app.core import storage
from app.core.settings import Settings
from voxnerf.files import CHECKPOINT
from voxnerf.training.checkpoint import load_checkpoint
from worker.model_cache import ModelCache, job_model


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


def test_with_an_object_store_a_render_machine_fetches_a_newer_checkpoint_the_job_row_names(tmp_path):
    """A render worker on another machine (its own cache) renders the job's latest uploaded checkpoint: it fetches
    the run when its cached checkpoint is older than the row's ``checkpoint_iteration`` and the store holds another
    upload, and only then; the training machine itself, always ahead of the store, never fetches."""
    store_url = f"file://{tmp_path}/store"
    options = {"auto_mkdir": True}  # a local directory as the store: its upload makes its folders
    trainer = Settings(_env_file=None, data_dir=tmp_path / "trainer", storage_url=store_url, storage_options=options)
    renderer = Settings(_env_file=None, data_dir=tmp_path / "renderer", storage_url=store_url,
                        storage_options=options)
    job_id = "a" * 32
    run = trainer.runs_dir / job_id
    store = storage.open_store(trainer)

    def upload(iteration: int) -> None:
        write_tiny_run(run, iteration=iteration) if not run.exists() else _save_newer(run, iteration)
        storage.put_dir(store, run, f"{storage.RUNS}/{job_id}")

    upload(100)
    assert job_model(renderer, job_id, 100).iteration == 100
    upload(200)
    assert job_model(renderer, job_id, None).iteration == 100  # a row from before the column: the cache as it is
    generation = storage.local_generation(renderer.runs_dir / job_id)
    assert job_model(renderer, job_id, 200).iteration == 200
    assert storage.local_generation(renderer.runs_dir / job_id) != generation
    _save_newer(run, 300)  # saved, not uploaded yet: the row says 300, the store holds 200
    assert job_model(renderer, job_id, 300).iteration == 200
    assert job_model(trainer, job_id, 300).iteration == 300
