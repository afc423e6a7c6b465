"""``voxnerf serve``: the API and embedded workers (one ``train``, one ``render``, one ``outputs``) from one
command."""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import time

import uvicorn

from app.core.celery_app import OUTPUTS_QUEUE, RENDER_QUEUE, TRAIN_QUEUE
from app.core.settings import get_settings
from app.main import create_app

STOP_GRACE_S = 15.0
log = logging.getLogger(__name__)


def _spawn_worker(queue: str) -> subprocess.Popen:
    """A worker process for ``queue`` in its own process group (so stopping it also stops its pool)."""
    return subprocess.Popen(
        [sys.executable, "-m", "worker", "--queues", queue, "--concurrency", "1"], start_new_session=True
    )


def _stop_all(procs: list[subprocess.Popen]) -> None:
    """Warm shutdown of every worker at once; after STOP_GRACE_S kill what is left, pool processes included
    (a job cut short is requeued and resumes from its checkpoint on the next start)."""
    for proc in procs:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + STOP_GRACE_S
    for proc in procs:
        try:
            proc.wait(max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def serve(host: str, port: int) -> None:
    """Serve the API on ``host:port`` with embedded train, render and outputs workers; blocks until stopped."""
    settings = get_settings()
    settings.make_dirs()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    workers = [_spawn_worker(TRAIN_QUEUE), _spawn_worker(RENDER_QUEUE), _spawn_worker(OUTPUTS_QUEUE)]
    log.info("data in %s; broker %s", settings.data_dir, settings.broker_url or "embedded filesystem queue")
    try:
        uvicorn.run(create_app(settings), host=host, port=port)
    finally:
        _stop_all(workers)
