"""Starting a Celery worker for some queues (``voxnerf worker``; the embedded ones of ``voxnerf serve``)."""

from __future__ import annotations

import logging
import os
import socket

from app.core import storage
from app.core.celery_app import QUEUES, create_celery
from app.core.redact import install_log_masking
from app.core.settings import get_settings

TASK_MODULES = ("worker.tasks",)  # imported by the worker (and its pool processes) for their tasks


def worker_name(queues: list[str], embedded: bool) -> str:
    """Celery node name. With the filesystem broker it is stable per host and queue set, so a restarted
    worker takes over its predecessor's control queue instead of leaving one behind; with Redis each
    process gets its own name."""
    base = "+".join(queues)
    return f"{base}@{socket.gethostname()}" if embedded else f"{base}-{os.getpid()}@{socket.gethostname()}"


def run_worker(queues: list[str], concurrency: int) -> None:
    """Run a worker consuming ``queues`` (``train``, ``render``) with ``concurrency`` processes; blocks."""
    unknown = sorted(set(queues) - set(QUEUES))
    if not queues or unknown:
        raise ValueError(f"queues must be a non-empty subset of {list(QUEUES)}, got {queues}")
    if concurrency < 1:
        raise ValueError(f"concurrency must be >= 1, got {concurrency}")
    settings = get_settings()
    settings.make_dirs()
    storage.check_store(settings)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    install_log_masking()  # broker and storage URLs' credentials never reach a log line
    celery_app = create_celery(settings, include=TASK_MODULES, queues=queues)
    celery_app.worker_main(
        [
            "worker",
            "--queues",
            ",".join(queues),
            "--concurrency",
            str(concurrency),
            "--hostname",
            worker_name(queues, settings.embedded_broker),
            "--pool",
            "prefork",
            "--without-gossip",
            "--without-mingle",
            "--without-heartbeat",
            "--loglevel",
            "INFO",
        ]
    )
