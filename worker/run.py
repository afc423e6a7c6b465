"""Starting a Celery worker for some queues (``voxnerf worker``; the embedded ones of ``voxnerf serve``)."""

from __future__ import annotations

import logging
import os
import socket
import sys
from collections.abc import MutableMapping, Sequence

from app.core import storage
from app.core.celery_app import QUEUES, TRAIN_QUEUE, create_celery
from app.core.log_format import configure_logging
from app.core.redact import install_log_masking
from app.core.settings import get_settings
from worker import (
    device_report,  # noqa: F401  (registers the remote-control command GET /metrics asks)
    json_logs,
)
from worker.tasks import preload_work

# imported by the worker for its tasks (their work's modules load with the first task, or at start: preload_work)
TASK_MODULES = ("worker.tasks",)
log = logging.getLogger(__name__)


def openmp_wait_policy(queues: Sequence[str]) -> str | None:
    """How the OpenMP threads of a worker consuming ``queues`` wait at the end of a parallel region: None (the
    runtime's default, as ``voxnerf train`` runs: they spin briefly, then sleep) for a worker that trains,
    ``PASSIVE`` (they sleep at once) for a render or outputs worker.

    A training step is hundreds of short parallel regions (the compiled step's fused loops, ATen's operations):
    with ``PASSIVE`` each one ends in a sleep and starts with a wake-up, and a job trained several times slower
    than the CLI. A render worker shares the cores with a training job: with spinning threads its views wait
    for a sibling thread the scheduler has taken the core from. docs/performance.md ("OpenMP threads in the
    workers") says why; benchmarks/results/service_speed/notes.md holds the measurements.
    """
    return None if TRAIN_QUEUE in queues else "PASSIVE"


def set_openmp_wait_policy(queues: Sequence[str], environ: MutableMapping[str, str] | None = None) -> str | None:
    """Set ``OMP_WAIT_POLICY`` for ``queues`` (:func:`openmp_wait_policy`) unless the environment sets it; the
    policy the process runs with (None: the runtime's default). It must run before torch loads (OpenMP reads
    it once, when its runtime loads; the pool processes, forked later, inherit it): a warning says when torch
    has already loaded."""
    env = os.environ if environ is None else environ
    wanted = openmp_wait_policy(queues)
    if "OMP_WAIT_POLICY" not in env and wanted is not None:
        if "torch" in sys.modules:
            log.warning("torch loaded before the worker set OMP_WAIT_POLICY=%s: its OpenMP threads keep the "
                        "policy they loaded with", wanted)
        env["OMP_WAIT_POLICY"] = wanted
    return env.get("OMP_WAIT_POLICY")


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
    configure_logging(settings.log_format)
    if settings.log_format == "json":
        json_logs.install()
    policy = set_openmp_wait_policy(queues)  # before the work's modules load torch
    log.info("OpenMP wait policy %s", policy or "default (as voxnerf train)")
    if settings.worker_preload:  # in this process, before the pool's processes fork: they start with it
        log.info("loaded %s", ", ".join(preload_work(queues)))
    settings.make_dirs()
    storage.check_store(settings)
    install_log_masking()  # broker and storage URLs' credentials never reach a log line
    celery_app = create_celery(settings, include=TASK_MODULES, queues=queues)
    celery_app.worker_main(
        [
            *(["--quiet"] if settings.log_format == "json" else []),  # no start-up banner: it is no log record
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
