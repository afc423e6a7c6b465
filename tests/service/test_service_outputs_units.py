"""Output jobs piece by piece, without workers: the store's claims, fencing, cancel and stale-output recovery
(app/core/outputs.py, app/core/dispatch.py), the rules of which jobs outputs and renders are made from, video
request checks, and the worker's key cameras (worker/outputs.py)."""

from __future__ import annotations

import time

import numpy as np
import pytest
from sqlalchemy import update

from app.core import jobstore, outputs
from app.core.db import session_scope
from app.core.dispatch import requeue_stale
from app.core.models import JobRow, OutputRow
from app.core.settings import Settings
from voxnerf.cameras.paths import CameraPathError
from voxnerf.files import CHECKPOINT


@pytest.fixture
def settings(tmp_path) -> Settings:
    settings = Settings(data_dir=tmp_path / "data", stale_after_s=5)
    settings.make_dirs()
    return settings


class Publisher:
    """Records what would be published (a real Celery client needs a broker)."""

    def __init__(self) -> None:
        self.sent: list[tuple[str, list]] = []

    def send_task(self, name: str, args: list, **_) -> None:
        self.sent.append((name, args))


def _output(settings: Settings, job_id: str = "a" * 32) -> OutputRow:
    return outputs.create_output(settings, job_id, "video", {"path": "orbit", "frames": 4}, 4, False)


def test_a_claim_fences_the_writes_of_the_worker_before(settings):
    row = _output(settings)
    first = outputs.OUTPUTS.claim(settings, row.id, "host:1")
    assert first.state == "running" and first.attempt == 1
    assert outputs.OUTPUTS.claim(settings, row.id, "host:2") is None  # fresh lease: not stale
    assert outputs.OUTPUTS.record_progress(settings, row.id, 1, 2, 4, 1.5)
    assert outputs.OUTPUTS.get(settings, row.id).progress == 0.5
    with session_scope(settings) as session:  # the lease expires
        session.execute(update(OutputRow).where(OutputRow.id == row.id).values(heartbeat_at=time.time() - 60))
    second = outputs.OUTPUTS.claim(settings, row.id, "host:3")
    assert second.attempt == 2 and second.requeues == 1 and second.done == 0
    assert not outputs.OUTPUTS.record_progress(settings, row.id, 1, 3, 4, None)  # the old worker writes nothing
    assert not outputs.OUTPUTS.finish(settings, row.id, 1, "succeeded", {})
    assert outputs.OUTPUTS.renew_lease(settings, row.id, 1).owned is False
    assert outputs.OUTPUTS.finish(settings, row.id, 2, "succeeded", {"file_name": "video.mp4", "summary": {}})
    done = outputs.OUTPUTS.get(settings, row.id)
    assert done.state == "succeeded" and done.progress == 1.0 and done.eta_s is None


def test_cancel_a_queued_output_at_once_and_a_running_one_through_its_lease(settings):
    queued = _output(settings)
    assert outputs.OUTPUTS.request_cancel(settings, queued.id).state == "cancelled"
    assert outputs.OUTPUTS.claim(settings, queued.id, "host:1") is None
    running = _output(settings)
    claimed = outputs.OUTPUTS.claim(settings, running.id, "host:1")
    row = outputs.OUTPUTS.request_cancel(settings, running.id)
    assert row.state == "running" and row.cancel_requested
    assert outputs.OUTPUTS.renew_lease(settings, running.id, claimed.attempt).cancel_requested


def test_stale_outputs_are_requeued_then_failed_after_max_requeues(settings):
    row = _output(settings)
    publisher = Publisher()
    for attempt in range(settings.max_worker_deaths):
        claimed = outputs.OUTPUTS.claim(settings, row.id, "host:1")
        assert claimed is not None and claimed.attempt == attempt + 1
        with session_scope(settings) as session:
            session.execute(update(OutputRow).where(OutputRow.id == row.id).values(heartbeat_at=0.0))
        requeued = requeue_stale(settings, publisher, outputs.OUTPUTS)
        if attempt < settings.max_worker_deaths - 1:
            assert requeued == [row.id] and outputs.OUTPUTS.get(settings, row.id).state == "queued"
    final = outputs.OUTPUTS.get(settings, row.id)
    assert final.state == "failed" and "died 3 times" in final.error
    assert len(publisher.sent) == settings.max_worker_deaths - 1


