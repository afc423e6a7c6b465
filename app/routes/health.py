"""``GET /healthz``: the database, the broker and the live workers of each queue (200 or 503)."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import JSONResponse

from app.core import db
from app.core.celery_app import RENDER_QUEUE, TRAIN_QUEUE
from app.deps import CeleryDep, SettingsDep
from app.schemas import Check, HealthOut

router = APIRouter(tags=["health"])


def _error(err: Exception) -> str:
    return f"{type(err).__name__}: {err}"


@router.get(
    "/healthz",
    response_model=HealthOut,
    responses={503: {"model": HealthOut}},
    summary="Database, broker and live workers (no auth)",
)
def healthz(settings: SettingsDep, celery: CeleryDep) -> JSONResponse:
    try:
        db.ping(settings)
        database = Check(ok=True, detail="ok")
    except Exception as err:  # any driver error means "not reachable"
        database = Check(ok=False, detail=_error(err))

    workers: dict[str, list[str]] = {TRAIN_QUEUE: [], RENDER_QUEUE: []}
    try:
        with celery.connection_for_write() as conn:
            conn.ensure_connection(max_retries=1, timeout=settings.health_timeout_s)
            embedded = f"filesystem queue in {settings.broker_dir}"
            where = embedded if settings.embedded_broker else conn.as_uri()  # as_uri() masks the password
        replies = celery.control.inspect(timeout=settings.health_timeout_s).active_queues() or {}
        for name, queues in sorted(replies.items()):
            for queue in queues:
                workers.setdefault(queue["name"], []).append(name)
        broker = Check(ok=True, detail=where)
    except Exception as err:  # connection refused, timeout, auth...: the broker is not usable
        broker = Check(ok=False, detail=_error(err))

    healthy = database.ok and broker.ok and bool(workers[TRAIN_QUEUE]) and bool(workers[RENDER_QUEUE])
    body = HealthOut(
        status="ok" if healthy else "unavailable", database=database, broker=broker, workers=workers
    )
    return JSONResponse(body.model_dump(), status_code=200 if healthy else 503)
