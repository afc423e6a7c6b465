"""The job store: every read and write of scenes and jobs, shared by the API and the workers.

Jobs move ``queued -> running -> succeeded | failed | cancelled``. A worker *claims* a job (the row's
``attempt`` goes up by one) and then writes progress, renews its lease (``heartbeat_at``) and finishes the
job only while the row still carries that attempt. A running job whose lease is older than
``stale_after_s``, or whose worker process on this host is gone, is *stale*: :func:`mark_requeued` puts it
back to ``queued`` so that the next worker resumes it from its checkpoint.

Progress is written from the engine's typed records: :func:`record_progress` takes a ``ProgressEvent`` and
:func:`finish_with_report` a ``TrainReport`` (the columns are :data:`app.core.progress.PROGRESS_FIELDS`).
"""

from __future__ import annotations

import math
import os
import re
import socket
import time
import uuid
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from sqlalchemy import select, update

from app.core.db import session_scope
from app.core.models import ACTIVE_STATES, JobRow, SceneRow
from app.core.progress import initial_values, json_safe, progress_values
from app.core.settings import Settings
from voxnerf.training.records import ProgressEvent, TrainReport

ID_RE = re.compile(r"^[0-9a-f]{32}$")


def new_id() -> str:
    """A fresh resource id: 32 lowercase hex digits (uuid4)."""
    return uuid.uuid4().hex


def worker_identity() -> str:
    """``host:pid`` of the calling process, recorded on the jobs it claims."""
    return f"{socket.gethostname()}:{os.getpid()}"


def finite_or_none(value: Any) -> float | None:
    """``float(value)`` when it is a finite number, else None (NaN never reaches the store or the API)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return float(value) if math.isfinite(value) else None


# ------------------------------------------------------------------------------------------------ scenes


class SceneBusy(Exception):
    """The scene is used by queued or running jobs and cannot be deleted."""

    def __init__(self, job_ids: list[str]) -> None:
        self.job_ids = job_ids
        super().__init__(f"used by {len(job_ids)} active job(s): {', '.join(job_ids)}")


def add_scene(settings: Settings, scene_id: str, name: str, summary: dict, size_bytes: int) -> SceneRow:
    row = SceneRow(
        id=scene_id, name=name, created_at=time.time(), size_bytes=size_bytes, summary=json_safe(summary)
    )
    with session_scope(settings) as session:
        session.add(row)
    return row


def list_scenes(settings: Settings) -> list[SceneRow]:
    with session_scope(settings) as session:
        return list(session.scalars(select(SceneRow).order_by(SceneRow.created_at.desc())))


def get_scene(settings: Settings, scene_id: str) -> SceneRow | None:
    with session_scope(settings) as session:
        return session.get(SceneRow, scene_id)


def delete_scene(settings: Settings, scene_id: str) -> bool:
    """Delete the scene's row; False when it does not exist. Raises SceneBusy while active jobs use it.

    The delete is written first and the jobs checked in the same transaction, so a job created concurrently
    (which inserts first and then checks the scene) and this delete can never both succeed.
    """
    with session_scope(settings) as session:
        row = session.get(SceneRow, scene_id)
        if row is None:
            return False
        session.delete(row)
        session.flush()
        active = list(
            session.scalars(
                select(JobRow.id).where(JobRow.scene_id == scene_id, JobRow.state.in_(ACTIVE_STATES))
            )
        )
        if active:
            raise SceneBusy(active)
    return True


# ------------------------------------------------------------------------------------------------ jobs


def create_job(settings: Settings, scene_id: str, options: dict) -> JobRow | None:
    """A new queued job on ``scene_id``; None when the scene does not exist."""
    row = JobRow(
        id=new_id(),
        scene_id=scene_id,
        state="queued",
        options=options,
        created_at=time.time(),
        cancel_requested=False,
        attempt=0,
        requeues=0,
        **initial_values(),
    )
    with session_scope(settings) as session:
        session.add(row)
        session.flush()
        if session.get(SceneRow, scene_id) is None:
            session.rollback()
            return None
    return row


def list_jobs(settings: Settings, limit: int = 100, scene_id: str | None = None) -> list[JobRow]:
    query = select(JobRow).order_by(JobRow.created_at.desc()).limit(limit)
    if scene_id is not None:
        query = query.where(JobRow.scene_id == scene_id)
    with session_scope(settings) as session:
        return list(session.scalars(query))


def get_job(settings: Settings, job_id: str) -> JobRow | None:
    with session_scope(settings) as session:
        return session.get(JobRow, job_id)


def fail_job(settings: Settings, job_id: str, error: str) -> None:
    """Mark a job that never reached a worker (e.g. the broker refused it) as failed."""
    with session_scope(settings) as session:
        session.execute(
            update(JobRow)
            .where(JobRow.id == job_id, JobRow.state.in_(ACTIVE_STATES))
            .values(state="failed", error=error, finished_at=time.time())
        )


def request_cancel(settings: Settings, job_id: str) -> JobRow | None:
    """Cancel a job: a queued one at once, a running one at its next iteration (its worker sees the flag)."""
    now = time.time()
    with session_scope(settings) as session:
        done = session.execute(
            update(JobRow)
            .where(JobRow.id == job_id, JobRow.state == "queued")
            .values(state="cancelled", cancel_requested=True, finished_at=now, stage="cancelled")
        ).rowcount
        if not done:
            session.execute(
                update(JobRow)
                .where(JobRow.id == job_id, JobRow.state == "running")
                .values(cancel_requested=True)
            )
    return get_job(settings, job_id)


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def is_stale(job: JobRow, settings: Settings, now: float) -> bool:
    """Whether a running job's worker is presumed dead: lease expired, or its process on this host is gone."""
    if job.heartbeat_at is None or now - job.heartbeat_at > settings.stale_after_s:
        return True
    host, _, pid = (job.worker or "").rpartition(":")
    return host == socket.gethostname() and pid.isdigit() and not _pid_alive(int(pid))


