"""Publishing work to the queues: training jobs, render requests, output jobs, recovery of stale jobs and of
lost messages (API and workers; :func:`sweep_jobs` is one round).

Only task names cross this boundary, so publishing never imports the engine.
"""

from __future__ import annotations

import logging

from celery import Celery

from app.core import jobstore, outputs
from app.core.celery_app import OUTPUT_TASK, RENDER_TASK, TRAIN_TASK
from app.core.models import JobRow, OutputRow
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
    as :func:`requeue_stale_jobs` does for training; one whose worker died ``max_worker_deaths`` times is
    failed instead, naming why (it may be what kills its workers)."""
    requeued = []
    for row in outputs.stale_outputs(settings):
        if jobstore.fail_worn_out(settings, OutputRow, row):
            continue
        send_output(app, row.id)
        requeued += outputs.mark_requeued(settings, [row])
    if requeued:
        log.warning("requeued %d output job(s) whose worker stopped: %s", len(requeued), ", ".join(requeued))
    return requeued


def requeue_stale_jobs(settings: Settings, app: Celery) -> list[str]:
    """Requeue running jobs whose worker died; the next worker resumes each from its checkpoint. One whose
    worker died ``max_worker_deaths`` times is failed instead (:func:`app.core.jobstore.fail_worn_out`).

    The message is published before the row goes back to ``queued``: if publishing fails the job stays
    stale and the next sweep tries again. A worker may get the message before the row is marked; it then
    takes the stale job over itself (see :func:`app.core.jobstore.claim_job`). A duplicate message is harmless
    because claims are fenced.
    """
    requeued = []
    for job in jobstore.stale_jobs(settings):
        if jobstore.fail_worn_out(settings, JobRow, job):
            log.error("job %s failed: its worker died %d times", job.id, job.requeues + 1)
            continue
        send_train(app, job.id)
        requeued += jobstore.mark_requeued(settings, [job])
    if requeued:
        log.warning("requeued %d job(s) whose worker stopped: %s", len(requeued), ", ".join(requeued))
    return requeued


def resend_lost_jobs(settings: Settings, app: Celery) -> list[str]:
    """Send again the message of every job queued ``resend_queued_after_s`` or longer since its last send
    (:func:`app.core.jobstore.lost_jobs`: the API died between the row and the send, the broker lost it, or
    a consumer died holding it). A copy of a message that was not lost is refused by the claim's fence."""
    resent = []
    for job in jobstore.lost_jobs(settings):
        send_train(app, job.id)
        if jobstore.mark_resent(settings, job):
            resent.append(job.id)
    if resent:
        log.warning("re-sent %d queued job(s) no worker took: %s", len(resent), ", ".join(resent))
    return resent


def sweep_jobs(settings: Settings, app: Celery) -> None:
    """One round of recovery: stale training jobs, stale output jobs, queued jobs whose message was lost."""
    requeue_stale_jobs(settings, app)
    requeue_stale_outputs(settings, app)
    resend_lost_jobs(settings, app)
