"""The workers' tasks (worker/tasks.py) and their work (worker/training.py, worker/rendering.py) without Celery or
training: the ProgressWriter fed with the engine's ProgressEvent objects, the train task around a stand-in
``train()`` returning a TrainReport, and the render task's outcome around a stand-in model."""

from __future__ import annotations

from types import SimpleNamespace

import imageio.v3 as iio
import numpy as np
import pytest
from worker_fixtures import SCENE, claimed_job, store_with_scene

from app.core import jobstore
from app.core.render_results import receive_outcome
from app.core.settings import Settings
from voxnerf.cameras.rules import Intrinsics
from voxnerf.errors import SceneError
from voxnerf.training.records import EvalRecord, ProgressEvent, StageRecord, TrainReport
from worker import rendering, tasks, training


@pytest.fixture
def settings(tmp_path, monkeypatch) -> Settings:
    s = store_with_scene(tmp_path, progress_interval_s=60.0, heartbeat_s=0.05, max_render_pixels=100)
    for module in (tasks, rendering):
        monkeypatch.setattr(module, "get_settings", lambda: s)
    return s


def test_progress_writer_writes_each_stage_then_one_event_per_interval(settings):
    job = claimed_job(settings)
    writer = training.ProgressWriter(settings, job.id, job.attempt)
    writer(ProgressEvent(stage="load_scene"))
    assert jobstore.JOBS.get(settings, job.id).stage == "load_scene"
    writer(ProgressEvent(stage="train", iteration=10, progress=0.2, loss=0.5, eta_s=40.0))
    writer(ProgressEvent(stage="train", iteration=20, progress=0.4, loss=0.4))  # within the interval: skipped
    row = jobstore.JOBS.get(settings, job.id)
    assert (row.stage, row.iteration, row.progress, row.loss, row.eta_s) == ("train", 10, 0.2, 0.5, 40.0)
    history = [EvalRecord(elapsed_s=5.0, iteration=20, psnr={"test": 19.0})]
    writer(ProgressEvent(stage="final_eval", iteration=20, progress=0.4, history=history))
    assert jobstore.JOBS.get(settings, job.id).history == [{"elapsed_s": 5.0, "iteration": 20, "psnr": {"test": 19.0}}]


def test_progress_writer_never_goes_back_and_leaves_done_to_the_task(settings):
    job = claimed_job(settings)
    writer = training.ProgressWriter(settings, job.id, job.attempt)
    writer(ProgressEvent(stage="train", iteration=30, progress=0.6))
    writer(ProgressEvent(stage="checkpoint", iteration=0, progress=0.0))  # stage events carry iteration 0
    row = jobstore.JOBS.get(settings, job.id)
    assert (row.stage, row.iteration, row.progress) == ("checkpoint", 30, 0.6)
    writer(ProgressEvent(stage="done", iteration=50, progress=1.0))
    assert jobstore.JOBS.get(settings, job.id).stage == "checkpoint"
    assert (writer.iteration, writer.progress) == (30, 0.6)


def test_a_fenced_off_writer_writes_nothing(settings):
    job = claimed_job(settings)
    stale = training.ProgressWriter(settings, job.id, job.attempt - 1)
    stale(ProgressEvent(stage="train", iteration=7, progress=0.3))
    assert jobstore.JOBS.get(settings, job.id).iteration == 0


def _fake_train(status: str, seen: list):
    def train(scene_dir, run_dir, config, on_progress, should_stop, resume, progress_bar, may_write):
        seen.append((scene_dir, run_dir, config, resume))
        on_progress(ProgressEvent(stage="train", iteration=25, progress=0.5, loss=0.2))
        return TrainReport(
            status=status,
            config=config.model_dump(),
            device="cpu",
            iteration=25 if status == "cancelled" else 50,
            train_seconds=3.0,
            history=[EvalRecord(elapsed_s=3.0, iteration=50, psnr={"test": 22.0}, final=True)],
            stages=[StageRecord(name="train", ran=True, why=f"{status}", seconds=3.0)],
            metrics={"test": {"psnr": 22.0}} if status == "succeeded" else None,
        )

    return train