def _job(settings: Settings, state: str):
    scene_id = jobstore.new_id()
    jobstore.add_scene(settings, scene_id, "room", {}, 1)
    job = jobstore.create_job(settings, scene_id, {"max_iters": 1})
    with session_scope(settings) as session:
        session.execute(update(JobRow).where(JobRow.id == job.id).values(state=state))
    return jobstore.JOBS.get(settings, job.id)


@pytest.mark.parametrize("state", ["queued", "running", "failed", "cancelled"])
def test_only_a_succeeded_or_a_checkpointed_cancelled_job_is_rendered_from(settings, state):
    job = _job(settings, state)
    with pytest.raises(outputs.NotRenderable, match=state):
        outputs.trained_source(settings, job)
    if state == "cancelled":
        (settings.runs_dir / job.id).mkdir(parents=True)
        (settings.runs_dir / job.id / CHECKPOINT).write_bytes(b"x")
        assert outputs.trained_source(settings, job) is True


def test_a_succeeded_job_is_not_partial(settings):
    assert outputs.trained_source(settings, _job(settings, "succeeded")) is False


@pytest.mark.parametrize(("state", "before_a_checkpoint"), [
    ("queued", "is queued: it can be rendered once training has written its first checkpoint"),
    ("running", "has no checkpoint yet: training writes its first about 60 s after its set-up"),
    ("failed", "is failed without a checkpoint"),
    ("cancelled", "is cancelled without a checkpoint"),
])
def test_renders_take_a_running_or_ended_jobs_latest_checkpoint_as_partial(settings, state, before_a_checkpoint):
    """POST /render's rule (the viewer's): unlike outputs, a running job renders from its latest checkpoint and a
    failed one from its last good one, once the run has one; a queued job never."""
    job = _job(settings, state)
    with pytest.raises(outputs.NotRenderable, match=before_a_checkpoint):
        outputs.render_source(settings, job)
    (settings.runs_dir / job.id).mkdir(parents=True)
    (settings.runs_dir / job.id / CHECKPOINT).write_bytes(b"x")
    if state == "queued":
        with pytest.raises(outputs.NotRenderable, match="is queued"):
            outputs.render_source(settings, job)
    else:
        assert outputs.render_source(settings, job) is True
    assert outputs.render_source(settings, _job(settings, "succeeded")) is False


def _camera_path(**changes) -> dict:
    entry = {"camera_to_world": np.eye(4).reshape(-1).tolist(), "fov": 50.0, "aspect": 1.0}
    return {"render_width": 32, "render_height": 24, "fps": 10, "camera_path": [entry, entry], **changes}


def test_a_camera_path_is_stored_in_scene_units_with_its_frame_count(settings):
    params, frames = outputs.video_params(settings, {"camera_path": _camera_path()})
    assert frames == 2 and params["frames"] == 2 and (params["width"], params["height"]) == (32, 24)
    assert len(params["camera_path"]["camera_path"]) == 2


@pytest.mark.parametrize(
    ("request_body", "key"),
    [
        ({"camera_path": _camera_path(render_width=31)}, "render_width"),
        ({"camera_path": _camera_path(camera_path=[])}, "camera_path"),
        ({"path": "orbit", "frames": 0}, "frames"),
        ({"path": "orbit", "frames": 3601}, "frames"),
        ({"path": "orbit", "frames": 2, "width": 4096, "height": 8192}, "width, height"),
        ({"path": "orbit", "frames": 2, "width": 33, "height": 24}, "width, height"),
    ],
)
def test_bad_video_requests_name_the_key(settings, request_body, key):
    with pytest.raises(CameraPathError) as err:
        outputs.video_params(settings, request_body)
    assert err.value.key.startswith(key) or key in str(err.value)


def test_key_cameras_thin_evenly_and_keep_the_ends():
    from voxnerf.cameras.paths import FRAMES_PER_KEY, key_cameras

    poses = np.tile(np.eye(4), (20, 1, 1))
    poses[:, 0, 3] = np.arange(20)
    assert key_cameras(poses, 6)[:, 0, 3].tolist() == [0, 19]
    chosen = key_cameras(poses, 10 * FRAMES_PER_KEY)[:, 0, 3]
    assert len(chosen) == 10 and chosen[0] == 0 and chosen[-1] == 19
    assert len(key_cameras(poses, 10_000)) == 20
