"""Publishing work to the queues: training jobs, render requests, output jobs, capture imports, and the sweep
that recovers every kind of queued work (:data:`KINDS`) from dead workers and lost messages (API and workers;
:func:`sweep_jobs` is one round).

A queued row has at most one message waiting in the broker: the sweep sends a row's message again only when
the broker no longer holds it (:func:`waiting_row_ids` reads the queue of the embedded filesystem broker or of
Redis), so a row queued behind a long job keeps the one message it was sent instead of gathering a copy every
``resend_queued_after_s``. Only a broker whose queue cannot be read (neither of those) gets a copy per period.

Only task names cross this boundary, so publishing never imports the engine.
"""

from __future__ import annotations

import base64
import json
import logging
import time
from urllib.parse import urlparse

from celery import Celery

from app.core.broker import waiting_payloads
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


def send_render(app: Celery, request_id: str, job_id: str, request: dict, expires_s: float,
                checkpoint_iteration: int | None = None) -> None:
    """Queue one render; a worker that gets it after ``expires_s`` drops it, and one that is still rendering it
    then stops (its ``deadline``, a Unix time: the caller has given up). ``checkpoint_iteration``: the job's last
    checkpoint as its row says (a worker whose cached checkpoint is older fetches the run again from an object
    store)."""
    kwargs = {"deadline": time.time() + expires_s, "checkpoint_iteration": checkpoint_iteration}
    app.send_task(RENDER_TASK, args=[request_id, job_id, request], kwargs=kwargs, expires=expires_s)


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


def _first_arg(payload: dict) -> str | None:
    """The first argument of a Celery message (protocol 2: the body is ``[args, kwargs, embed]``, base64 when the
    message says so): the row id of a job's or an output's message; None for a message of another shape."""
    try:
        body = payload["body"]
        if payload.get("properties", {}).get("body_encoding") == "base64":
            body = base64.b64decode(body)
        args = json.loads(body)[0]
        return args[0] if args and isinstance(args[0], str) else None
    except (KeyError, IndexError, TypeError, ValueError):
        return None


def _redis_payloads(app: Celery, queue: str) -> list[dict]:
    """The messages waiting in Redis list ``queue`` (and its priority lists, kombu's names for them)."""
    with app.connection_for_read() as connection:
        channel = connection.default_channel
        keys = dict.fromkeys(channel._q_for_pri(queue, priority) for priority in channel.priority_steps)
        raw = [message for key in keys for message in channel.client.lrange(key, 0, -1)]
    payloads = []
    for message in raw:
        try:
            payloads.append(json.loads(message))
        except ValueError:
            continue
    return payloads


def waiting_messages(settings: Settings, app: Celery, queue: str) -> list[dict] | None:
    """The messages (kombu payloads) waiting in ``queue``, not yet taken by a consumer; None when the broker's
    queue cannot be read (a broker other than the embedded one and Redis)."""
    if settings.embedded_broker:
        return waiting_payloads(settings.broker_dir / "queue", queue)
    if urlparse(settings.broker_url).scheme in ("redis", "rediss"):
        return _redis_payloads(app, queue)
    return None


def waiting_row_ids(settings: Settings, app: Celery, queue: str) -> set[str] | None:
    """The row ids whose message waits in ``queue`` (:func:`waiting_messages`); None when it cannot be read."""
    payloads = waiting_messages(settings, app, queue)
    if payloads is None:
        return None
    return {row_id for row_id in map(_first_arg, payloads) if row_id is not None}


def resend_lost(settings: Settings, app: Celery, kind: WorkKind) -> list[str]:
    """Send again the message of every row of ``kind`` queued ``resend_queued_after_s`` or longer since its last
    send (:meth:`app.core.lease.WorkKind.lost`: the API died between the row and the send, the broker lost it,
    or a consumer died holding it), unless the broker still holds it (:func:`waiting_row_ids`: the row waits its
    turn, and is looked at again ``resend_queued_after_s`` later). A copy of a message that was not lost is
    refused by the claim's fence."""
    lost = kind.lost(settings)
    if not lost:
        return []
    waiting = waiting_row_ids(settings, app, app.amqp.router.route({}, kind.task)["queue"].name)
    resent = []
    for row in lost:
        if waiting is not None and row.id in waiting:
            kind.mark_resent(settings, row)  # its one message waits: looked at again a period later
            continue
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
