"""``voxnerf serve``: the API and embedded workers (one ``train``, one ``render``, one ``outputs``) from one
command; ``python -m app.serve --api-only`` serves the API alone (the API container's entry).

Both refuse to listen beyond loopback without an API token (:func:`app.origin_guard.check_bind`).
SIGTERM and SIGINT both stop the server and then the workers: uvicorn catches either signal while it serves
and raises it again once it has shut down, so :func:`serve` installs handlers that only note the signal for
that moment; the workers are then stopped in the ``finally`` whichever signal it was. SIGKILL cannot be caught:
each worker watches this process and stops itself the same way when it dies (``worker.parent_watch``).
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator

import uvicorn

from app.core.celery_app import OUTPUTS_QUEUE, RENDER_QUEUE, TRAIN_QUEUE
from app.core.log_format import configure_logging
from app.core.redact import install_log_masking
from app.core.settings import get_settings
from app.main import create_app
from app.origin_guard import SERVER_OPTIONS, UnsafeBindError, check_bind

STOP_GRACE_S = 15.0
STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT)
log = logging.getLogger(__name__)


def _spawn_worker(queue: str) -> subprocess.Popen:
    """A worker process for ``queue`` in its own process group (so stopping it also stops its pool), which
    stops itself as :func:`_stop_all` would when this process dies without stopping it (SIGKILL)."""
    return subprocess.Popen(
        [sys.executable, "-m", "worker", "--queues", queue, "--concurrency", "1",
         "--exit-with-parent", str(os.getpid()), "--stop-grace-s", str(STOP_GRACE_S)],
        start_new_session=True,
    )


def _kill_group(proc: subprocess.Popen) -> None:
    """SIGKILL the process group of ``proc`` (itself and whatever it started), if any of it is left."""
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(proc.pid, signal.SIGKILL)


def _stop_all(procs: list[subprocess.Popen], grace_s: float = STOP_GRACE_S) -> None:
    """Warm shutdown of every worker at once; after ``grace_s`` kill what is left, then kill each worker's
    process group in any case so that no pool process outlives its worker (a job cut short is requeued and
    resumes from its checkpoint on the next start)."""
    for proc in procs:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + grace_s
    for proc in procs:
        try:
            proc.wait(max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            log.warning("worker %d did not stop within %.0f s: killing its process group", proc.pid, grace_s)
        _kill_group(proc)
        proc.wait()


@contextlib.contextmanager
def _signals_noted() -> Iterator[list[int]]:
    """While inside, SIGTERM and SIGINT are noted in the yielded list instead of ending the process (uvicorn
    installs its own handlers while it serves and re-raises the signal it caught once it is done)."""
    received: list[int] = []
    previous = {sig: signal.signal(sig, lambda signum, _frame: received.append(signum)) for sig in STOP_SIGNALS}
    try:
        yield received
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def serve(host: str, port: int, workers: bool = True) -> None:
    """Serve the API on ``host:port`` with embedded train, render and outputs workers (unless ``workers`` is
    False); blocks until SIGTERM or SIGINT, then stops the workers (at most ``STOP_GRACE_S``, then kills).

    Raises :class:`app.origin_guard.UnsafeBindError` before starting anything when ``host`` is not loopback
    and neither a token nor the opt-out is set."""
    settings = get_settings()
    check_bind(host, settings)
    settings.make_dirs()
    configure_logging(settings.log_format)
    install_log_masking()  # broker and storage URLs' credentials never reach a log line
    with _signals_noted() as received:
        procs = [_spawn_worker(q) for q in (TRAIN_QUEUE, RENDER_QUEUE, OUTPUTS_QUEUE)] if workers else []
        log.info("data in %s; broker %s", settings.data_dir, settings.broker_url or "embedded filesystem queue")
        try:
            if not received:  # a signal during start-up: stop at once
                # JSON logs: uvicorn's loggers get no handlers of their own and write through the root's
                logs = {"log_config": None} if settings.log_format == "json" else {}
                uvicorn.run(create_app(settings), host=host, port=port, **SERVER_OPTIONS, **logs)
        finally:
            if received:
                log.info("received %s: stopping the workers", signal.Signals(received[0]).name)
            _stop_all(procs)


def main(argv: list[str] | None = None) -> int:
    """``python -m app.serve [--api-only] [--host H] [--port P]``; a refused bind is one line on stderr, 2."""
    parser = argparse.ArgumentParser(prog="python -m app.serve", description=__doc__.splitlines()[0])
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=8000)
    parser.add_argument("--api-only", action="store_true", help="no embedded workers")
    args = parser.parse_args(argv)
    try:
        serve(args.host, args.port, workers=not args.api_only)
    except UnsafeBindError as err:
        print(f"voxnerf: error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
