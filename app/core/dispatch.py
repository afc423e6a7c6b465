"""Publishing work to the queues: training jobs, render requests, output jobs, stale-job recovery (API and
workers).

Only task names cross this boundary, so publishing never imports the engine.
"""

from __future__ import annotations

import logging

from celery import Celery

from app.core import jobstore, outputs
from app.core.celery_app import OUTPUT_TASK, RENDER_TASK, TRAIN_TASK
from app.core.settings import Settings

log = logging.getLogger(__name__)


def send_train(app: Celery, job_id: str) -> None:
    """Queue the training of ``job_id`` (its row must exist). Raises kombu errors if the broker is down."""
    app.send_task(TRAIN_TASK, args=[job_id])


def send_render(app: Celery, request_id: str, job_id: str, request: dict, expires_s: float) -> None:
    """Queue one render; a worker that gets it after ``expires_s`` drops it (the caller has given up)."""
    app.send_task(RENDER_TASK, args=[request_id, job_id, request], expires=expires_s)


def send_output(app: Celery, output_id: str) -> None:
    """Queue output job ``output_id`` (its row must exist). Raises kombu errors if the broker is down."""
    app.send_task(OUTPUT_TASK, args=[output_id])


def requeue_stale_outputs(settings: Settings, app: Celery) -> list[str]:
    """Requeue running output jobs whose worker died (the next worker starts them again from the first frame),
    as :func:`requeue_stale_jobs` does for training; one requeued :data:`app.core.outputs.MAX_REQUEUES` times
    already is failed instead, naming why (it may be what kills its workers)."""
    requeued = []
    for row in outputs.stale_outputs(settings):
        if row.requeues >= outputs.MAX_REQUEUES:
            outputs.fail_output(settings, row.id, f"its worker stopped {row.requeues + 1} times (killed, or out of "
                                "memory?); not requeued again")
            continue
        send_output(app, row.id)
        requeued += outputs.mark_requeued(settings, [row])
    if requeued:
        log.warning("requeued %d output job(s) whose worker stopped: %s", len(requeued), ", ".join(requeued))
    return requeued


def requeue_stale_jobs(settings: Settings, app: Celery) -> list[str]:
    """Requeue running jobs whose worker died; the next worker resumes each from its checkpoint.

    The message is published before the row goes back to ``queued``: if publishing fails the job stays
    stale and the next sweep tries again. A worker may get the message before the row is marked; it then
    takes the stale job over itself (see :func:`app.core.jobstore.claim_job`). A duplicate message is harmless
    because claims are fenced.
    """
    requeued = []
    for job in jobstore.stale_jobs(settings):
        send_train(app, job.id)
        requeued += jobstore.mark_requeued(settings, [job])
    if requeued:
        log.warning("requeued %d job(s) whose worker stopped: %s", len(requeued), ", ".join(requeued))
    return requeued
