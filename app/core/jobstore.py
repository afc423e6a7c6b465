"""The job store: every read and write of scenes and jobs, shared by the API and the workers.

Jobs move ``queued -> running -> succeeded | failed | cancelled``. A worker *claims* a job (the row's
``attempt`` goes up by one) and then writes progress, renews its lease (``heartbeat_at``) and finishes the
job only while the row still carries that attempt. A running job whose lease is older than
``stale_after_s``, or whose worker process on this host is gone, is *stale*: :func:`mark_requeued` puts it
back to ``queued`` so that the next worker resumes it from its checkpoint. A job whose worker died
``max_worker_deaths`` times is failed instead (:func:`fail_worn_out`): it may be what kills its workers.

A queued job's ``heartbeat_at`` is when its message was last sent (created, requeued or re-sent): one queued
for longer than ``resend_queued_after_s`` may have lost its message (:func:`lost_jobs`) and is sent again;
a duplicate is harmless because claims are fenced.

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
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

from sqlalchemy import delete, func, select, update

from app.core.db import session_scope
from app.core.models import ACTIVE_STATES, JobRow, OutputRow, SceneRow
from app.core.progress import initial_values, json_safe, progress_values
from app.core.settings import Settings
from voxnerf.training.records import ProgressEvent, TrainReport, thin_series

ID_RE = re.compile(r"^[0-9a-f]{32}$")
WORKER_DIED = "the worker died"  # how a recorded worker death starts (:func:`record_worker_death`)
Table = type[JobRow] | type[OutputRow]  # the two kinds of claimable rows: training and output jobs


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


class QueueFull(Exception):
    """The client already has ``max_queued_jobs`` jobs waiting (the API answers 429)."""


def create_job(settings: Settings, scene_id: str, options: dict) -> JobRow | None:
    """A new queued job on ``scene_id``; None when the scene does not exist. Raises QueueFull when
    ``settings.max_queued_jobs`` jobs are queued already: the limit per client, and the API has one client
    (whoever holds its token, or everyone without one). The row is inserted first and the queue counted in
    the same transaction, so concurrent requests cannot both slip under the limit."""
    now = time.time()
    row = JobRow(
        id=new_id(),
        scene_id=scene_id,
        state="queued",
        options=options,
        created_at=now,
        heartbeat_at=now,  # a queued job's: when its message was sent
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
        queued = session.scalar(select(func.count()).select_from(JobRow).where(JobRow.state == "queued"))
        if queued > settings.max_queued_jobs:
            session.rollback()
            raise QueueFull(f"{queued - 1} jobs are queued already (the limit is {settings.max_queued_jobs}); "
                            "wait for some to start, or cancel some")
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


class JobActive(Exception):
    """The job, or an output job made from it, is queued or running (the API answers 409)."""


def delete_job(settings: Settings, job_id: str) -> list[str] | None:
    """Delete a finished job's row and its output jobs' rows: the ids of those output jobs, None when the job
    does not exist. Raises JobActive while the job or one of its output jobs is queued or running. The files
    are the caller's to remove."""
    with session_scope(settings) as session:
        job = session.get(JobRow, job_id)
        if job is None:
            return None
        busy_outputs = session.scalars(
            select(OutputRow.id).where(OutputRow.job_id == job_id, OutputRow.state.in_(ACTIVE_STATES))
        ).all()
        if job.state in ACTIVE_STATES or busy_outputs:
            what = f"job {job_id} is {job.state}" if job.state in ACTIVE_STATES else (
                f"output job(s) {', '.join(busy_outputs)} of job {job_id} are queued or running")
            raise JobActive(f"{what}; cancel it and wait for it to stop first")
        output_ids = list(session.scalars(select(OutputRow.id).where(OutputRow.job_id == job_id)))
        session.execute(delete(OutputRow).where(OutputRow.job_id == job_id))
        session.delete(job)
    return output_ids


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


def claim_row(settings: Settings, table: Table, row_id: str, worker: str,
              fresh: Callable[[Any, float], dict]) -> Any | None:
    """Take a queued (or stale running) row of ``table`` for ``worker``; None when it is not there to take.

    Returns the row as claimed; its ``attempt`` is the fencing token for every later write. Taking over a
    stale running row counts as a requeue, as :func:`mark_requeued` does, so ``requeues`` says how often the
    row was taken from a dead worker whichever of the sweep and the next worker comes first; one whose
    worker died ``max_worker_deaths`` times is failed instead (:func:`fail_worn_out`). ``fresh(row, now)``:
    the further columns the claim sets. When the row changes under the claim (the sweep moved it to
    ``queued`` meanwhile) the claim reads it again.
    """
    for _ in range(CLAIM_TRIES):
        now = time.time()
        with session_scope(settings) as session:
            row = session.get(table, row_id)
        if row is None or row.state not in ACTIVE_STATES:
            return None
        if row.state == "running" and (not is_stale(row, settings, now) or fail_worn_out(settings, table, row)):
            return None
        with session_scope(settings) as session:
            claimed = session.execute(
                update(table)
                .where(table.id == row_id, table.attempt == row.attempt, table.state == row.state)
                .values(
                    state="running",
                    attempt=row.attempt + 1,
                    requeues=row.requeues + int(row.state == "running"),
                    worker=worker,
                    heartbeat_at=now,
                    **fresh(row, now),
                )
            ).rowcount
        if claimed:
            with session_scope(settings) as session:
                return session.get(table, row_id)
    return None


