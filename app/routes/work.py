"""What the routes of every kind of queued work share (training jobs: :mod:`app.routes.jobs`, output jobs:
:mod:`app.routes.outputs`): the row or a 404, and a cancel request's answer. Their lifecycle is
:mod:`app.core.lease`'s."""

from __future__ import annotations

from typing import Any

from fastapi import HTTPException

from app.core.lease import WorkKind
from app.core.settings import Settings


def found(settings: Settings, kind: WorkKind, row_id: str) -> Any:
    """The row ``row_id`` of ``kind``; 404 naming it when there is none."""
    row = kind.get(settings, row_id)
    if row is None:
        raise HTTPException(404, f"no {kind.name} {row_id}")
    return row


def cancel(settings: Settings, kind: WorkKind, row_id: str) -> Any:
    """Cancel row ``row_id`` of ``kind`` (a queued one at once, a running one when its worker next reads the
    flag); the row as it is now. 404 for an unknown row, 409 for one that has already succeeded or failed (a
    cancelled one is answered as it is)."""
    found(settings, kind, row_id)
    row = kind.request_cancel(settings, row_id)
    if row.state in ("succeeded", "failed"):
        raise HTTPException(409, f"{kind.name} {row_id} already {row.state}")
    return row
