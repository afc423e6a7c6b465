"""``train()`` (voxnerf/training/run.py) on a tiny room: the typed report and events, report.json, resuming;
and the throughput figures and the ``voxnerf.trainer`` facade."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from synthetic_fixtures import make_micro_scene, micro_config

import voxnerf.trainer
from voxnerf.config import TrainConfig
from voxnerf.files import CHECKPOINT
from voxnerf.training.checkpoint import load_checkpoint
from voxnerf.training.records import ProgressEvent, TrainReport
from voxnerf.training.run import REPORT, throughput, train

STAGES = ["load_scene", "corrections", "weight_decay", "prior", "focal", "hash_kernel", "octree", "pseudo_depth",
          "depth_target", "octree_carving", "first_hit_cache", "window_check", "colour_prior", "prior_rays", "compile",
          "train", "final_eval"]


@pytest.fixture(scope="module")
def tiny_room(tmp_path_factory) -> Path:
    return make_micro_scene(tmp_path_factory, "training")


_config = micro_config


def test_train_returns_the_report_it_writes_and_sends_typed_events(tiny_room, tmp_path):
    events: list[ProgressEvent] = []
    report = train(tiny_room, tmp_path, _config(), on_progress=events.append, progress_bar=False)
    assert isinstance(report, TrainReport) and report.status == "succeeded" and report.iteration == 3
    assert [s.name for s in report.stages] == STAGES
    assert json.loads((tmp_path / REPORT).read_text()) == json.loads(json.dumps(report.to_json_dict()))
    assert all(isinstance(e, ProgressEvent) for e in events)
    set_up = STAGES[: STAGES.index("compile") + 1]
    assert [e.stage for e in events if e.stage != "train"] == [*set_up, "final_eval", "final_eval", "done"]
    assert events[-1].progress == 1.0 and events[-1].iteration == 3 and len(events[-1].history) == 1
    assert report.runtime["octree_misses"] == "gather"  # the voxnerf sampler's "auto" on a CPU


def test_a_run_with_masked_octree_misses_trains_and_says_so(tiny_room, tmp_path):
    """The sync-free fallback a GPU takes by default also trains on a CPU when asked (its loss finite at every step:
    the divergence guard would have failed the run), and report.json names it."""
    report = train(tiny_room, tmp_path, _config(octree_misses="mask", final_eval=False), progress_bar=False)
    assert report.status == "succeeded" and report.iteration == 3 and report.runtime["octree_misses"] == "mask"


def test_a_run_drawing_half_its_rays_by_the_error_map_trains(tiny_room, tmp_path):
    """Its loss finite at every step (the divergence guard would have failed the run), report.json names it."""
    report = train(tiny_room, tmp_path, _config(error_map=0.5, final_eval=False), progress_bar=False)
    assert report.status == "succeeded" and report.iteration == 3 and report.config["error_map"] == 0.5


def test_a_resumed_run_continues_its_iterations_and_history(tiny_room, tmp_path):
    train(tiny_room, tmp_path, _config(final_eval=False, eval_every_s=1e-6), progress_bar=False)
    report = train(tiny_room, tmp_path, _config(max_iters=5, final_eval=False, eval_every_s=1e-6),
                   progress_bar=False)
    assert report.resumed_from_iteration == 3 and report.iteration == 5
    assert [h.iteration for h in report.history] == [0, 1, 2, 3, 4]


def test_throughput_counts_patch_rays_over_the_training_seconds():
    cfg = TrainConfig(max_iters=10, rays_per_batch=100, n_importance=6, n_rest=2)
    got = throughput(cfg, 10, 10.0, True, 28)
    assert got == {"rays_per_step": 128, "rays_per_s": 128.0, "samples_per_s": 128.0 * cfg.sampling.samples_per_ray,
                   "seconds_excluding_compile": 10.0}
    assert throughput(cfg, 10, 10.0, False, 28)["rays_per_step"] == 100


def test_throughput_is_the_loops_own_and_a_resumed_run_counts_its_own_steps(tiny_room, tmp_path):
    """Set-up and compilation are left out of the rate: the loop's steps over this command's training seconds."""
    first = train(tiny_room, tmp_path, _config(final_eval=False), progress_bar=False)
    assert first.throughput["seconds_excluding_compile"] == pytest.approx(first.budget["seconds"]["training"],
                                                                          abs=1e-3)
    assert first.throughput["seconds_excluding_compile"] == pytest.approx(first.train_seconds, abs=1e-3)
    again = train(tiny_room, tmp_path, _config(max_iters=5, final_eval=False), progress_bar=False)
    seconds = again.throughput["seconds_excluding_compile"]
    assert again.throughput["rays_per_s"] == pytest.approx(again.throughput["rays_per_step"] * 2 / seconds)


def test_the_trainer_facade_keeps_the_old_names():
    for name in ("train", "Budget", "eval_views_of", "REPORT", "TrainingDiverged", "TrainingPixels"):
        assert hasattr(voxnerf.trainer, name), name
    assert voxnerf.trainer.train is train


def test_every_event_names_the_checkpoint_the_run_directory_holds_then(tiny_room, tmp_path):
    """``checkpoint_iteration`` (what the service's viewer renders from while a job trains): None until the first
    save, then always the iteration of the complete checkpoint on disk; a resumed run starts from its checkpoint's."""
    seen: list[tuple[str, int | None, int | None]] = []

    def check(event: ProgressEvent) -> None:
        path = tmp_path / CHECKPOINT
        on_disk = int(load_checkpoint(path)["iteration"]) if path.is_file() else None
        seen.append((event.stage, event.checkpoint_iteration, on_disk))

    train(tiny_room, tmp_path, _config(final_eval=False, checkpoint_every_s=1e-6), on_progress=check,
          progress_bar=False)
    assert all(named == on_disk for _, named, on_disk in seen), seen
    assert seen[0] == ("load_scene", None, None) and seen[-1] == ("done", 3, 3)
    seen.clear()
    train(tiny_room, tmp_path, _config(max_iters=5, final_eval=False), on_progress=check, progress_bar=False)
    assert seen[0] == ("load_scene", 3, 3) and seen[-1] == ("done", 5, 5)
    assert all(named == on_disk for _, named, on_disk in seen), seen
