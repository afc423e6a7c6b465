"""The small things of issue #22 (item 8): credentials masked in log lines and messages, error details without
server paths, ``write_atomic`` fsyncing its directory, leftovers cleaned at start-up, evaluation renders of
frames with the same stem kept apart, and dependency floors past known CVE fixes."""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
import stat
import subprocess
import sys
import time
from importlib import metadata
from pathlib import Path

import pytest
import tomllib
from fastapi.testclient import TestClient
from packaging.requirements import Requirement
from packaging.version import Version
from service_fixtures import free_port, stop_process, wait_for
from tiny_run import write_tiny_run

from app.core import jobstore, storage
from app.core import outputs as output_store
from app.core.cleanup import clean_leftovers
from app.core.lease import worker_identity
from app.core.redact import install_log_masking, mask_url, public_error
from app.core.render_results import receive_outcome
from app.core.settings import Settings
from app.main import create_app
from voxnerf.data.image_io import write_atomic
from voxnerf.data.scene import load_scene
from voxnerf.errors import SceneError
from voxnerf.files import CHECKPOINT
from voxnerf.inference.evaluation import evaluate_views, view_names
from voxnerf.inference.render import load_model
from voxnerf.synthetic import RoomSpec, make_room_scene
from voxnerf.training.eval_passes import eval_views_of
from worker import outputs as output_tasks
from worker import rendering, tasks, training

ROOT = Path(__file__).resolve().parents[1]
PASSWORD = "hunter2-s3cr3t"
SCENE = "c" * 32

# ------------------------------------------------------------------------------------------------ credentials

MASKED = [
    (f"redis://user:{PASSWORD}@10.0.0.5:6379/0", "redis://user:***@10.0.0.5:6379/0"),
    (f"redis://:{PASSWORD}@redis:6379/0", "redis://:***@redis:6379/0"),
    (f"rediss://{PASSWORD}@redis:6380", "rediss://***@redis:6380"),
    (f"postgresql://voxnerf:{PASSWORD}@db/voxnerf", "postgresql://voxnerf:***@db/voxnerf"),
    (f"redis://u:p@ss{PASSWORD}@h:1/0", "redis://u:***@h:1/0"),  # an '@' inside the password
    (f"s3://bucket/prefix?secret_key={PASSWORD}&region=eu", "s3://bucket/prefix?secret_key=***&region=eu"),
    (f"https://h/x?X-Amz-Signature={PASSWORD}", "https://h/x?X-Amz-Signature=***"),
    (f"cannot connect to redis://user:{PASSWORD}@h:1/0: refused", "cannot connect to redis://user:***@h:1/0: refused"),
    ("redis://127.0.0.1:6379/0", "redis://127.0.0.1:6379/0"),
    ("s3://bucket/prefix", "s3://bucket/prefix"),
    ("mail a@b.c about http://host/a@b", "mail a@b.c about http://host/a@b"),
]


@pytest.mark.parametrize(("url", "expected"), MASKED)
def test_mask_url_hides_passwords_tokens_and_secret_query_values(url, expected):
    assert mask_url(url) == expected
    assert mask_url(None) is None


@pytest.fixture
def masked_logging():
    """:func:`install_log_masking` for one test; the process's record factory restored afterwards."""
    before = logging.getLogRecordFactory()
    install_log_masking()
    install_log_masking()  # idempotent: one wrapper
    yield
    logging.setLogRecordFactory(before)


def test_log_records_are_masked_in_message_arguments_and_traceback(masked_logging, caplog):
    log = logging.getLogger("voxnerf.test.masking")
    url = f"redis://user:{PASSWORD}@broker:6379/0"
    with caplog.at_level(logging.INFO, logger="voxnerf.test.masking"):
        log.info("broker %s", url)
        log.info(f"storage s3://k:{PASSWORD}@bucket/p")
        log.warning("job failed: %s (%d tries)", ConnectionError(f"cannot reach {url}"), 3)
        try:
            raise OSError(f"Error 111 connecting to {url}")
        except OSError:
            log.exception("sweep failed")
    text = caplog.text
    assert PASSWORD not in text, text
    assert "broker redis://user:***@broker:6379/0" in text and "(3 tries)" in text
    assert "OSError: Error 111 connecting to redis://user:***@broker:6379/0" in text


