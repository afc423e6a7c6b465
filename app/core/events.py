"""A training job's event log (``job_events``) and the webhook deliveries of its state changes.

Every change of a job is journalled by :func:`journal` in the transaction that makes it, from the one place each
kind of change is made: the lease lifecycle (:mod:`app.core.lease`: claim, progress, cancel, finish, failure,
requeue) and the job's creation (:func:`app.core.jobstore.create_job`). A change appends, in this order:

- one ``stage`` event per stage record that is new or changed (a stage's record is compared with the last
  ``stage`` event of its name: the engine updates some records in place, e.g. ``progress_evals`` after each
  progress evaluation), with the record as data;
- one ``evaluation`` event per history point not sent before, with the point as data;
- one ``state`` event when its state changed (data: the job's columns), else one ``progress`` event (the same).

Each job's events are numbered from 1 (``seq``, only growing): the number is taken after the job's row is
written in the same transaction, and that write serializes the transactions of one job (SQLite's one writer,
PostgreSQL's row lock), so two changes never take the same number (the unique constraint would refuse it).
``progress`` events are snapshots, so only the newest :data:`PROGRESS_EVENTS_KEPT` of a job are kept; stage,
evaluation and state events are all kept. A deleted job's events and deliveries go with it (:func:`forget`).

A job with a ``callback_url`` gets one webhook delivery per ``state`` event, written beside it; the API process
sends them (``app/webhooks.py``) and records each attempt here.
"""

from __future__ import annotations

import json
import time
from typing import Any

from sqlalchemy import delete, func, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from app.core.db import session_scope
from app.core.models import JobEventRow, JobRow, WebhookDeliveryRow
from app.core.progress import json_safe
from app.core.settings import Settings

PROGRESS_EVENTS_KEPT = 100  # a job's newest progress events kept; older ones are superseded snapshots
FINAL_STATES = ("succeeded", "failed", "cancelled")
JOURNALLED_CHANGES = ("state", "progress")


def job_columns(row: JobRow) -> dict[str, Any]:
    """Every column of a job row, JSON-safe: the data of its ``state`` and ``progress`` events."""
    return json_safe({column.name: getattr(row, column.name) for column in JobRow.__table__.columns})


def job_from_columns(data: dict[str, Any]) -> JobRow:
    """A detached job row made from :func:`job_columns`' dict (keys it no longer has are left out)."""
    names = {column.name for column in JobRow.__table__.columns}
    return JobRow(**{name: value for name, value in data.items() if name in names})


def _sent(session: Session, job_id: str, kind: str) -> list[dict]:
    """The data of the job's events of ``kind``, oldest first."""
    return list(session.scalars(
        select(JobEventRow.data).where(JobEventRow.job_id == job_id, JobEventRow.kind == kind).order_by(JobEventRow.seq)
    ))


def _new_records(session: Session, job_id: str, stages: list | None, history: list | None) -> list[tuple[str, Any]]:
    """``(kind, record)`` of the stage records that are new or changed since their last ``stage`` event and of the
    history points no ``evaluation`` event has carried (a resumed run reports its earlier ones again)."""
    last_stage = {data.get("name"): data for data in _sent(session, job_id, "stage")}
    evaluated = {json.dumps(data, sort_keys=True) for data in _sent(session, job_id, "evaluation")}
    new: list[tuple[str, Any]] = []
    for record in json_safe(stages or []):
        if last_stage.get(record.get("name")) != record:
            last_stage[record.get("name")] = record
            new.append(("stage", record))
    for point in json_safe(history or []):
        key = json.dumps(point, sort_keys=True)
        if key not in evaluated:
            evaluated.add(key)
            new.append(("evaluation", point))
    return new


def _last_state(session: Session, job_id: str) -> str | None:
    """The state of the job's newest ``state`` event; None before its first."""
    data = session.scalar(
        select(JobEventRow.data)
        .where(JobEventRow.job_id == job_id, JobEventRow.kind == "state")
        .order_by(JobEventRow.seq.desc())
        .limit(1)
    )
    return None if data is None else data.get("state")


def _thin_progress(session: Session, job_id: str) -> None:
    """Delete the job's progress events older than its newest :data:`PROGRESS_EVENTS_KEPT`."""
    oldest_dropped = session.scalar(
        select(JobEventRow.seq)
        .where(JobEventRow.job_id == job_id, JobEventRow.kind == "progress")
        .order_by(JobEventRow.seq.desc())
        .offset(PROGRESS_EVENTS_KEPT)
        .limit(1)
    )
    if oldest_dropped is not None:
        session.execute(
            delete(JobEventRow).where(
                JobEventRow.job_id == job_id, JobEventRow.kind == "progress", JobEventRow.seq <= oldest_dropped
            )
        )


