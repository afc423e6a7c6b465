"""What the routes of every kind of queued work share (training jobs: :mod:`app.routes.jobs`, output jobs:
:mod:`app.routes.outputs`, capture imports: :mod:`app.routes.imports`): sending a new row's message (or failing
the row: 503), the row or a 404, and a cancel request's answer. Their lifecycle is :mod:`app.core.lease`'s."""

from __future__ import annotations

import logging
from typing import Any

from celery import Celery
from fastapi import HTTPException
from kombu.exceptions import KombuError

from app.core.dispatch import send
from app.core.lease import WorkKind
from app.core.redact import public_error
from app.core.settings import Settings
from app.core.tokens import Principal
from app.deps import require_owner

log = logging.getLogger(__name__)


def send_or_503(settings: Settings, celery: Celery, kind: WorkKind, row_id: str) -> None:
    """Publish the message of the new row ``row_id`` of ``kind``; when the broker refuses it the row is failed
    (naming why) and the client gets 503."""
    try:
        send(celery, kind, row_id)
    except (KombuError, OSError) as err:
        log.error("cannot queue %s %s: %s", kind.name, row_id, err)
        kind.fail(settings, row_id, public_error(f"the broker refused it: {err}", settings))
        raise HTTPException(503, public_error(f"the {kind.name} queue is unavailable ({err}); try again later",
                                              settings)) from None


def found(settings: Settings, kind: WorkKind, row_id: str) -> Any:
    """The row ``row_id`` of ``kind``; 404 naming it when there is none."""
    row = kind.get(settings, row_id)
    if row is None:
        raise HTTPException(404, f"no {kind.name} {row_id}")
    return row


def cancel(settings: Settings, kind: WorkKind, row_id: str, principal: Principal) -> Any:
    """Cancel row ``row_id`` of ``kind`` for ``principal`` (a queued one at once, a running one when its worker
    next reads the flag); the row as it is now. 404 for an unknown row, 403 for another principal's row
    (:func:`app.deps.require_owner`), 409 for one that has already succeeded or failed (a cancelled one is
    answered as it is)."""
    require_owner(principal, f"{kind.name} {row_id}", found(settings, kind, row_id).created_by)
    row = kind.request_cancel(settings, row_id, by=principal.name)
    log.info("%s %s: cancel requested by %r", kind.name, row_id, principal.name)
    if row.state in ("succeeded", "failed"):
        raise HTTPException(409, f"{kind.name} {row_id} already {row.state}")
    return row
