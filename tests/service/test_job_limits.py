"""Bounded work per job and per client (issue #22, item 6) and a running job's files fenced (item 8): the queue
limit (429), ``DELETE /jobs/{id}``, the wall-clock cap a worker puts on every job, the cap of ``eval_at``
evaluations, cancelling in set-up and in the final evaluation, and a trainer that lost its lease writing
nothing more. Real parts throughout: SQLite job store, the filesystem broker, ``train()`` on a tiny room."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from synthetic_fixtures import make_micro_scene, micro_config

from app.core import jobstore, outputs
from app.core.db import session_scope
from app.core.models import JobRow, SceneRow
from app.core.settings import Settings
from app.main import create_app
from voxnerf.config import TrainConfig
from voxnerf.files import CHECKPOINT
from voxnerf.training.budget import Budget
from voxnerf.training.callbacks import ProgressEvaluation
from voxnerf.training.loop import LoopState
from voxnerf.training.records import ProgressEvent
from voxnerf.training.run import REPORT, LeaseLost, train
from worker.training import job_config

TOKEN = "limits-token"
SCENE = "c" * 32


@pytest.fixture
def api(tmp_path):
    settings = Settings(_env_file=None, data_dir=tmp_path / "data", device="cpu", api_token=TOKEN,
                        max_queued_jobs=2, max_queued_outputs=2, max_output_pixels=20_000, sweep_interval_s=3600)
    with TestClient(create_app(settings), headers={"Authorization": f"Bearer {TOKEN}"}) as client:
        jobstore.add_scene(settings, SCENE, "room", {"frames": 1}, 10)
        yield client, settings


def _submit(client: TestClient):
    return client.post(f"/scenes/{SCENE}/jobs", json={"max_iters": 5})


def _set_state(settings: Settings, job_id: str, state: str) -> None:
    with session_scope(settings) as session:
        session.get(JobRow, job_id).state = state


# ------------------------------------------------------------------------------------------------ per client


def test_queued_jobs_beyond_the_limit_are_answered_429(api):
    client, settings = api
    first, second = _submit(client), _submit(client)
    assert first.status_code == second.status_code == 202
    refused = _submit(client)
    assert refused.status_code == 429 and "limit is 2" in refused.json()["detail"]
    assert len(jobstore.JOBS.newest(settings)) == 2  # the refused job left no row
    _set_state(settings, first.json()["id"], "running")  # one started: room for one more
    assert _submit(client).status_code == 202


def _trained_job(client: TestClient, settings: Settings, **options) -> str:
    job_id = client.post(f"/scenes/{SCENE}/jobs", json={"max_iters": 5, **options}).json()["id"]
    _set_state(settings, job_id, "succeeded")
    return job_id


def _video(client: TestClient, job_id: str, **fields):
    return client.post(f"/jobs/{job_id}/videos", json={"path": "orbit", "frames": 4, **fields})


def test_queued_outputs_beyond_their_own_limit_are_answered_429(api):
    """Issue #42: ten video requests were all accepted with VOXNERF_MAX_QUEUED_JOBS=3 (outputs had no limit)."""
    client, settings = api
    job_id = _trained_job(client, settings)
    first, second = _video(client, job_id), client.post(f"/jobs/{job_id}/exports", json={"kind": "mesh"})
    assert first.status_code == second.status_code == 202, second.text
    refused = _video(client, job_id)
    assert refused.status_code == 429
    assert "limit is 2, VOXNERF_MAX_QUEUED_OUTPUTS" in refused.json()["detail"]
    assert len(outputs.OUTPUTS.newest(settings)) == 2  # the refused output left no row
    assert _submit(client).status_code == 202  # training jobs have their own limit
    outputs.OUTPUTS.request_cancel(settings, first.json()["id"])  # one gone from the queue: room for one more
    assert _video(client, job_id).status_code == 202


def test_a_video_beyond_the_cost_cap_is_refused_naming_the_limit(api):
    client, settings = api
    job_id = _trained_job(client, settings)
    assert _video(client, job_id, frames=100, width=16, height=12).status_code == 202  # 19 200 pixels in all
    refused = _video(client, job_id, frames=100, width=16, height=14)  # 22 400
    assert refused.status_code == 422
    detail = refused.json()["detail"]
    assert "22400 pixels" in detail and "limit of 20000" in detail and "VOXNERF_MAX_OUTPUT_PIXELS" in detail
    assert len(outputs.OUTPUTS.newest(settings)) == 1


