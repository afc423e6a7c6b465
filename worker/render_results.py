"""Render results travel from the render worker to the API as files in ``<data_dir>/render-results``.

The worker writes ``<request_id>.out`` (the image bytes, when it succeeded) and then ``<request_id>.json``
(status, media type or error detail), each atomically; the API waits for the ``.json`` marker, reads both and
deletes them. This works unchanged with the filesystem broker and with Redis, needs no result backend, and
carries images of any size.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

from voxnerf.image_io import write_atomic

POLL_INTERVAL_S = 0.005


@dataclass(frozen=True)
class RenderOutcome:
    status: int  # HTTP status the API answers with: 200, or 4xx/5xx with ``detail``
    media_type: str | None = None
    data: bytes | None = None
    detail: str | None = None


def write_outcome(results_dir: Path, request_id: str, outcome: RenderOutcome) -> None:
    if outcome.data is not None:
        write_atomic(results_dir / f"{request_id}.out", outcome.data)
    meta = {"status": outcome.status, "media_type": outcome.media_type, "detail": outcome.detail}
    write_atomic(results_dir / f"{request_id}.json", json.dumps(meta).encode())


def wait_outcome(results_dir: Path, request_id: str, timeout_s: float) -> RenderOutcome | None:
    """Block until the worker's outcome for ``request_id`` is there (then remove it); None on timeout."""
    marker = results_dir / f"{request_id}.json"
    data_path = results_dir / f"{request_id}.out"
    deadline = time.monotonic() + timeout_s
    while not marker.exists():
        if time.monotonic() > deadline:
            return None
        time.sleep(POLL_INTERVAL_S)
    meta = json.loads(marker.read_text())
    data = data_path.read_bytes() if data_path.exists() else None
    marker.unlink()
    data_path.unlink(missing_ok=True)
    return RenderOutcome(meta["status"], meta.get("media_type"), data, meta.get("detail"))


def remove_old_outcomes(results_dir: Path, older_than_s: float) -> int:
    """Delete outcomes nobody picked up (their request timed out); returns how many files went."""
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