def test_voxnerf_serve_logs_the_broker_url_masked(tmp_path):
    """A real ``python -m app.serve --api-only`` (no torch, no workers) with a password in the broker URL."""
    env = {**os.environ, "VOXNERF_DATA_DIR": str(tmp_path / "data"), "PYTHONUNBUFFERED": "1",
           "VOXNERF_BROKER_URL": f"redis://user:{PASSWORD}@127.0.0.1:1/0", "VOXNERF_SWEEP_INTERVAL_S": "0.2"}
    log_path = tmp_path / "serve.log"
    with log_path.open("wb") as out:
        proc = subprocess.Popen([sys.executable, "-m", "app.serve", "--api-only", "--port", str(free_port())],
                                cwd=ROOT, env=env, stdout=out, stderr=subprocess.STDOUT)
    try:
        wait_for(lambda: "Application startup complete" in log_path.read_text(), 60, "the API's start-up")
    finally:
        stop_process(proc)
    text = log_path.read_text()
    assert "broker redis://user:***@127.0.0.1:1/0" in text, text
    assert PASSWORD not in text, text


def test_a_storage_settings_error_names_the_url_masked(tmp_path):
    settings = Settings(data_dir=tmp_path, storage_url=f"memory://user:{PASSWORD}@bucket/p", storage_key="k")
    with pytest.raises(ValueError, match=r"memory://user:\*\*\*@bucket/p") as info:
        storage.check_store(settings)
    assert PASSWORD not in str(info.value)


# ------------------------------------------------------------------------------------------------ paths


@pytest.fixture
def settings(tmp_path, monkeypatch) -> Settings:
    s = Settings(data_dir=tmp_path / "data", progress_interval_s=60.0, heartbeat_s=0.05)
    s.make_dirs()
    (s.scenes_dir / SCENE).mkdir()
    jobstore.add_scene(s, SCENE, "room", {"frames": 1}, 10)
    for module in (tasks, rendering):
        monkeypatch.setattr(module, "get_settings", lambda: s)
    return s


def test_public_error_writes_data_dir_paths_relative(tmp_path):
    settings = Settings(data_dir=tmp_path / "data")
    root = str(settings.data_dir)
    text = f"{root}/runs/j/checkpoint.pt: unreadable; {root} full; {root}2/x stays; redis://u:{PASSWORD}@h"
    assert public_error(text, settings) == "runs/j/checkpoint.pt: unreadable; <data_dir> full; " \
                                           f"{root}2/x stays; redis://u:***@h"


def test_a_failed_training_job_error_carries_no_server_path(settings, monkeypatch):
    def broken(*_args, **_kwargs):
        raise SceneError(settings.scenes_dir / SCENE / "transforms.json", "empty", key="frames")

    monkeypatch.setattr(training, "train", broken)
    job = jobstore.create_job(settings, SCENE, {"max_iters": 5})
    tasks.train_job(job.id)
    row = jobstore.JOBS.get(settings, job.id)
    assert row.state == "failed" and row.error == f"SceneError: scenes/{SCENE}/transforms.json: frames: empty"


def _job_with_garbage_checkpoint(settings: Settings) -> str:
    job = jobstore.create_job(settings, SCENE, {"max_iters": 5})
    run = settings.runs_dir / job.id
    run.mkdir(parents=True)
    (run / CHECKPOINT).write_bytes(b"garbage")
    return job.id


def test_a_render_refusal_detail_carries_no_server_path(settings):
    job_id = _job_with_garbage_checkpoint(settings)
    tasks.render_pose("r1", job_id, {"job_id": job_id, "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0],
                                                                            [0, 0, 1, 3], [0, 0, 0, 1]]})
    outcome = receive_outcome(settings, "r1", timeout_s=5)
    assert outcome.status == 409 and str(settings.data_dir) not in outcome.detail, outcome.detail
    assert f"runs/{job_id}/{CHECKPOINT}: unreadable checkpoint" in outcome.detail


def test_a_failed_output_error_carries_no_server_path(settings):
    job_id = _job_with_garbage_checkpoint(settings)
    row = output_store.create_output(settings, job_id, "video", {}, 2, False)
    row = output_store.OUTPUTS.claim(settings, row.id, worker_identity())
    values = output_tasks.produce(settings, row, lease=None)
    assert values["state"] == "failed" and str(settings.data_dir) not in values["error"], values
    assert values["error"].startswith(f"RunError: runs/{job_id}/{CHECKPOINT}: unreadable checkpoint")


# ------------------------------------------------------------------------------------------------ fsync


def test_write_atomic_fsyncs_the_file_then_its_directory(tmp_path, monkeypatch):
    synced: list[str] = []
    real_fsync = os.fsync

    def recording_fsync(fd: int) -> None:
        synced.append("dir" if stat.S_ISDIR(os.fstat(fd).st_mode) else "file")
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", recording_fsync)
    write_atomic(tmp_path / "a.bin", b"payload")
    assert synced == ["file", "dir"] and (tmp_path / "a.bin").read_bytes() == b"payload"


# ------------------------------------------------------------------------------------------------ start-up


