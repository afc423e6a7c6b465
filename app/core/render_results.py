"""Render results travel from the render worker back to the API process that asked for them.

With Redis as the broker (``broker_url`` set) the worker RPUSHes the outcome to
``voxnerf:render:<request id>`` with an expiry of ``render_timeout_s + 60`` s (an outcome nobody collects goes
away by itself) and the API waits for it with BLPOP (in slices of at most a second), so an API and its render
workers need no directory in common: they may run on different machines with their own ``data_dir``. One
list item carries the JSON header (status, media type or error detail), a newline, then the image bytes.

With the embedded filesystem broker the worker writes ``<request_id>.out`` (the image bytes, when it
succeeded) and then ``<request_id>.json`` (the header) under ``<data_dir>/render-results``, each atomically;
the API waits for the ``.json`` marker, reads both and deletes them, and its sweep removes what nobody
collected (:func:`remove_old_outcomes`).

Neither mode needs a Celery result backend, and both carry images of any size.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import redis

from app.core.folder_watch import FolderWatch
from app.core.settings import Settings
from voxnerf.data.image_io import write_atomic

POLL_INTERVAL_S = 0.005
REDIS_KEY_PREFIX = "voxnerf:render:"
REDIS_EXPIRY_MARGIN_S = 60  # an uncollected outcome outlives the API's wait by this much
BLPOP_SLICE_S = 1.0  # one BLPOP waits at most this long: well under redis-py's 5 s socket read timeout
BLPOP_MIN_S = 0.01  # and at least this long (a BLPOP timeout of 0 would block forever)


@dataclass(frozen=True)
class RenderOutcome:
    status: int  # HTTP status the API answers with: 200, or 4xx/5xx with ``detail``
    media_type: str | None = None
    data: bytes | None = None
    detail: str | None = None
    iteration: int | None = None  # the training iteration of the checkpoint that rendered

    def header(self) -> bytes:
        """The JSON header (no image bytes), one line."""
        meta = {"status": self.status, "media_type": self.media_type, "detail": self.detail,
                "iteration": self.iteration}
        return json.dumps(meta).encode()

    @classmethod
    def from_parts(cls, header: bytes, data: bytes | None) -> RenderOutcome:
        meta = json.loads(header)
        return cls(meta["status"], meta.get("media_type"), data, meta.get("detail"), meta.get("iteration"))


def redis_key(request_id: str) -> str:
    return f"{REDIS_KEY_PREFIX}{request_id}"


@lru_cache(maxsize=4)
def _redis(url: str) -> redis.Redis:
    """One thread-safe client (and connection pool) per broker URL and process."""
    return redis.Redis.from_url(url)


def deliver_outcome(settings: Settings, request_id: str, outcome: RenderOutcome) -> None:
    """Hand ``outcome`` to the API waiting on ``request_id`` (through Redis, or files when embedded)."""
    if settings.embedded_broker:
        write_outcome(settings.render_results_dir, request_id, outcome)
        return
    key = redis_key(request_id)
    payload = outcome.header() + b"\n" + (outcome.data or b"")
    expiry_s = int(settings.render_timeout_s) + REDIS_EXPIRY_MARGIN_S
    with _redis(settings.broker_url).pipeline(transaction=True) as pipe:
        pipe.rpush(key, payload)
        pipe.expire(key, expiry_s)
        pipe.execute()


def receive_outcome(settings: Settings, request_id: str, timeout_s: float) -> RenderOutcome | None:
    """Block until the worker's outcome for ``request_id`` arrives (consuming it); None on timeout.

    Raises ``redis.RedisError`` when Redis is unreachable while waiting.
    """
    if settings.embedded_broker:
        return wait_outcome(settings.render_results_dir, request_id, timeout_s)
    client, key = _redis(settings.broker_url), redis_key(request_id)
    deadline = time.monotonic() + timeout_s
    while (remaining := deadline - time.monotonic()) > 0:
        popped = client.blpop([key], timeout=min(max(remaining, BLPOP_MIN_S), BLPOP_SLICE_S))
        if popped is not None:
            header, _, data = popped[1].partition(b"\n")
            return RenderOutcome.from_parts(header, data or None)
    return None


def write_outcome(results_dir: Path, request_id: str, outcome: RenderOutcome) -> None:
    """Embedded mode: the image bytes, then the header marker, each written atomically."""
    if outcome.data is not None:
        write_atomic(results_dir / f"{request_id}.out", outcome.data)
    write_atomic(results_dir / f"{request_id}.json", outcome.header())


def wait_outcome(results_dir: Path, request_id: str, timeout_s: float) -> RenderOutcome | None:
    """Embedded mode: wait until the outcome's marker is there (then remove both files); None on timeout. The wait
    sleeps on a watch of ``results_dir`` (any outcome written there wakes it to look), or polls every
    ``POLL_INTERVAL_S`` without inotify."""
    marker = results_dir / f"{request_id}.json"
    data_path = results_dir / f"{request_id}.out"
    deadline = time.monotonic() + timeout_s
    watch = FolderWatch.open(results_dir)  # before the first look: an outcome written after it wakes the wait
    try:
        while not marker.exists():
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            if watch is None:
                time.sleep(min(POLL_INTERVAL_S, left))
            else:
                watch.wait(left)
    finally:
        if watch is not None:
            watch.close()
    header = marker.read_bytes()
    data = data_path.read_bytes() if data_path.exists() else None
    marker.unlink()
    data_path.unlink(missing_ok=True)
    return RenderOutcome.from_parts(header, data)


def remove_old_outcomes(results_dir: Path, older_than_s: float) -> int:
    """Embedded mode: delete outcomes nobody picked up (their request timed out); returns how many went."""
    cutoff = time.time() - older_than_s
    removed = 0
    for path in results_dir.iterdir():
        try:
            if path.stat().st_mtime < cutoff:
                path.unlink()
                removed += 1
        except FileNotFoundError:
            continue
    return removed
