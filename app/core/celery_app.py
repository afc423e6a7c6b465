"""Task and queue names, and the Celery app factory, configured from :mod:`app.core.settings`.

Embedded default: ``broker_url = "filesystem://"`` served by :mod:`app.core.broker` in ``<data_dir>/broker``,
which works across processes on one host with no server. ``VOXNERF_BROKER_URL=redis://...`` selects Redis.
No Celery result backend is used: job state lives in the job store and render results come back through
Redis, or as files in ``<data_dir>/render-results`` in embedded mode (see :mod:`app.core.render_results`).

Nothing is built at import time: the API builds its app in ``create_app``, a worker process in
``worker.run`` (with its tasks), and :func:`get_celery` builds this process's app from the environment's
settings on first use.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import lru_cache

from celery import Celery

from app.core.settings import Settings, get_settings

TRAIN_TASK = "voxnerf.train"
RENDER_TASK = "voxnerf.inference.render"
OUTPUT_TASK = "voxnerf.output"
IMPORT_TASK = "voxnerf.import"  # capture imports (worker/imports.py): heavy CPU work, taken by the train workers
TRAIN_QUEUE = "train"
RENDER_QUEUE = "render"
OUTPUTS_QUEUE = "outputs"  # output jobs: videos, meshes, point clouds (worker/outputs.py)
QUEUES = (TRAIN_QUEUE, RENDER_QUEUE, OUTPUTS_QUEUE)
DEVICE_REPORT = "voxnerf_device"  # remote-control command: a worker's device and its memory (worker/device_report.py)


def create_celery(settings: Settings, include: Sequence[str] = (), queues: Sequence[str] = ()) -> Celery:
    """A Celery app for ``settings``: JSON messages, train/render/outputs routing, prefetch 1, no result backend.

    ``include``: modules whose tasks a worker runs (the API only publishes by task name and needs none);
    ``queues``: those it consumes (they choose its polling interval on the embedded broker).
    """
    app = Celery("voxnerf", include=list(include))
    app.conf.update(
        task_serializer="json",
        accept_content=["json"],
        task_ignore_result=True,
        task_routes={
            TRAIN_TASK: {"queue": TRAIN_QUEUE},
            RENDER_TASK: {"queue": RENDER_QUEUE},
            OUTPUT_TASK: {"queue": OUTPUTS_QUEUE},
            IMPORT_TASK: {"queue": TRAIN_QUEUE},
        },
        task_default_queue=TRAIN_QUEUE,
        worker_prefetch_multiplier=1,
        worker_lost_wait=settings.worker_lost_wait_s,
        worker_send_task_events=False,
        broker_connection_retry_on_startup=True,
        worker_hijack_root_logger=False,
    )
    if settings.embedded_broker:
        queue = str(settings.broker_dir / "queue")
        app.conf.update(
            broker_url="filesystem://",
            broker_transport="app.core.broker:Transport",
            broker_transport_options={
                "data_folder_in": queue,
                "data_folder_out": queue,
                "control_folder": str(settings.broker_dir / "control"),
                "claimed_folder": str(settings.broker_dir / "claimed"),
                "polling_interval": polling_interval_s(settings, queues),
            },
        )
    else:
        app.conf.update(broker_url=settings.broker_url)
    return app


@lru_cache(maxsize=1)
def get_celery() -> Celery:
    """This process's publishing app for the environment's settings, built on first use (health checks,
    scripts); the API keeps its own in ``app.state.celery``."""
    return create_celery(get_settings())


def polling_interval_s(settings: Settings, queues: Sequence[str]) -> float:
    """How often a worker consuming ``queues`` looks into the embedded filesystem queue while it runs a task (an
    idle one waits on the folder's watch, app/core/broker.py): the render interval when it serves renders (a render
    queued behind another waits that long after it), else the broker's."""
    if RENDER_QUEUE in queues:
        return min(settings.render_polling_interval_s, settings.broker_polling_interval_s)
    return settings.broker_polling_interval_s
