"""One lease lifecycle for every kind of queued work: training jobs (:data:`app.core.jobstore.JOBS`) and output
jobs (videos, meshes, point clouds: :data:`app.core.outputs.OUTPUTS`), shared by the API, the dispatcher's sweep
(:mod:`app.core.dispatch`) and the workers (:mod:`worker.lease` drives it on their side).

A row of work moves ``queued -> running -> succeeded | failed | cancelled``. A worker *claims* it (the row's
``attempt`` goes up by one: the fence) and then writes progress, renews its lease (``heartbeat_at``) and finishes
it only while the row still carries that attempt, so a worker presumed dead never overwrites its successor. A
running row whose lease is older than ``stale_after_s``, or whose worker process on this host is gone, is
*stale* (:func:`is_stale`): the sweep sends its message again and puts it back to ``queued``
(:meth:`WorkKind.mark_requeued`), and the next worker takes it over (a training job resumes from its checkpoint,
an output starts again from its first frame). One whose worker died ``max_worker_deaths`` times is failed instead
(:meth:`WorkKind.fail_worn_out`): it may be what kills its workers.

A queued row's ``heartbeat_at`` is when its message was last sent (created, requeued or re-sent) or last seen
waiting in the broker: one queued for ``resend_queued_after_s`` or longer may have lost its message
(:meth:`WorkKind.lost`) and is sent again unless the broker still holds it (:func:`app.core.dispatch.resend_lost`);
a duplicate is harmless because claims are fenced.

What differs between kinds are a :class:`WorkKind`'s parameters: its table, the Celery task that runs it, the
columns a claim sets, how its progress is written, whether its rows have a ``stage`` column, and the journal its
changes are recorded in (training jobs: :func:`app.core.events.journal`), which each move below calls in its own
transaction.
"""

from __future__ import annotations

import os
import socket
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from sqlalchemy import func, select, update

from app.core.db import session_scope
from app.core.models import ACTIVE_STATES
from app.core.progress import json_safe
from app.core.settings import Settings

if TYPE_CHECKING:
    from app.core.tokens import QueueQuota

WORKER_DIED = "the worker died"  # how a recorded worker death starts (:meth:`WorkKind.record_worker_death`)
CLAIM_TRIES = 3  # a claim re-reads the row when another writer changed it between its read and its update
FINAL_STAGES = {"succeeded": "done", "failed": "failed", "cancelled": "cancelled"}  # the ``stage`` of a final row


def worker_identity() -> str:
    """``host:pid`` of the calling process, recorded on the rows it claims."""
    return f"{socket.gethostname()}:{os.getpid()}"


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def is_stale(row: Any, settings: Settings, now: float) -> bool:
    """Whether a running row's worker is presumed dead: lease expired, or its process on this host is gone."""
    if row.heartbeat_at is None or now - row.heartbeat_at > settings.stale_after_s:
        return True
    host, _, pid = (row.worker or "").rpartition(":")
    return host == socket.gethostname() and pid.isdigit() and not _pid_alive(int(pid))


class QueueFull(Exception):
    """The client already has as many rows of a kind queued as its limit allows (the API answers 429)."""


@dataclass(frozen=True)
class LeaseStatus:
    owned: bool
    cancel_requested: bool


