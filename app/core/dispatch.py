"""Publishing work to the queues: training jobs, render requests, output jobs, capture imports, and the sweep
that recovers every kind of queued work (:data:`KINDS`) from dead workers and lost messages (API and workers;
:func:`sweep_jobs` is one round).

Only task names cross this boundary, so publishing never imports the engine.
"""

from __future__ import annotations

import logging

from celery import Celery

from app.core.celery_app import RENDER_TASK
from app.core.imports import IMPORTS
from app.core.jobstore import JOBS
from app.core.lease import WorkKind
from app.core.outputs import OUTPUTS
from app.core.settings import Settings

log = logging.getLogger(__name__)
KINDS: tuple[WorkKind, ...] = (JOBS, OUTPUTS, IMPORTS)  # every kind of queued work the sweep recovers


def send(app: Celery, kind: WorkKind, row_id: str) -> None:
    """Queue the work of row ``row_id`` of ``kind`` (the row must exist). Raises kombu errors if the broker is
    down."""
    app.send_task(kind.task, args=[row_id])


def send_render(app: Celery, request_id: str, job_id: str, request: dict, expires_s: float) -> None:
    """Queue one render; a worker that gets it after ``expires_s`` drops it (the caller has given up)."""
    app.send_task(RENDER_TASK, args=[request_id, job_id, request], expires=expires_s)


def requeue_stale(settings: Settings, app: Celery, kind: WorkKind) -> list[str]:
    """Requeue the running rows of ``kind`` whose worker died; the next worker takes each over (a training job
    resumes from its checkpoint, an output starts again from its first frame). One whose worker died
    ``max_worker_deaths`` times is failed instead (:meth:`app.core.lease.WorkKind.fail_worn_out`).

    The message is published before the row goes back to ``queued``: if publishing fails the row stays
    stale and the next sweep tries again. A worker may get the message before the row is marked; it then
    takes the stale row over itself (see :meth:`app.core.lease.WorkKind.claim`). A duplicate message is
    harmless because claims are fenced.
    """
    requeued = []
    for row in kind.stale(settings):
        if kind.fail_worn_out(settings, row):
            log.error("%s %s failed: its worker died %d times", kind.noun, row.id, row.requeues + 1)
            continue
        send(app, kind, row.id)
        requeued += kind.mark_requeued(settings, [row])
    if requeued:
        log.warning("requeued %d %s(s) whose worker stopped: %s", len(requeued), kind.noun, ", ".join(requeued))
    return requeued


def resend_lost(settings: Settings, app: Celery, kind: WorkKind) -> list[str]:
    """Send again the message of every row of ``kind`` queued ``resend_queued_after_s`` or longer since its last
    send (:meth:`app.core.lease.WorkKind.lost`: the API died between the row and the send, the broker lost it,
    or a consumer died holding it). A copy of a message that was not lost is refused by the claim's fence."""
    resent = []
    for row in kind.lost(settings):
        send(app, kind, row.id)
        if kind.mark_resent(settings, row):
            resent.append(row.id)
    if resent:
        log.warning("re-sent %d queued %s(s) no worker took: %s", len(resent), kind.noun, ", ".join(resent))
    return resent


def sweep_jobs(settings: Settings, app: Celery) -> None:
    """One round of recovery, for every kind of queued work: stale rows first, then queued ones whose message
    was lost."""
    for kind in KINDS:
        requeue_stale(settings, app, kind)
    for kind in KINDS:
        resend_lost(settings, app, kind)