def test_the_cost_of_a_video_without_a_size_is_counted_at_the_jobs_training_size(api):
    client, settings = api
    with session_scope(settings) as session:
        session.get(SceneRow, SCENE).summary = {"frames": 1, "image_size": [64, 48]}
    halved = _trained_job(client, settings, downscale=2)  # 32 x 24 = 768 pixels a frame
    assert _video(client, halved, frames=26).status_code == 202  # 19 968
    assert _video(client, halved, frames=27).status_code == 422  # 20 736
    full = _trained_job(client, settings)  # 64 x 48 = 3072 a frame
    assert _video(client, full, frames=7).status_code == 422  # 21 504


def _export(client: TestClient, job_id: str, **fields):
    return client.post(f"/jobs/{job_id}/exports", json={"kind": "pointcloud", **fields})


def test_an_export_beyond_the_cost_cap_is_refused_naming_the_limit(api):
    """An export renders five views per training camera (voxnerf.inference.export_plan), each at most 320 pixels
    a side: 64 x 48 here (3072 pixels), under the limit of 20 000 for one camera (5 views), over it for two."""
    client, settings = api
    with session_scope(settings) as session:
        session.get(SceneRow, SCENE).summary = {"frames": 3, "image_size": [64, 48], "splits": {"train": 2}}
    job_id = _trained_job(client, settings)
    refused = _export(client, job_id)  # 10 views: 30 720 pixels
    assert refused.status_code == 422
    assert refused.json()["detail"] == ("10 views of 64x48 are 30720 pixels, beyond the limit of 20000 per output "
                                        "(VOXNERF_MAX_OUTPUT_PIXELS): a lower max_views")
    assert _export(client, job_id, max_views=6).status_code == 202  # 18 432
    with session_scope(settings) as session:
        session.get(SceneRow, SCENE).summary = {"frames": 3, "image_size": [1280, 960], "splits": {"train": 1}}
    detail = _export(client, job_id, kind="mesh").json()["detail"]  # 5 views scaled to 320 x 240
    assert detail.startswith("5 views of 320x240 are 384000 pixels")


def test_the_cost_of_an_export_of_mixed_sizes_counts_every_view_at_the_largest_size(api):
    """Two training cameras of 32x24 and 64x48: 10 views counted at 64x48 (30 720 pixels, over the limit), not at
    the first training image's 32x24 (7 680)."""
    client, settings = api
    with session_scope(settings) as session:
        session.get(SceneRow, SCENE).summary = {"frames": 3, "image_size": [32, 24], "splits": {"train": 2},
                                                "image_sizes": {"32x24": 2, "64x48": 1}}
    job_id = _trained_job(client, settings)
    refused = _export(client, job_id)
    assert refused.status_code == 422
    assert refused.json()["detail"].startswith("10 views of up to 64x48 are 30720 pixels")
    assert _export(client, job_id, max_views=6).status_code == 202  # 18 432


# ------------------------------------------------------------------------------------------------ DELETE


def test_deleting_a_finished_job_removes_its_row_run_and_outputs(api):
    client, settings = api
    job_id = _submit(client).json()["id"]
    _set_state(settings, job_id, "succeeded")
    run_dir = settings.runs_dir / job_id
    (run_dir / "eval" / "test").mkdir(parents=True)
    (run_dir / CHECKPOINT).write_bytes(b"ckpt")
    output = outputs.create_output(settings, job_id, "mesh", {}, 4, False)
    outputs.OUTPUTS.fail(settings, output.id, "done with it")
    assert client.delete(f"/jobs/{job_id}").status_code == 204
    assert not run_dir.exists() and jobstore.JOBS.get(settings, job_id) is None
    assert outputs.OUTPUTS.get(settings, output.id) is None
    assert client.get(f"/jobs/{job_id}").status_code == 404


def test_deleting_an_unknown_job_is_404(api):
    client, _ = api
    assert client.delete(f"/jobs/{'d' * 32}").status_code == 404


@pytest.mark.parametrize("state", ["queued", "running"])
def test_deleting_an_active_job_is_409_and_keeps_everything(api, state):
    client, settings = api
    job_id = _submit(client).json()["id"]
    _set_state(settings, job_id, state)
    (settings.runs_dir / job_id).mkdir(parents=True)
    response = client.delete(f"/jobs/{job_id}")
    assert response.status_code == 409 and state in response.json()["detail"]
    assert (settings.runs_dir / job_id).is_dir() and jobstore.JOBS.get(settings, job_id) is not None


def test_deleting_a_job_whose_output_is_running_is_409(api):
    client, settings = api
    job_id = _submit(client).json()["id"]
    _set_state(settings, job_id, "succeeded")
    output = outputs.create_output(settings, job_id, "video", {}, 4, False)
    response = client.delete(f"/jobs/{job_id}")
    assert response.status_code == 409 and output.id in response.json()["detail"]


# ------------------------------------------------------------------------------------------------ caps


