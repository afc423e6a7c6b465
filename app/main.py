"""The FastAPI application: routes, auth, request guards, body limits, the dashboard, and stale-job recovery.

``create_app(settings)`` builds one app; ``uvicorn --factory app.main:create_app`` serves it with settings
from the environment.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import re
from collections.abc import AsyncIterator
from pathlib import Path

from fastapi import Depends, FastAPI, Request, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.encoders import jsonable_encoder
from fastapi.exception_handlers import http_exception_handler
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse
from fastapi.staticfiles import StaticFiles
from starlette.exceptions import HTTPException as StarletteHTTPException

from app.api_reference import install_api_reference
from app.body_limit import BodyCountMiddleware, BodyLimitMiddleware
from app.core import db, storage
from app.core.celery_app import create_celery
from app.core.cleanup import clean_leftovers
from app.core.disk_space import InsufficientStorage
from app.core.dispatch import sweep_jobs
from app.core.log_format import configure_logging
from app.core.metrics import ApiMetrics
from app.core.progress import json_safe
from app.core.redact import install_log_masking, public_error
from app.core.render_results import remove_old_outcomes
from app.core.settings import Settings, get_settings
from app.deps import require_token
from app.origin_guard import RequestGuardMiddleware, log_exposure
from app.routes import events, health, imports, jobs, metrics, outputs, render, scenes, tokens, uploads, viewer
from app.uploads import sessions as upload_sessions
from app.uploads.rules import UploadError
from app.webhooks import deliver_due

log = logging.getLogger(__name__)
STATIC_DIR = Path(__file__).parent / "static"
UPLOAD_PART_PATH = re.compile(r"^/uploads/[^/]+/parts/[^/]+$")  # PUT: one part of an upload session


def is_upload(method: str, path: str) -> bool:
    """Whether a request's body is upload bytes (the metrics count them): ``POST /scenes``, or a ``PUT`` of one
    part of an upload session."""
    return (method, path) == ("POST", "/scenes") or (method == "PUT" and bool(UPLOAD_PART_PATH.match(path)))


def sweep_once(app: FastAPI) -> None:
    """Requeue jobs and output jobs whose worker died, re-send lost messages, drop uncollected render results,
    remove expired upload sessions."""
    settings: Settings = app.state.settings
    sweep_jobs(settings, app.state.celery)
    remove_old_outcomes(settings.render_results_dir, 2 * settings.render_timeout_s)
    for session_id in upload_sessions.remove_expired(settings):
        log.info("upload session %s expired; removed with its parts", session_id)


async def _sweep_forever(app: FastAPI) -> None:
    while True:
        try:
            await run_in_threadpool(sweep_once, app)
        except Exception:  # broker or database down: keep serving, try again next round
            log.exception("stale-job sweep failed")
        await asyncio.sleep(app.state.settings.sweep_interval_s)


async def _deliver_webhooks_forever(app: FastAPI) -> None:
    """Send the webhook deliveries that are due, every ``webhook_poll_s`` (:func:`app.webhooks.deliver_due`)."""
    while True:
        try:
            await deliver_due(app.state.settings)
        except Exception:  # database down: keep serving, try again next round
            log.exception("webhook delivery round failed")
        await asyncio.sleep(app.state.settings.webhook_poll_s)


@contextlib.asynccontextmanager
async def _lifespan(app: FastAPI) -> AsyncIterator[None]:
    settings: Settings = app.state.settings
    log_exposure(settings)
    settings.make_dirs()
    await run_in_threadpool(storage.check_store, settings)  # a bad store URL or credentials stop start-up
    db.get_engine(settings)
    install_log_masking()  # credentials in URLs never reach a log line
    await run_in_threadpool(clean_leftovers, settings)  # staging and half-made scenes a crash left
    sweeper = asyncio.create_task(_sweep_forever(app))  # its first round is the startup recovery
    deliverer = asyncio.create_task(_deliver_webhooks_forever(app))
    try:
        yield
    finally:
        for task in (sweeper, deliverer):
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task


async def _upload_error(request: Request, err: UploadError) -> JSONResponse:
    return JSONResponse({"detail": public_error(err.detail, request.app.state.settings)}, status_code=err.status_code)


async def _http_error(request: Request, err: StarletteHTTPException) -> Response:
    """FastAPI's answer to an HTTPException, its ``detail`` (when text) through :func:`public_error`: every
    detail a client reads, a token holder's included, names paths relative to the data directory, no
    credentials (a route that quotes an exception cannot forget it)."""
    if isinstance(err.detail, str):
        err = StarletteHTTPException(err.status_code, public_error(err.detail, request.app.state.settings),
                                     headers=err.headers)
    return await http_exception_handler(request, err)


async def _insufficient_storage(_request: Request, err: InsufficientStorage) -> JSONResponse:
    return JSONResponse({"detail": err.detail}, status_code=err.status_code)


async def _validation_error(_request: Request, err: RequestValidationError) -> JSONResponse:
    """FastAPI's 422, with NaN/inf in the echoed input made JSON-safe (a NaN pose must not become a 500)."""
    return JSONResponse({"detail": json_safe(jsonable_encoder(err.errors()))}, status_code=422)


def create_app(settings: Settings | None = None) -> FastAPI:
    """The API for ``settings`` (default: from ``VOXNERF_*`` environment variables)."""
    settings = settings or get_settings()
    if settings.log_format == "json":  # uvicorn has set its logging up by now (it calls this factory after)
        configure_logging("json")
    app = FastAPI(
        title="VoxNeRF",
        version="0.1.0",
        summary="Upload indoor scans, train prior-guided radiance fields, render any pose.",
        lifespan=_lifespan,
        openapi_url=None,  # app.api_reference serves the schema (behind the token), /docs and /redoc
        docs_url=None,
        redoc_url=None,
    )
    app.state.settings = settings
    app.state.celery = create_celery(settings)
    app.state.render_slots = render.RenderSlots(settings.max_concurrent_renders)
    app.state.event_streams = render.RenderSlots(settings.max_event_streams)  # open GET /jobs/{id}/events
    app.state.metrics = ApiMetrics()
    app.add_middleware(BodyCountMiddleware, counts=is_upload, count=app.state.metrics.upload_bytes.inc)
    app.add_middleware(
        BodyLimitMiddleware,
        limit_for=lambda method, path: (
            settings.max_upload_bytes if (method, path) == ("POST", "/scenes")
            else settings.max_upload_part_bytes if method == "PUT" and UPLOAD_PART_PATH.match(path)
            else settings.max_request_bytes
        ),
    )
    app.add_middleware(RequestGuardMiddleware, settings=settings)  # added last: runs first
    app.add_exception_handler(UploadError, _upload_error)
    app.add_exception_handler(InsufficientStorage, _insufficient_storage)
    app.add_exception_handler(StarletteHTTPException, _http_error)
    app.add_exception_handler(RequestValidationError, _validation_error)

    protected = [Depends(require_token)]
    for module in (scenes, uploads, imports, jobs, events, outputs, render, viewer, tokens, metrics):
        app.include_router(module.router, dependencies=protected)
    app.include_router(health.router)
    install_api_reference(app, protected)

    @app.get("/", include_in_schema=False)
    def dashboard() -> FileResponse:
        """The dashboard shell (static; it asks for the API token itself when the API needs one)."""
        return FileResponse(STATIC_DIR / "index.html", media_type="text/html")

    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")
    return app