def test_train_task_records_the_report(settings, monkeypatch):
    seen: list = []
    monkeypatch.setattr(training, "train", _fake_train("succeeded", seen))
    job = jobstore.create_job(settings, SCENE, {"max_iters": 50, "compile": False})
    tasks.train_job(job.id)
    ((scene_dir, run_dir, config, resume),) = seen
    assert scene_dir == settings.scenes_dir / SCENE and run_dir == settings.runs_dir / job.id and resume
    run = config.run
    assert (run.max_iters, run.device, run.checkpoint_every_s) == (50, "auto", settings.checkpoint_every_s)
    row = jobstore.JOBS.get(settings, job.id)
    assert (row.state, row.stage, row.progress, row.iteration, row.elapsed_s) == ("succeeded", "done", 1.0, 50, 3.0)
    assert row.metrics == {"test": {"psnr": 22.0}} and row.history[0]["final"] and row.loss == 0.2


def test_train_task_cancelled_keeps_progress(settings, monkeypatch):
    monkeypatch.setattr(training, "train", _fake_train("cancelled", []))
    job = jobstore.create_job(settings, SCENE, {"max_iters": 50})
    tasks.train_job(job.id)
    row = jobstore.JOBS.get(settings, job.id)
    assert (row.state, row.progress, row.iteration) == ("cancelled", 0.5, 25)


def test_train_task_marks_engine_errors_failed(settings, monkeypatch):
    def broken(*_args, **_kwargs):
        raise SceneError("transforms.json", "frames: empty")

    monkeypatch.setattr(training, "train", broken)
    job = jobstore.create_job(settings, SCENE, {"max_iters": 50})
    tasks.train_job(job.id)
    row = jobstore.JOBS.get(settings, job.id)
    assert row.state == "failed" and row.stage == "failed" and "frames: empty" in row.error
    tasks.train_job(job.id)  # a redelivered message for a finished job claims nothing
    assert jobstore.JOBS.get(settings, job.id).attempt == 1


rendered_with: list[bool | None] = []  # the antialias each render of the fake model was asked for


def _fake_model(monkeypatch, settings: Settings) -> None:
    trained = SimpleNamespace(default_intrinsics=Intrinsics(8.0, 8.0, 4.0, 3.0, 8, 6), depth_unit_scale=0.001,
                              model=SimpleNamespace(device=SimpleNamespace(type="cpu")), iteration=42)
    monkeypatch.setattr(rendering, "job_model", lambda settings, job_id, checkpoint_iteration: trained)

    def render(model, c2w, intrinsics, outputs, path, should_stop, antialias):
        assert path == settings.render_path
        rendered_with.append(antialias)
        shape = (intrinsics.height, intrinsics.width)
        return {"rgb": np.full((*shape, 3), 0.5, np.float32), "depth": np.ones(shape, np.float32),
                "opacity": np.ones(shape, np.float32)}

    monkeypatch.setattr(rendering, "render", render)


def test_render_task_answers_the_image_or_a_4xx(settings, monkeypatch):
    _fake_model(monkeypatch, settings)
    request = {"job_id": "b" * 32, "transform_matrix": np.eye(4).tolist()}
    tasks.render_pose("r1", "b" * 32, request)
    outcome = receive_outcome(settings, "r1", timeout_s=5)
    assert outcome.status == 200 and outcome.media_type == "image/png" and outcome.iteration == 42
    assert iio.imread(outcome.data).shape == (6, 8, 3)
    tasks.render_pose("r2", "b" * 32, {**request, "width": 20, "height": 10})  # 200 pixels > 100
    outcome = receive_outcome(settings, "r2", timeout_s=5)
    assert outcome.status == 422 and "exceeds the limit of 100 pixels" in outcome.detail
    tasks.render_pose("r3", "b" * 32, {**request, "transform_matrix": [[1, 2]]})
    outcome = receive_outcome(settings, "r3", timeout_s=5)
    assert outcome.status == 500 and "render failed" in outcome.detail
    rendered_with.clear()
    tasks.render_pose("r4", "b" * 32, {**request, "antialias": False})  # the request's choice reaches the engine
    assert receive_outcome(settings, "r4", timeout_s=5).status == 200 and rendered_with == [False]