def claim_job(settings: Settings, job_id: str, worker: str) -> JobRow | None:
    """Take a queued (or stale running) job for ``worker`` (:func:`claim_row`); None when it is not there to
    take. The returned row's ``attempt`` fences every later write."""
    return claim_row(settings, JobRow, job_id, worker,
                     lambda job, now: {"started_at": job.started_at or now, "stage": "starting"})


def record_worker_death(settings: Settings, table: Table, row_id: str, why: str) -> None:
    """Note on an active row that its worker process died (``why``: e.g. Celery's "Worker exited prematurely:
    signal 9 (SIGKILL)"); the error of a job failed for too many deaths names the last one."""
    with session_scope(settings) as session:
        session.execute(
            update(table)
            .where(table.id == row_id, table.state.in_(ACTIVE_STATES))
            .values(error=f"{WORKER_DIED}: {why}")
        )


def fail_worn_out(settings: Settings, table: Table, row: Any) -> bool:
    """Fail a stale running row (read as ``row``) when its worker has now died ``max_worker_deaths`` times,
    naming the last death; True when failed (False: requeue it). Fenced like a claim."""
    deaths = row.requeues + 1
    if deaths < settings.max_worker_deaths:
        return False
    noun = "job" if table is JobRow else "output job"
    last = row.error[len(WORKER_DIED) + 2:] if (row.error or "").startswith(WORKER_DIED) else (
        "no exit status recorded: killed, out of memory, or its lease expired")
    error = f"{WORKER_DIED} {deaths} times while running this {noun} (last: {last}); not retried again"
    with session_scope(settings) as session:
        session.execute(
            update(table)
            .where(table.id == row.id, table.attempt == row.attempt, table.state == "running")
            .values(state="failed", error=error, finished_at=time.time(), eta_s=None,
                    **({"stage": "failed"} if table is JobRow else {}))
        )
    return True


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
    """Write a progress event's fields (and renew the lease) of a claimed job; False when no longer owned.
    The loss series keeps the points an earlier attempt recorded before this one resumed (:func:`joined_series`)."""
    return _write_running(settings, job_id, attempt, _with_earlier_losses(settings, job_id, progress_values(event)))


def joined_series(stored: list | None, incoming: list) -> list:
    """The loss series of a job (``[seconds, loss]`` pairs): ``incoming`` (this attempt's, from the engine)
    after the ``stored`` points that come before its first, thinned to at most LOSS_SERIES_MAX_POINTS. A
    resumed run's engine starts its series afresh; the points an earlier attempt wrote after its last checkpoint
    (later than the resumed run's first point) are dropped."""
    if not incoming:
        return list(stored or [])
    earlier = [point for point in stored or [] if point[0] < incoming[0][0]]
    return thin_series([tuple(p) for p in earlier] + [tuple(p) for p in incoming])


def _with_earlier_losses(settings: Settings, job_id: str, values: dict) -> dict:
    """``values`` with their ``loss_series`` joined to the one the job's row holds (:func:`joined_series`)."""
    if "loss_series" not in values:
        return values
    with session_scope(settings) as session:
        stored = session.scalar(select(JobRow.loss_series).where(JobRow.id == job_id))
    return {**values, "loss_series": joined_series(stored, values["loss_series"])}


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
        loss_series=report.loss_series,
    )
    values = _with_earlier_losses(settings, job_id, progress_values(final, final.model_fields_set))
    values["metrics"] = json_safe(report.metrics)
    values["error"] = None  # a worker death noted on the way (record_worker_death) no longer applies
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


def still_owned(settings: Settings, job_id: str, attempt: int) -> bool:
    """Whether the job still carries ``attempt`` and runs (its worker may write the run's files); renews the
    lease."""
    return _write_running(settings, job_id, attempt, {})


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
                .values(state="queued", requeues=job.requeues + 1, stage="requeued", worker=None,
                        heartbeat_at=time.time())
            ).rowcount
            if done:
                moved.append(job.id)
    return moved


def lost_jobs(settings: Settings) -> list[JobRow]:
    """Queued jobs whose message was sent ``resend_queued_after_s`` ago or longer and no worker took: the
    message may be lost (the API died between the row and the send, the broker lost it, a consumer died
    holding it), or the job still waits its turn behind others (then the copy is refused by the fence)."""
    before = time.time() - settings.resend_queued_after_s
    with session_scope(settings) as session:
        return list(session.scalars(
            select(JobRow).where(JobRow.state == "queued", func.coalesce(JobRow.heartbeat_at, 0.0) <= before)
        ))


def mark_resent(settings: Settings, job: JobRow) -> bool:
    """Note that a queued job's message was sent again now (only if untouched since read)."""
    with session_scope(settings) as session:
        return bool(session.execute(
            update(JobRow)
            .where(JobRow.id == job.id, JobRow.state == "queued", JobRow.attempt == job.attempt)
            .values(heartbeat_at=time.time())
        ).rowcount)