CLAIM_TRIES = 3  # a claim re-reads the row when another writer changed it between its read and its update


def claim_job(settings: Settings, job_id: str, worker: str) -> JobRow | None:
    """Take a queued (or stale running) job for ``worker``; None when it is not there to take.

    Returns the row as claimed; its ``attempt`` is the fencing token for every later write. Taking over a
    stale running job counts as a requeue, as :func:`mark_requeued` does, so ``requeues`` says how often the
    job was taken from a dead worker whichever of the sweep and the next worker comes first. When the row
    changes under the claim (the sweep moved it to ``queued`` meanwhile) the claim reads it again.
    """
    for _ in range(CLAIM_TRIES):
        now = time.time()
        job = get_job(settings, job_id)
        if job is None or job.state not in ACTIVE_STATES:
            return None
        if job.state == "running" and not is_stale(job, settings, now):
            return None
        with session_scope(settings) as session:
            claimed = session.execute(
                update(JobRow)
                .where(JobRow.id == job_id, JobRow.attempt == job.attempt, JobRow.state == job.state)
                .values(
                    state="running",
                    attempt=job.attempt + 1,
                    requeues=job.requeues + int(job.state == "running"),
                    worker=worker,
                    heartbeat_at=now,
                    started_at=job.started_at or now,
                    stage="starting",
                )
            ).rowcount
        if claimed:
            return get_job(settings, job_id)
    return None


@dataclass(frozen=True)
class LeaseStatus:
    owned: bool
    cancel_requested: bool


def renew_lease(settings: Settings, job_id: str, attempt: int) -> LeaseStatus:
    """Refresh the heartbeat of a claimed job and read its cancel flag."""
    with session_scope(settings) as session:
        owned = session.execute(
            update(JobRow)
            .where(JobRow.id == job_id, JobRow.attempt == attempt, JobRow.state == "running")
            .values(heartbeat_at=time.time())
        ).rowcount
        cancel = session.scalar(select(JobRow.cancel_requested).where(JobRow.id == job_id))
    return LeaseStatus(bool(owned), bool(cancel))


def record_progress(settings: Settings, job_id: str, attempt: int, event: ProgressEvent) -> bool:
    """Write a progress event's fields (and renew the lease) of a claimed job; False when no longer owned."""
    return _write_running(settings, job_id, attempt, progress_values(event))


def finish_job(settings: Settings, job_id: str, attempt: int, state: str, values: dict) -> bool:
    """Move a claimed job to a final state with its last fields (error, stage...); False when not owned."""
    return _write_running(settings, job_id, attempt, {"state": state, "finished_at": time.time(), **values})


def finish_with_report(settings: Settings, job_id: str, attempt: int, report: TrainReport, progress: float) -> bool:
    """Move a claimed job to its final state from the report ``train()`` returned: ``succeeded`` (progress 1,
    metrics) or ``cancelled`` (stopped early: ``progress`` is how far it got). The last loss stays."""
    succeeded = report.status == "succeeded"
    final = ProgressEvent(
        stage="done" if succeeded else "cancelled",
        iteration=report.iteration,
        elapsed_s=report.train_seconds or 0.0,
        progress=1.0 if succeeded else progress,
        eta_s=None,
        history=report.history,
        stages=report.stages,
    )
    values = progress_values(final, final.model_fields_set)
    values["metrics"] = json_safe(report.metrics)
    return finish_job(settings, job_id, attempt, "succeeded" if succeeded else "cancelled", values)


def _write_running(settings: Settings, job_id: str, attempt: int, values: dict) -> bool:
    """Update a running job's row while it still carries ``attempt``; False when it does not."""
    with session_scope(settings) as session:
        return bool(
            session.execute(
                update(JobRow)
                .where(JobRow.id == job_id, JobRow.attempt == attempt, JobRow.state == "running")
                .values(heartbeat_at=time.time(), **{k: json_safe(v) for k, v in values.items()})
            ).rowcount
        )


def stale_jobs(settings: Settings) -> list[JobRow]:
    """Running jobs whose worker is presumed dead (see :func:`is_stale`)."""
    now = time.time()
    with session_scope(settings) as session:
        running = list(session.scalars(select(JobRow).where(JobRow.state == "running")))
    return [job for job in running if is_stale(job, settings, now)]


def mark_requeued(settings: Settings, jobs: Iterable[JobRow]) -> list[str]:
    """Put stale running jobs back to ``queued`` (only if untouched since read); returns the ids moved."""
    moved = []
    with session_scope(settings) as session:
        for job in jobs:
            done = session.execute(
                update(JobRow)
                .where(JobRow.id == job.id, JobRow.attempt == job.attempt, JobRow.state == "running")
                .values(state="queued", requeues=job.requeues + 1, stage="requeued", worker=None)
            ).rowcount
            if done:
                moved.append(job.id)
    return moved