def test_every_job_trains_under_the_wall_clock_cap(tmp_path):
    settings = Settings(_env_file=None, data_dir=tmp_path, max_job_seconds=60.0, max_eval_at_seconds=5.0)
    assert job_config(settings, {"max_iters": 10}).run.max_seconds == 60.0  # a max_iters-only job included
    assert job_config(settings, {"max_seconds": 3600}).run.max_seconds == 60.0
    assert job_config(settings, {"max_seconds": 10}).run.max_seconds == 10.0
    assert job_config(settings, {"max_iters": 10}).evaluation.eval_at_max_seconds == 5.0


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_eval_at_evaluations_stop_once_their_time_cap_is_spent():
    clock = Clock()
    budget = Budget(None, clock=clock)
    budget.start_training()
    warnings: list[str] = []
    done: list[bool] = []

    def evaluate(_iteration: int, _loss: float, rays: int | None) -> tuple[float, float]:
        done.append(rays is None)  # a full evaluation
        clock.now += 4.0  # each full evaluation takes 4 s
        return 4.0, 1e-5

    cfg = TrainConfig(max_iters=1, eval_at=[1, 2, 3, 4], eval_at_max_seconds=6.0, eval_every_s=1e9)
    evaluation = ProgressEvaluation(evaluate, budget, cfg, 100, warnings=warnings)
    for t in (1.0, 2.0, 3.0, 4.0):
        clock.now = t + budget.paused  # training time t
        evaluation.before_step(LoopState(0))
    assert done == [True, True]  # 8 s spent after the second: the third and fourth are skipped
    assert warnings == ["eval_at: 2 full evaluation(s) from 3 s on skipped: the 6 s allowed for them were spent"]


# ------------------------------------------------------------------------------------------------ cancel, fence


@pytest.fixture(scope="module")
def tiny_room(tmp_path_factory) -> Path:
    return make_micro_scene(tmp_path_factory, "limits")


_config = micro_config


def test_a_cancel_during_set_up_stops_before_the_next_stage(tiny_room, tmp_path):
    stages: list[str] = []
    report = train(tiny_room, tmp_path, _config(), on_progress=lambda e: stages.append(e.stage),
                   should_stop=lambda: "prior" in stages, progress_bar=False)
    assert report.status == "cancelled" and report.iteration == 0
    assert [s.name for s in report.stages] == ["load_scene", "corrections", "weight_decay", "prior", "train"]
    assert report.stages[-1].why == "cancelled during set-up"
    assert not (tmp_path / CHECKPOINT).exists() and (tmp_path / REPORT).is_file()


def test_a_cancel_during_the_final_evaluation_stops_it(tiny_room, tmp_path):
    stages: list[str] = []
    report = train(tiny_room, tmp_path, _config(), on_progress=lambda e: stages.append(e.stage),
                   should_stop=lambda: "final_eval" in stages, progress_bar=False)
    assert report.status == "cancelled" and report.iteration == 3 and report.metrics is None
    final = report.stages[-1]
    assert final.name == "final_eval" and not final.ran and final.why == "run cancelled during the evaluation"
    assert (tmp_path / CHECKPOINT).is_file()  # the trained model is kept, as for any cancel
    assert not (tmp_path / "eval").exists() and not list(tmp_path.glob(".eval-*"))  # no half evaluation


def test_a_trainer_that_lost_its_lease_writes_nothing_more(tiny_room, tmp_path):
    settings = Settings(_env_file=None, data_dir=tmp_path / "data", stale_after_s=5.0)
    jobstore.add_scene(settings, SCENE, "room", {"frames": 1}, 10)
    job = jobstore.create_job(settings, SCENE, {"max_iters": 3})
    first = jobstore.JOBS.claim(settings, job.id, "old:1")
    run_dir = tmp_path / "run"

    def taken_over_at_training(event: ProgressEvent) -> None:
        if event.stage == "first_hit_cache":  # set-up done: the lease expires and another worker claims the job
            with session_scope(settings) as session:
                session.get(JobRow, job.id).heartbeat_at = time.time() - 60
            assert jobstore.JOBS.claim(settings, job.id, "new:2").attempt == 2

    with pytest.raises(LeaseLost, match="another attempt owns this run"):
        train(tiny_room, run_dir, _config(), on_progress=taken_over_at_training, progress_bar=False,
              may_write=lambda: jobstore.JOBS.still_owned(settings, job.id, first.attempt))
    written = sorted(p.relative_to(run_dir).as_posix() for p in run_dir.rglob("*"))
    assert written == ["prior_tsdf.ply"] or written == []  # only what it wrote while it owned the job
    report = train(tiny_room, run_dir, _config(), progress_bar=False,
                   may_write=lambda: jobstore.JOBS.still_owned(settings, job.id, 2))  # the new owner writes
    assert report.status == "succeeded" and (run_dir / CHECKPOINT).is_file() and (run_dir / "eval").is_dir()
