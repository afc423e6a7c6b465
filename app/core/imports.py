"""Capture imports: raw captures (a ROS bag...) that a worker turns into a scene, on the lease lifecycle every
kind of queued work shares (:mod:`app.core.lease`: claim with a fence, lease renewal, stages and progress,
cancel, finish, stale sweep, re-send of a lost message, worker deaths). :data:`IMPORTS` is their kind.

``POST /scenes`` stores an upload whose layout the engine imports slowly (:data:`QUEUED_LAYOUTS`: the importer
reads a whole robot log, or solves structure from motion) in ``<imports_dir>/<id>`` and queues its import
instead of importing it in the request; the train workers take imports (heavy CPU work like training) and the
scene exists once its import has succeeded (``scene_id``). A claim starts the import again from the raw
capture, which stays until the import ends.
"""

from __future__ import annotations

import shutil
import time
from pathlib import Path

from app.core import tokens
from app.core.celery_app import IMPORT_TASK
from app.core.db import session_scope
from app.core.jobstore import new_id
from app.core.lease import WorkKind
from app.core.models import ImportRow
from app.core.scene_store import tree_size
from app.core.settings import Settings
from app.core.tokens import Principal
from voxnerf.data.importers import QUEUED_LAYOUTS

__all__ = ["IMPORTS", "QUEUED_LAYOUTS", "create_import", "raw_dir", "remove_raw"]


def _progress(settings: Settings, import_id: str, stage: str, progress: float, eta_s: float | None,
              step: str | None = None) -> dict:
    return {"stage": stage, "progress": min(max(float(progress), 0.0), 1.0), "eta_s": eta_s, "step": step}


IMPORTS = WorkKind(
    name="import",
    noun="capture import",
    table=ImportRow,
    task=IMPORT_TASK,
    # a claim starts the import again from the raw capture
    claimed=lambda row, now: {"started_at": row.started_at or now, "stage": "starting", "progress": 0.0},
    progress=_progress,
    staged=True,
)
"""Capture imports' lease lifecycle: ``IMPORTS.get``, ``claim``, ``record_progress(settings, id, attempt, stage,
progress, eta_s[, step])``, ``finish``, ``request_cancel``..."""


def raw_dir(settings: Settings, import_id: str) -> Path:
    """Where an import's raw capture waits: ``<imports_dir>/<id>``."""
    return settings.imports_dir / import_id


def remove_raw(settings: Settings, import_id: str) -> None:
    shutil.rmtree(raw_dir(settings, import_id), ignore_errors=True)


def create_import(settings: Settings, staged: Path, name: str, layout: str, params: dict,
                  principal: Principal | None = None) -> ImportRow:
    """A queued import of the raw capture at ``staged`` (a file or folder on the data directory's filesystem,
    moved into :func:`raw_dir`), made by ``principal`` (None: outside the API). Raises QueueFull when
    ``max_queued_jobs`` imports are queued already, or as many as the principal's own limit allows (counted per kind
    of work), ValueError for a layout that is not imported in a queue."""
    if layout not in QUEUED_LAYOUTS:
        raise ValueError(f"layout {layout!r} is imported on upload, not queued")
    row = IMPORTS.new_row(new_id(), name=name, layout=layout, params=params, size_bytes=tree_size(staged),
                          stage="queued", progress=0.0, created_by=principal and principal.name)
    settings.imports_dir.mkdir(parents=True, exist_ok=True)
    with session_scope(settings) as session:
        session.add(row)
        session.flush()
        IMPORTS.refuse_beyond(session, settings.max_queued_jobs, "max_queued_jobs",
                              principal and tokens.queue_quota(settings, principal))
        target = raw_dir(settings, row.id)
        target.mkdir()
        staged.replace(target / staged.name)
    return row


def elapsed_eta(started: float, progress: float) -> float | None:
    """Seconds left at ``progress`` (0..1) of work started at ``started`` (``time.monotonic``), linearly."""
    if progress <= 0.0:
        return None
    return (time.monotonic() - started) * (1.0 - progress) / progress