def journal(session: Session, job_id: str, change: str) -> None:
    """Append the events of a change just written to job ``job_id`` in ``session`` (see the module's docstring):
    ``change`` is ``state`` (the lifecycle moved it) or ``progress`` (its progress or cancel flag changed); a
    ``state`` change that leaves the state as it was (a stale running job taken over by another worker) is
    journalled as ``progress``."""
    if change not in JOURNALLED_CHANGES:
        raise ValueError(f"unknown change {change!r}: expected one of {JOURNALLED_CHANGES}")
    session.flush()
    row = session.get(JobRow, job_id, populate_existing=True)
    if row is None:
        return
    now = time.time()
    seq = session.scalar(select(func.coalesce(func.max(JobEventRow.seq), 0)).where(JobEventRow.job_id == job_id))
    events = _new_records(session, job_id, row.stages, row.history)
    if change == "state" and _last_state(session, job_id) == row.state:
        change = "progress"
    events.append((change, job_columns(row)))
    for kind, data in events:
        seq += 1
        session.add(JobEventRow(job_id=job_id, seq=seq, kind=kind, data=json_safe(data), created_at=now))
    if change == "state" and row.callback_url:
        session.add(WebhookDeliveryRow(job_id=job_id, event_seq=seq, state=row.state, outcome="pending",
                                       attempts=0, next_at=now, log=[], created_at=now))
    if change == "progress":
        session.flush()
        _thin_progress(session, job_id)


def complete_log(settings: Settings, job_id: str) -> None:
    """Journal the final state of a job that ended before it had an event log (its newest state event is not its
    state), so that its stream ends like any other's. A concurrent request doing the same wins alone."""
    try:
        with session_scope(settings) as session:
            row = session.get(JobRow, job_id)
            if row is not None and row.state in FINAL_STATES and _last_state(session, job_id) != row.state:
                journal(session, job_id, "state")
    except IntegrityError:  # the other request took the event's number first
        pass


def forget(session: Session, job_id: str) -> None:
    """Delete the events and webhook deliveries of job ``job_id`` (in the transaction deleting the job)."""
    session.execute(delete(JobEventRow).where(JobEventRow.job_id == job_id))
    session.execute(delete(WebhookDeliveryRow).where(WebhookDeliveryRow.job_id == job_id))


def events_after(settings: Settings, job_id: str, after: int, limit: int = 500) -> list[JobEventRow]:
    """The job's events numbered above ``after``, oldest first, at most ``limit``."""
    with session_scope(settings) as session:
        return list(session.scalars(
            select(JobEventRow)
            .where(JobEventRow.job_id == job_id, JobEventRow.seq > after)
            .order_by(JobEventRow.seq)
            .limit(limit)
        ))


def last_event(settings: Settings, job_id: str, kind: str | None = None) -> JobEventRow | None:
    """The job's newest event (of ``kind``, when given); None when it has none."""
    query = select(JobEventRow).where(JobEventRow.job_id == job_id)
    if kind is not None:
        query = query.where(JobEventRow.kind == kind)
    with session_scope(settings) as session:
        return session.scalar(query.order_by(JobEventRow.seq.desc()).limit(1))


def event(settings: Settings, job_id: str, seq: int) -> JobEventRow | None:
    """Event ``seq`` of the job (None when it is not kept)."""
    with session_scope(settings) as session:
        return session.scalar(select(JobEventRow).where(JobEventRow.job_id == job_id, JobEventRow.seq == seq))


# ------------------------------------------------------------------------------------------------ webhooks


def take_due_deliveries(settings: Settings, lease_s: float, limit: int = 20) -> list[WebhookDeliveryRow]:
    """Pending deliveries whose time has come, each taken for ``lease_s`` seconds (its ``next_at`` moved on, only
    if untouched since read), so that another API process does not send it meanwhile; oldest first."""
    now = time.time()
    taken = []
    with session_scope(settings) as session:
        due = list(session.scalars(
            select(WebhookDeliveryRow)
            .where(WebhookDeliveryRow.outcome == "pending", WebhookDeliveryRow.next_at <= now)
            .order_by(WebhookDeliveryRow.next_at)
            .limit(limit)
        ))
        for delivery in due:
            moved = session.execute(
                update(WebhookDeliveryRow)
                .where(WebhookDeliveryRow.id == delivery.id, WebhookDeliveryRow.attempts == delivery.attempts,
                       WebhookDeliveryRow.outcome == "pending")
                .values(next_at=now + lease_s)
            ).rowcount
            if moved:
                taken.append(delivery)
    return taken


def record_attempt(settings: Settings, delivery: WebhookDeliveryRow, status: int | None, error: str | None,
                   retry_after_s: float | None) -> None:
    """Log an attempt of ``delivery`` (as taken): its HTTP ``status`` (None when no answer came) and ``error``
    (None when delivered). ``retry_after_s``: when to try again (None: no more attempts, it is abandoned unless
    this one delivered)."""
    attempt = delivery.attempts + 1
    now = time.time()
    entry = {"attempt": attempt, "at": now, "status": status, "error": error}
    outcome = "delivered" if error is None else ("pending" if retry_after_s is not None else "abandoned")
    with session_scope(settings) as session:
        session.execute(
            update(WebhookDeliveryRow)
            .where(WebhookDeliveryRow.id == delivery.id, WebhookDeliveryRow.attempts == delivery.attempts)
            .values(attempts=attempt, log=[*(delivery.log or []), entry], outcome=outcome,
                    next_at=now + (retry_after_s or 0.0))
        )


def deliveries_of(settings: Settings, job_id: str) -> list[WebhookDeliveryRow]:
    """The job's webhook deliveries, oldest first."""
    with session_scope(settings) as session:
        return list(session.scalars(
            select(WebhookDeliveryRow).where(WebhookDeliveryRow.job_id == job_id).order_by(WebhookDeliveryRow.id)
        ))