def _leftovers(settings: Settings) -> list[Path]:
    staged = settings.staging_dir / "upload-abc123" / "scene" / "images"
    staged.mkdir(parents=True)
    (staged / "0.png").write_bytes(b"half an upload")
    doomed = settings.staging_dir / "deleted-xyz" / ("d" * 32)
    doomed.mkdir(parents=True)
    half_made = settings.scenes_dir / ("e" * 32)  # renamed into scenes/, then the API died before its row
    half_made.mkdir()
    (half_made / "transforms.json").write_text("{}")
    return [staged.parents[1], doomed.parent, half_made]


def test_start_up_removes_leftovers_and_keeps_committed_scenes(tmp_path):
    settings = Settings(data_dir=tmp_path / "data", leftover_age_s=0)
    settings.make_dirs()
    committed = settings.scenes_dir / SCENE
    committed.mkdir()
    (committed / "transforms.json").write_text("{}")
    jobstore.add_scene(settings, SCENE, "room", {"frames": 1}, 10)
    leftovers = _leftovers(settings)
    time.sleep(0.01)  # the cut-off is "unchanged up to now"
    with TestClient(create_app(settings)):
        pass
    assert not any(path.exists() for path in leftovers)
    assert (committed / "transforms.json").read_text() == "{}" and jobstore.get_scene(settings, SCENE)
    assert sorted(p.name for p in settings.staging_dir.iterdir()) == []


def test_leftovers_younger_than_the_age_are_kept(tmp_path):
    """Another process sharing data_dir may be mid-upload: a fresh staging directory stays."""
    settings = Settings(data_dir=tmp_path / "data", leftover_age_s=3600)
    settings.make_dirs()
    leftovers = _leftovers(settings)
    assert clean_leftovers(settings).staging == []
    assert all(path.exists() for path in leftovers)
    cleaned = clean_leftovers(settings, now=time.time() + 3601)
    assert cleaned.staging == ["deleted-xyz", "upload-abc123"] and cleaned.scenes == ["e" * 32]


# ------------------------------------------------------------------------------------------------ eval names


def test_view_names_keep_unique_stems_and_tell_shared_ones_apart():
    paths = ["a/frame1.png", "b/frame1.png", "frame1-4.png", "c/other.jpg"]
    assert view_names(paths, [4, 9, 2, 7]) == ["frame1-4-4", "frame1-9", "frame1-4-2", "other"]
    assert view_names(["x.png", "x.png"], [3, 3]) == ["x-0", "x-1"]  # a frame listed twice


def test_evaluation_renders_of_two_frames_with_the_same_stem_both_survive(tmp_path):
    scene_dir = make_room_scene(tmp_path / "room", RoomSpec(width=16, height=12, n_frames=12, train_every=4,
                                                            n_gaps=0, gap_len=0, prior_max_points=2000))
    doc = json.loads((scene_dir / "transforms.json").read_text())
    first, second = doc["test_filenames"][:2]
    moved = "other/" + Path(first).name  # the second test frame's image, under the first one's file name
    (scene_dir / "other").mkdir()
    shutil.move(scene_dir / second, scene_dir / moved)
    text = json.dumps(doc).replace(f'"{second}"', f'"{moved}"')
    (scene_dir / "transforms.json").write_text(text)
    trained = load_model(write_tiny_run(tmp_path / "run"), "cpu")
    views = eval_views_of(load_scene(scene_dir), trained.model.transform, ["test"])
    names = [v.name for v in views["test"]]
    assert len(set(names)) == len(names) and Path(first).stem not in names[:2]
    evaluate_views(trained.model, views, trained.model.config, out_dir=tmp_path / "eval", lpips=False)
    assert sorted(p.stem for p in (tmp_path / "eval" / "test").glob("*.png")) == sorted(names)


# ------------------------------------------------------------------------------------------------ floors

# The first release past the fixes of the known advisories (torch: of its weights_only unpickler).
FLOORS = {"torch": "2.10", "Pillow": "12.3", "fastapi": "0.133.1", "starlette": "1.3.1", "python-multipart": "0.0.27",
          "trimesh": "5.0"}  # trimesh: its file resolver confined to the loaded file's directory


def _requirements() -> dict[str, Requirement]:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    listed = project["dependencies"] + [r for rs in project["optional-dependencies"].values() for r in rs]
    return {Requirement(r).name.lower(): Requirement(r) for r in listed if not r.startswith("voxnerf")}


@pytest.mark.parametrize("name", sorted(FLOORS))
def test_dependency_floors_are_past_the_known_fixes_and_installed(name):
    requirement = _requirements()[name.lower()]
    floors = [Version(s.version) for s in requirement.specifier if s.operator == ">="]
    assert floors and min(floors) >= Version(FLOORS[name]), f"{requirement}: floor below {FLOORS[name]}"
    installed = Version(re.sub(r"\+.*", "", metadata.version(name)))
    assert requirement.specifier.contains(installed, prereleases=True), f"{name} {installed} outside {requirement}"