@dataclass(frozen=True, eq=False)
class WorkKind:
    """A kind of queued work and its lease lifecycle (see the module's docstring).

    ``name``: how the API names one (``job``, ``output``); ``noun``: how a worker-death error names one;
    ``table``: its ORM class (the columns ``state attempt requeues worker heartbeat_at cancel_requested
    created_at started_at finished_at error eta_s``); ``task``: the Celery task that runs it (its message's
    one argument is the row's id); ``claimed(row, now)``: the further columns a claim sets;
    ``progress(settings, row_id, *report)``: the columns a progress report writes; ``staged``: the rows have a
    ``stage`` column, which the lifecycle's moves name (``requeued``, ``done``, ``failed``, ``cancelled``);
    ``journal(session, row_id, change)``, when set, records each change in the transaction that writes it
    (``change``: ``state`` when the row moved in its lifecycle, ``progress`` when its progress or cancel flag
    changed).
    """

    name: str
    noun: str
    table: type
    task: str
    claimed: Callable[[Any, float], dict]
    progress: Callable[..., dict]
    staged: bool = False
    journal: Callable[[Any, str, str], None] | None = None

    def _stage(self, stage: str) -> dict:
        return {"stage": stage} if self.staged else {}

    def _changed(self, session: Any, row_id: str, change: str) -> None:
        """Journal a change just written to row ``row_id`` in ``session`` (when the kind has a journal)."""
        if self.journal is not None:
            self.journal(session, row_id, change)

    # -------------------------------------------------------------------------------------------- the API's

    def new_row(self, row_id: str, **columns: Any) -> Any:
        """A queued row (not yet added) whose message is about to be sent: ``heartbeat_at`` is now."""
        now = time.time()
        return self.table(id=row_id, state="queued", created_at=now, heartbeat_at=now, cancel_requested=False,
                          attempt=0, requeues=0, **columns)

    def refuse_beyond(self, session: Any, limit: int, setting: str, quota: QueueQuota | None = None) -> None:
        """Raise QueueFull when more than ``quota.limit`` rows of this kind made by ``quota.principal`` are queued
        (naming whose limit it is), or more than ``limit`` rows of all clients together (naming ``setting``),
        counting the one ``session`` has just added. The caller adds its row first and counts in the same
        transaction, which the exception rolls back, so concurrent requests cannot both slip under a limit."""
        if quota is not None:
            own = session.scalar(select(func.count()).select_from(self.table).where(
                self.table.state == "queued", self.table.created_by == quota.principal))
            if own > quota.limit:
                raise QueueFull(f"{own - 1} {self.name}s of token {quota.principal!r} are queued already (its limit "
                                f"is {quota.limit}: {quota.source}); wait for some to start, or cancel some")
        queued = session.scalar(select(func.count()).select_from(self.table).where(self.table.state == "queued"))
        if queued > limit:
            raise QueueFull(f"{queued - 1} {self.name}s are queued already (the limit is {limit}, "
                            f"VOXNERF_{setting.upper()}, for all clients together); wait for some to start, or "
                            "cancel some")

    def get(self, settings: Settings, row_id: str) -> Any | None:
        with session_scope(settings) as session:
            return session.get(self.table, row_id)

    def newest(self, settings: Settings, limit: int = 100, **equal: Any) -> list:
        """At most ``limit`` rows, newest first; ``column=value`` keeps the rows with that value (None: any)."""
        query = select(self.table).order_by(self.table.created_at.desc()).limit(limit)
        for column, value in equal.items():
            if value is not None:
                query = query.where(getattr(self.table, column) == value)
        with session_scope(settings) as session:
            return list(session.scalars(query))

    def fail(self, settings: Settings, row_id: str, error: str) -> None:
        """Fail a queued or running row whoever holds it: one that never reached a worker (the broker refused
        its message)."""
        with session_scope(settings) as session:
            if session.execute(
                update(self.table)
                .where(self.table.id == row_id, self.table.state.in_(ACTIVE_STATES))
                .values(state="failed", error=error, finished_at=time.time(), eta_s=None)
            ).rowcount:
                self._changed(session, row_id, "state")

    def request_cancel(self, settings: Settings, row_id: str, by: str | None = None) -> Any | None:
        """Cancel a row: a queued one at once, a running one when its worker next reads the flag (through its
        lease); the row as it is now. ``by``: the principal asking, recorded as ``cancelled_by`` (by the first
        request only; a finished row is left as it is)."""
        with session_scope(settings) as session:
            cancelled = session.execute(
                update(self.table)
                .where(self.table.id == row_id, self.table.state == "queued")
                .values(state="cancelled", cancel_requested=True, finished_at=time.time(), cancelled_by=by,
                        **self._stage("cancelled"))
            ).rowcount
            if cancelled:
                self._changed(session, row_id, "state")
            elif session.execute(
                update(self.table)
                .where(self.table.id == row_id, self.table.state == "running",
                       self.table.cancel_requested.is_(False))
                .values(cancel_requested=True, cancelled_by=by)
            ).rowcount:
                self._changed(session, row_id, "progress")
        return self.get(settings, row_id)

    # -------------------------------------------------------------------------------------------- the worker's

    def claim(self, settings: Settings, row_id: str, worker: str) -> Any | None:
        """Take a queued (or stale running) row for ``worker``; None when it is not there to take.

        Returns the row as claimed; its ``attempt`` is the fencing token for every later write. Taking over a
        stale running row counts as a requeue, as :meth:`mark_requeued` does, so ``requeues`` says how often the
        row was taken from a dead worker whichever of the sweep and the next worker comes first; one whose
        worker died ``max_worker_deaths`` times is failed instead (:meth:`fail_worn_out`). When the row changes
        under the claim (the sweep moved it to ``queued`` meanwhile) the claim reads it again.
        """
        table = self.table
        for _ in range(CLAIM_TRIES):
            now = time.time()
            row = self.get(settings, row_id)
            if row is None or row.state not in ACTIVE_STATES:
                return None
            if row.state == "running" and (not is_stale(row, settings, now) or self.fail_worn_out(settings, row)):
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
                        **self.claimed(row, now),
                    )
                ).rowcount
                if claimed:
                    self._changed(session, row_id, "state")
            if claimed:
                return self.get(settings, row_id)
        return None

    def write_running(self, settings: Settings, row_id: str, attempt: int, values: dict,
                      change: str | None = None) -> bool:
        """Update a running row (and renew its lease) while it still carries ``attempt``, journalling ``change``
        (none for a lease renewal); False when it does not."""
        table = self.table
        with session_scope(settings) as session:
            written = bool(
                session.execute(
                    update(table)
                    .where(table.id == row_id, table.attempt == attempt, table.state == "running")
                    .values(heartbeat_at=time.time(), **{k: json_safe(v) for k, v in values.items()})
                ).rowcount
            )
            if written and change is not None:
                self._changed(session, row_id, change)
            return written

    def renew_lease(self, settings: Settings, row_id: str, attempt: int) -> LeaseStatus:
        """Refresh a claimed row's heartbeat and read its cancel flag (the lease of ``worker.lease.Lease``)."""
        owned = self.write_running(settings, row_id, attempt, {})
        with session_scope(settings) as session:
            cancel = session.scalar(select(self.table.cancel_requested).where(self.table.id == row_id))
        return LeaseStatus(owned, bool(cancel))

    def still_owned(self, settings: Settings, row_id: str, attempt: int) -> bool:
        """Whether the row still carries ``attempt`` and runs (its worker may write its files); renews the
        lease."""
        return self.write_running(settings, row_id, attempt, {})

    def record_progress(self, settings: Settings, row_id: str, attempt: int, *report: Any) -> bool:
        """Write a progress report (the kind's ``progress`` makes its columns) of a claimed row; False when no
        longer owned."""
        return self.write_running(settings, row_id, attempt, self.progress(settings, row_id, *report), "progress")

    def finish(self, settings: Settings, row_id: str, attempt: int, state: str, values: dict) -> bool:
        """Move a claimed row to final ``state`` (succeeded, failed, cancelled) with its last fields (error,
        summary...); no ETA any more, progress 1 when succeeded. False when no longer owned."""
        final = {"state": state, "finished_at": time.time(), "eta_s": None, **self._stage(FINAL_STAGES[state])}
        if state == "succeeded":
            final["progress"] = 1.0
        return self.write_running(settings, row_id, attempt, {**final, **values}, "state")

    def record_worker_death(self, settings: Settings, row_id: str, why: str) -> None:
        """Note on an active row that its worker process died (``why``: e.g. Celery's "Worker exited
        prematurely: signal 9 (SIGKILL)"); the error of a row failed for too many deaths names the last one."""
        with session_scope(settings) as session:
            session.execute(
                update(self.table)
                .where(self.table.id == row_id, self.table.state.in_(ACTIVE_STATES))
                .values(error=f"{WORKER_DIED}: {why}")
            )

    # -------------------------------------------------------------------------------------------- the sweep's

    def fail_worn_out(self, settings: Settings, row: Any) -> bool:
        """Fail a stale running row (read as ``row``) when its worker has now died ``max_worker_deaths`` times,
        naming the last death; True when failed (False: requeue it). Fenced like a claim."""
        deaths = row.requeues + 1
        if deaths < settings.max_worker_deaths:
            return False
        last = row.error[len(WORKER_DIED) + 2:] if (row.error or "").startswith(WORKER_DIED) else (
            "no exit status recorded: killed, out of memory, or its lease expired")
        error = f"{WORKER_DIED} {deaths} times while running this {self.noun} (last: {last}); not retried again"
        table = self.table
        with session_scope(settings) as session:
            if session.execute(
                update(table)
                .where(table.id == row.id, table.attempt == row.attempt, table.state == "running")
                .values(state="failed", error=error, finished_at=time.time(), eta_s=None, **self._stage("failed"))
            ).rowcount:
                self._changed(session, row.id, "state")
        return True

    def stale(self, settings: Settings) -> list:
        """Running rows whose worker is presumed dead (:func:`is_stale`)."""
        now = time.time()
        with session_scope(settings) as session:
            running = list(session.scalars(select(self.table).where(self.table.state == "running")))
        return [row for row in running if is_stale(row, settings, now)]

    def mark_requeued(self, settings: Settings, rows: Iterable[Any]) -> list[str]:
        """Put stale running rows back to ``queued`` (only if untouched since read), their message just sent
        again; returns the ids moved."""
        table = self.table
        moved = []
        with session_scope(settings) as session:
            for row in rows:
                done = session.execute(
                    update(table)
                    .where(table.id == row.id, table.attempt == row.attempt, table.state == "running")
                    .values(state="queued", requeues=row.requeues + 1, worker=None, heartbeat_at=time.time(),
                            eta_s=None, **self._stage("requeued"))
                ).rowcount
                if done:
                    self._changed(session, row.id, "state")
                    moved.append(row.id)
        return moved

    def lost(self, settings: Settings) -> list:
        """Queued rows whose message was sent ``resend_queued_after_s`` ago or longer and no worker took: the
        message may be lost (the API died between the row and the send, the broker lost it, a consumer died
        holding it), or the row still waits its turn behind others (then the copy is refused by the fence)."""
        before = time.time() - settings.resend_queued_after_s
        table = self.table
        with session_scope(settings) as session:
            return list(session.scalars(
                select(table).where(table.state == "queued", func.coalesce(table.heartbeat_at, 0.0) <= before)
            ))

    def mark_resent(self, settings: Settings, row: Any) -> bool:
        """Note that a queued row's message was sent again, or seen waiting in the broker, now (only if untouched
        since read)."""
        table = self.table
        with session_scope(settings) as session:
            return bool(session.execute(
                update(table)
                .where(table.id == row.id, table.state == "queued", table.attempt == row.attempt)
                .values(heartbeat_at=time.time())
            ).rowcount)
