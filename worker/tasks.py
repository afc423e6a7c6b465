"""The worker's Celery tasks, one per kind of queued work, under the names the API sends them by
(:mod:`app.core.celery_app`): train a job (queue ``train``), import a capture (queue ``train``), render a pose
(queue ``render``), make a video, mesh or point cloud (queue ``outputs``).

A task is the Celery side of its work only. The leased kinds (jobs, imports, outputs) are held with
:func:`worker.lease.hold`: claimed in the job store, fenced by their attempt number, their lease renewed from a
side thread that also picks up cancellation. ``acks_late`` + ``reject_on_worker_lost`` give the message back to
the broker if the process dies (the Celery main process notes the death on the row first,
:class:`worker.lease.DeathNotingRequest`); the dispatcher's sweep covers the rest, and fails work whose worker died
``max_worker_deaths`` times.

The work itself is in the module of its kind (:data:`WORK_MODULES`), which loads the engine (torch, about 4 s of
CPU): :mod:`worker.training`, :mod:`worker.imports`, :mod:`worker.rendering`, :mod:`worker.outputs`. This module
loads none of them: a task imports its kind's module when it runs, unless the worker loaded its queues' modules
when it started (``worker_preload``, the default, :func:`preload_work`), so the first task starts at once.

The tasks are Celery *shared* tasks: no Celery app is built when this module is imported; they bind to the app
:func:`worker.run.run_worker` builds (``app.core.celery_app.create_celery``).
"""

from __future__ import annotations

import importlib
import logging
from collections.abc import Sequence

from celery import shared_task
from celery.signals import worker_ready, worker_shutting_down

from app.core import folder_watch
from app.core.celery_app import OUTPUTS_QUEUE, RENDER_QUEUE, RENDER_TASK, TRAIN_QUEUE
from app.core.dispatch import sweep_jobs
from app.core.imports import IMPORTS
from app.core.jobstore import JOBS
from app.core.outputs import OUTPUTS
from app.core.settings import get_settings
from worker.lease import hold, leased_task

log = logging.getLogger(__name__)

# The modules of the work each queue's tasks do; each loads the engine.
WORK_MODULES: dict[str, tuple[str, ...]] = {
    TRAIN_QUEUE: ("worker.training", "worker.imports"),
    RENDER_QUEUE: ("worker.rendering",),
    OUTPUTS_QUEUE: ("worker.outputs",),
}


def preload_work(queues: Sequence[str]) -> list[str]:
    """Import the work modules of ``queues`` (and with them the engine) now; their names."""
    names = [name for queue in queues for name in WORK_MODULES[queue]]
    for name in names:
        importlib.import_module(name)
    return names


@leased_task(JOBS)
def train_job(job_id: str) -> None:
    """Train job ``job_id`` to a final state (succeeded, cancelled, failed) unless another worker owns it."""
    from worker.training import train_claimed

    hold(get_settings(), JOBS, job_id, train_claimed)


@leased_task(IMPORTS)
def run_capture_import(import_id: str) -> None:
    """Import capture ``import_id`` to a final state (succeeded, cancelled, failed) unless another worker owns
    it."""
    from worker.imports import import_capture, remove_capture

    hold(get_settings(), IMPORTS, import_id, import_capture, ending=remove_capture)


@leased_task(OUTPUTS)
def make_output(output_id: str) -> None:
    """Make output ``output_id`` to a final state (succeeded, cancelled, failed) unless another worker owns it."""
    from worker.outputs import produce, remove_unfinished

    hold(get_settings(), OUTPUTS, output_id, produce, ending=remove_unfinished)


@shared_task(name=RENDER_TASK)
def render_pose(request_id: str, job_id: str, request: dict, deadline: float | None = None,
                checkpoint_iteration: int | None = None) -> None:
    """Render one request for the waiting API (:func:`worker.rendering.render_and_deliver`): ``deadline`` (a Unix
    time) is when the API gives up on it, ``checkpoint_iteration`` the job's last checkpoint when it was sent."""
    from worker.rendering import render_and_deliver

    render_and_deliver(request_id, job_id, request, deadline, checkpoint_iteration)


@worker_ready.connect
def _recover_stale_jobs(sender=None, **_) -> None:
    """At worker start-up, requeue jobs whose previous worker died and re-send lost messages (the API also
    does so periodically)."""
    try:
        sweep_jobs(get_settings(), sender.app)
    except Exception:
        log.exception("start-up recovery of stale jobs failed")


@worker_shutting_down.connect
def _wake_idle_consumer(**_) -> None:
    """On the embedded broker an idle worker waits on the queue folder's watch for up to 2 s at a time, and Celery
    reads its stop flag only between waits: end the wait, so a stop request is seen at once (a no-op on Redis)."""
    folder_watch.wake_all()
