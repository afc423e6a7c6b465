"""A job store with one scene and a claimed training job, for the worker's unit tests (no Celery, no training)."""

from __future__ import annotations

from pathlib import Path

from app.core import jobstore
from app.core.lease import worker_identity
from app.core.settings import Settings

SCENE = "a" * 32


def store_with_scene(tmp_path: Path, **overrides) -> Settings:
    """Settings on a fresh data directory in ``tmp_path`` (``overrides`` replace fields) whose job store holds
    scene ``SCENE``."""
    settings = Settings(data_dir=tmp_path / "data", **overrides)
    settings.make_dirs()
    (settings.scenes_dir / SCENE).mkdir()
    jobstore.add_scene(settings, SCENE, "room", {"frames": 1}, 10)
    return settings


def claimed_job(settings: Settings) -> jobstore.JobRow:
    """A new training job on ``SCENE``, claimed by this process (attempt 1)."""
    job = jobstore.create_job(settings, SCENE, {"max_iters": 50, "compile": False})
    return jobstore.JOBS.claim(settings, job.id, worker_identity())
