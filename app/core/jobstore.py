"""The job store: every read and write of scenes and training jobs, shared by the API and the workers.

A training job's lease lifecycle (claim with a fence, lease renewal, progress, cancel, finish, stale sweep,
re-send of a lost message, worker deaths) is the one every kind of queued work shares
(:mod:`app.core.lease`): :data:`JOBS` is the training jobs' kind, whose claim starts (or resumes) a run and
whose progress is written from the engine's typed records: :meth:`~app.core.lease.WorkKind.record_progress`
takes a ``ProgressEvent`` and :func:`finish_with_report` a ``TrainReport`` (the columns are
:data:`app.core.progress.PROGRESS_FIELDS`). What is a job's own is here: its creation under the queue limit,
the scenes it trains on and their busy checks, its deletion, and its loss series joined across attempts.
"""

from __future__ import annotations

import math
import re
import time
import uuid
from typing import Any

from sqlalchemy import delete, select

from app.core import events, tokens
from app.core.celery_app import TRAIN_TASK
from app.core.db import session_scope
from app.core.lease import WorkKind
from app.core.models import ACTIVE_STATES, JobRow, OutputRow, SceneRow
from app.core.progress import initial_values, json_safe, progress_values
from app.core.settings import Settings
from app.core.tokens import Principal
from voxnerf.training.records import ProgressEvent, TrainReport, thin_series

ID_RE = re.compile(r"^[0-9a-f]{32}$")


def new_id() -> str:
    """A fresh resource id: 32 lowercase hex digits (uuid4)."""
    return uuid.uuid4().hex


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


def add_scene(settings: Settings, scene_id: str, name: str, summary: dict, size_bytes: int,
              created_by: str | None = None) -> SceneRow:
    """Add scene ``scene_id``'s row, made by principal ``created_by`` (None: outside the API)."""
    row = SceneRow(
        id=scene_id, name=name, created_at=time.time(), size_bytes=size_bytes, summary=json_safe(summary),
        created_by=created_by,
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


def _progress(settings: Settings, job_id: str, event: ProgressEvent) -> dict:
    """The columns of a progress event's fields; the loss series keeps the points an earlier attempt recorded
    before this one resumed (:func:`joined_series`)."""
    return _with_earlier_losses(settings, job_id, progress_values(event))


JOBS = WorkKind(
    name="job",
    noun="job",
    table=JobRow,
    task=TRAIN_TASK,
    # a claim starts the run, or resumes it from its checkpoint: the first start and the progress stay
    claimed=lambda job, now: {"started_at": job.started_at or now, "stage": "starting"},
    progress=_progress,
    staged=True,
    journal=events.journal,  # every change of a job is in its event log (GET /jobs/{id}/events, webhooks)
)
"""Training jobs' lease lifecycle (:class:`app.core.lease.WorkKind`): ``JOBS.get``, ``claim``,
``record_progress(settings, job_id, attempt, event)``, ``finish``, ``request_cancel``..."""


def create_job(settings: Settings, scene_id: str, options: dict, principal: Principal | None = None,
               callback_url: str | None = None) -> JobRow | None:
    """A new queued job on ``scene_id`` made by ``principal`` (None: outside the API, by no one), its first event
    (``queued``) journalled with it; its state changes are posted to ``callback_url`` when given. None when the
    scene does not exist. Raises :class:`app.core.lease.QueueFull` when ``settings.max_queued_jobs`` jobs are queued
    already, or as many as the principal's own limit allows (:meth:`app.core.lease.WorkKind.refuse_beyond`; nothing
    is written then)."""
    row = JOBS.new_row(new_id(), scene_id=scene_id, options=options, created_by=principal and principal.name,
                       callback_url=callback_url, **initial_values())
    with session_scope(settings) as session:
        session.add(row)
        session.flush()
        if session.get(SceneRow, scene_id) is None:
            session.rollback()
            return None
        JOBS.refuse_beyond(session, settings.max_queued_jobs, "max_queued_jobs",
                           principal and tokens.queue_quota(settings, principal))
        events.journal(session, row.id, "state")
    return row


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
        events.forget(session, job_id)
        session.delete(job)
    return output_ids


def report_outcome(settings: Settings, job_id: str, report: TrainReport, progress: float) -> tuple[str, dict]:
    """The final state and columns of a job from the report ``train()`` returned: ``succeeded`` (progress 1,
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
    return ("succeeded" if succeeded else "cancelled"), values


def finish_with_report(settings: Settings, job_id: str, attempt: int, report: TrainReport, progress: float) -> bool:
    """Move a claimed job to its final state from its report (:func:`report_outcome`); False when not owned."""
    return JOBS.finish(settings, job_id, attempt, *report_outcome(settings, job_id, report, progress))
