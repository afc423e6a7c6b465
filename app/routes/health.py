"""``GET /healthz``: the database, the broker and the live workers of each queue (200 or 503).

A check can take ``health_timeout_s`` (the broker's worker inspection), so one :class:`HealthProbe` per API
process runs at most one check at a time, in one thread, and every request that arrives meanwhile awaits that
same check without holding a thread. Callers with a valid token (everyone when the service has none) get the details
of a check that was running or started when they asked; other callers get ``status`` alone, from a check at
most ``health_cache_s`` old, so a flood of anonymous requests costs one check every ``health_cache_s``.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Callable

from celery import Celery
from fastapi import APIRouter, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse

from app.core import db, tokens
from app.core.celery_app import RENDER_QUEUE, TRAIN_QUEUE
from app.core.redact import public_error
from app.core.settings import Settings
from app.schemas import Check, HealthOut

router = APIRouter(tags=["health"])


def _error(err: Exception, settings: Settings) -> str:
    """An exception as a check's detail: no credentials, paths relative to the data directory."""
    return public_error(f"{type(err).__name__}: {err}", settings)


class HealthProbe:
    """Runs ``check()`` (blocking, returns a :class:`HealthOut`) at most once at a time, in the thread pool;
    concurrent callers share the running check. Use from the app's event loop only."""

    def __init__(self, check: Callable[[], HealthOut]) -> None:
        self._check = check
        self._running: asyncio.Task[HealthOut] | None = None
        self._latest: HealthOut | None = None
        self._latest_at = -math.inf  # time.monotonic() when _latest was computed

    async def current(self) -> HealthOut:
        """The result of the running check, or of one started now."""
        if self._running is None or self._running.get_loop() is not asyncio.get_running_loop():
            self._running = asyncio.ensure_future(self._run())
        return await asyncio.shield(self._running)  # a caller that goes away does not cancel the others'

    async def recent(self, max_age_s: float) -> HealthOut:
        """The last result if at most ``max_age_s`` old, else :meth:`current`."""
        if self._latest is not None and time.monotonic() - self._latest_at <= max_age_s:
            return self._latest
        return await self.current()

    async def _run(self) -> HealthOut:
        try:
            result = await run_in_threadpool(self._check)
            self._latest, self._latest_at = result, time.monotonic()
            return result
        finally:
            self._running = None


def health_probe(request: Request) -> HealthProbe:
    """The app's probe, made on first use (routes of one app run on one event loop)."""
    state = request.app.state
    if getattr(state, "health_probe", None) is None:
        state.health_probe = HealthProbe(lambda: check_health(state.settings, state.celery))
    return state.health_probe


def check_health(settings: Settings, celery: Celery) -> HealthOut:
    """Ping the database, connect to the broker and ask the workers for their queues (blocks up to about
    2 x ``health_timeout_s``)."""
    try:
        db.ping(settings)
        database = Check(ok=True, detail="ok")
    except Exception as err:  # any driver error means "not reachable"
        database = Check(ok=False, detail=_error(err, settings))

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
        broker = Check(ok=True, detail=public_error(where, settings))
    except Exception as err:  # connection refused, timeout, auth...: the broker is not usable
        broker = Check(ok=False, detail=_error(err, settings))

    healthy = database.ok and broker.ok and bool(workers[TRAIN_QUEUE]) and bool(workers[RENDER_QUEUE])
    return HealthOut(
        status="ok" if healthy else "unavailable", database=database, broker=broker, workers=workers
    )


def _has_principal(settings: Settings, authorization: str | None) -> bool:
    """Whether the caller is a principal (any valid token, read scope included; everyone on a tokenless service),
    who gets the details; False too when the database cannot say (the check itself then reports it)."""
    try:
        return tokens.resolve(settings, authorization) is not None
    except Exception:  # the database is down: answer as to an anonymous caller
        return False


@router.get(
    "/healthz",
    response_model=HealthOut,
    responses={503: {"model": HealthOut, "description": "the database, the broker or a queue's workers are missing",
                     "content": {"application/json": {"example": {"status": "unavailable"}}}}},
    summary="Status (no auth); database, broker and live workers with the token",
)
async def healthz(request: Request) -> JSONResponse:
    """200 when the database and the broker answer and the train and render queues each have a live worker, else
    503. Without the token only ``status`` (from a check at most ``VOXNERF_HEALTH_CACHE_S`` old); with it (or on a
    tokenless service) the database, the broker and the live workers of each queue."""
    # Async with no sync dependencies: a waiting request holds no thread of the pool.
    settings: Settings = request.app.state.settings
    probe = health_probe(request)
    if await run_in_threadpool(_has_principal, settings, request.headers.get("authorization")):
        body = await probe.current()
        content = body.model_dump()
    else:
        body = await probe.recent(settings.health_cache_s)
        content = {"status": body.status}
    return JSONResponse(content, status_code=200 if body.status == "ok" else 503)
