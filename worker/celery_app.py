"""The Celery application, configured from :mod:`app.settings` (one place for broker and queues).

Embedded default: ``broker_url = "filesystem://"`` served by :mod:`worker.broker` in ``<data_dir>/broker``,
which works across processes on one host with no server. ``VOXNERF_BROKER_URL=redis://...`` selects Redis.
No Celery result backend is used: job state lives in the job store and render results come back through
Redis, or as files in ``<data_dir>/render-results`` in embedded mode (see :mod:`worker.render_results`).
"""

from __future__ import annotations

from celery import Celery

from app.settings import Settings, get_settings

TRAIN_TASK = "voxnerf.train"
RENDER_TASK = "voxnerf.render"
TRAIN_QUEUE = "train"
RENDER_QUEUE = "render"


def create_celery(settings: Settings) -> Celery:
    """A Celery app for ``settings``: JSON messages, train/render routing, prefetch 1, no result backend."""
    app = Celery("voxnerf", include=["worker.tasks"])
    app.conf.update(
        task_serializer="json",
        accept_content=["json"],
        task_ignore_result=True,
        task_routes={TRAIN_TASK: {"queue": TRAIN_QUEUE}, RENDER_TASK: {"queue": RENDER_QUEUE}},
        task_default_queue=TRAIN_QUEUE,
        worker_prefetch_multiplier=1,
        worker_send_task_events=False,
        broker_connection_retry_on_startup=True,
        worker_hijack_root_logger=False,
    )
    if settings.embedded_broker:
        queue = str(settings.broker_dir / "queue")
        app.conf.update(
            broker_url="filesystem://",
            broker_transport="worker.broker:Transport",
            broker_transport_options={
                "data_folder_in": queue,
                "data_folder_out": queue,
                "control_folder": str(settings.broker_dir / "control"),
                "claimed_folder": str(settings.broker_dir / "claimed"),
                "polling_interval": settings.broker_polling_interval_s,
            },
        )
    else:
        app.conf.update(broker_url=settings.broker_url)
    return app


celery_app = create_celery(get_settings())
