"""``GET /jobs/{id}/events``: a job's live events as Server-Sent Events; ``GET /jobs/{id}/deliveries``: its webhook
deliveries.

The stream reads the job's event log (:mod:`app.core.events`) every ``event_poll_s`` (no database connection is
held between reads), so it works the same whichever broker carries the work. Each event is ``id:`` (the job's
event number), ``event:`` (``progress``, ``stage``, ``evaluation`` or ``state``) and ``data:`` (one JSON object:
the job as ``GET /jobs/{id}`` returns it for ``progress`` and ``state``, the stage record for ``stage``, the history
point for ``evaluation``). Progress events are snapshots, so of those read together only the newest is sent. The
stream ends after the ``state`` event of a final state. ``Last-Event-ID: N`` resumes after event N; for a job that
has already ended it gets just the final state event (204 when N is that event or later: nothing is left to send,
which also stops a browser's EventSource from reconnecting). A comment line is sent every ``event_keepalive_s``
while nothing happens. One API process keeps at most ``max_event_streams`` streams open (429 beyond). When the
server is told to stop (SIGTERM, SIGINT) the open streams end within ``event_poll_s``: uvicorn waits for every open
response before it stops, and a client reconnects with ``Last-Event-ID`` anyway (:func:`server_stopping`).

The stream is written with Starlette's ``StreamingResponse``: the format is three lines per event and the read
loop is this module's own, so a library (sse-starlette) would add a dependency without taking any work away.
"""

from __future__ import annotations

import asyncio
import json
import signal
import time
from collections.abc import AsyncIterator

from fastapi import APIRouter, Header, HTTPException, Request, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import StreamingResponse
from starlette.types import Receive, Scope, Send

from app.api_reference import error_responses
from app.core import events
from app.core.jobstore import JOBS
from app.core.models import JobEventRow
from app.core.settings import Settings
from app.deps import JobId, SettingsDep
from app.routes import work
from app.routes.render import RenderSlots
from app.schemas import JobOut, WebhookDeliveryOut

router = APIRouter(tags=["jobs"])

STREAM_RETRY_AFTER_S = 5  # what a client refused for too many open streams is told to wait
KEEPALIVE = b": keep-alive\n\n"
EVENTS_PER_READ = 500
EVENT_EXAMPLE = (
    'id: 7\nevent: progress\ndata: {"id": "...", "state": "running", "progress": 0.42, ...}\n\n'
    'id: 8\nevent: stage\ndata: {"name": "prior", "ran": true, "why": "...", "seconds": 1.2}\n\n'
    'id: 12\nevent: state\ndata: {"id": "...", "state": "succeeded", ...}\n\n'
)


def event_data(event: JobEventRow) -> dict:
    """The ``data:`` object of an event: the job (``JobOut``) for ``progress`` and ``state``, else the record."""
    if event.kind in ("progress", "state"):
        return JobOut.from_row(events.job_from_columns(event.data)).model_dump(mode="json")
    return event.data


def _is_final(event: JobEventRow) -> bool:
    return event.kind == "state" and event.data.get("state") in events.FINAL_STATES


def sse_message(event: JobEventRow) -> bytes:
    """One event in the text/event-stream format (its JSON on one ``data:`` line)."""
    data = json.dumps(event_data(event), separators=(",", ":"), allow_nan=False)
    return f"id: {event.seq}\nevent: {event.kind}\ndata: {data}\n\n".encode()


def server_stopping() -> bool:
    """Whether the uvicorn server of this process has been told to stop: while it serves, its ``handle_exit`` is the
    SIGTERM handler, and it sets the server's ``should_exit``. False under any other server (its streams then end
    with their jobs, or when the client goes)."""
    server = getattr(signal.getsignal(signal.SIGTERM), "__self__", None)
    return bool(getattr(server, "should_exit", False))


def _newest_progress_only(batch: list[JobEventRow]) -> list[JobEventRow]:
    """``batch`` without the progress events a later one in it supersedes."""
    last_progress = max((i for i, e in enumerate(batch) if e.kind == "progress"), default=-1)
    return [e for i, e in enumerate(batch) if e.kind != "progress" or i == last_progress]


async def _stream(settings: Settings, job_id: str, after: int) -> AsyncIterator[bytes]:
    """The job's events after ``after`` as they are written, up to and including its final state event."""
    last_sent = time.monotonic()
    while not server_stopping():
        batch = await run_in_threadpool(events.events_after, settings, job_id, after, EVENTS_PER_READ)
        if batch:
            after = batch[-1].seq
            chunk = b""
            for event in _newest_progress_only(batch):
                chunk += sse_message(event)
                if _is_final(event):
                    yield chunk
                    return
            yield chunk
            last_sent = time.monotonic()
            if len(batch) == EVENTS_PER_READ:
                continue  # more may be behind it: read again at once
        if time.monotonic() - last_sent >= settings.event_keepalive_s:
            # an ended (or deleted) job with nothing after ``after``: its final event is behind the client already
            job = await run_in_threadpool(JOBS.get, settings, job_id)
            if job is None or job.state in events.FINAL_STATES:
                return
            yield KEEPALIVE
            last_sent = time.monotonic()
        await asyncio.sleep(settings.event_poll_s)


class EventStreamResponse(StreamingResponse):
    """A ``text/event-stream`` response that gives its slot back when it ends, however it ends (finished, the
    client gone, the server stopping)."""

    media_type = "text/event-stream"

    def __init__(self, content: AsyncIterator[bytes], slots: RenderSlots) -> None:
        super().__init__(content, headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})
        self.slots = slots

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        try:
            await super().__call__(scope, receive, send)
        finally:
            self.slots.release()


def _last_event_id(value: str | None) -> int | None:
    if value is None or not value.strip():
        return None
    if not value.strip().isdigit():
        raise HTTPException(422, f"Last-Event-ID must be an event id (a whole number >= 0), not {value[:40]!r}")
    return int(value)


@router.get(
    "/jobs/{job_id}/events",
    response_class=StreamingResponse,
    summary="Live events of a job (Server-Sent Events): progress, stage, evaluation, state",
    responses={
        200: {"description": "an event stream that ends with the job's final state",
              "content": {"text/event-stream": {"schema": {"type": "string"}, "example": EVENT_EXAMPLE}}},
        204: {"description": "Last-Event-ID is the final event of a job that has ended: nothing left to send"},
        **error_responses(404, 422, 429, e422="Last-Event-ID must be an event id (a whole number >= 0), not 'x'",
                          e429="64 event streams are open (VOXNERF_MAX_EVENT_STREAMS); retry later"),
    },
)
async def job_events(
    job_id: JobId,
    request: Request,
    settings: SettingsDep,
    last_event_id: str | None = Header(None, alias="Last-Event-ID",
                                       description="resume after this event id (browsers send it on reconnecting)"),
) -> Response:
    """The job's events as they are written: ``progress`` (the job), ``stage`` (a stage record), ``evaluation`` (a
    history point), ``state`` (the job); the stream ends after the final state's event. ``Last-Event-ID: N``
    resumes after event N (a browser's EventSource sends it when it reconnects)."""
    after = _last_event_id(last_event_id)
    job = await run_in_threadpool(work.found, settings, JOBS, job_id)
    if job.state in events.FINAL_STATES:
        await run_in_threadpool(events.complete_log, settings, job_id)
    if after is not None and job.state in events.FINAL_STATES:
        final = await run_in_threadpool(events.last_event, settings, job_id, "state")
        if final is None or final.seq <= after:
            return Response(status_code=204)
        after = final.seq - 1
        stream = _stream(settings, job_id, after)
    else:
        stream = _stream(settings, job_id, after or 0)
    slots: RenderSlots = request.app.state.event_streams
    if not slots.try_acquire():
        raise HTTPException(429, f"{slots.limit} event streams are open (VOXNERF_MAX_EVENT_STREAMS); retry later",
                            headers={"Retry-After": str(STREAM_RETRY_AFTER_S)})
    return EventStreamResponse(stream, slots)


@router.get("/jobs/{job_id}/deliveries", response_model=list[WebhookDeliveryOut],
            summary="Webhook deliveries of a job's state changes, with every attempt",
            responses=error_responses(404))
def job_deliveries(job_id: JobId, settings: SettingsDep) -> list[WebhookDeliveryOut]:
    """One delivery per state change of a job that has a ``callback_url``, oldest first: its outcome
    (``pending``, ``delivered``, ``abandoned``) and each attempt's time, HTTP status and error. 404 for an unknown
    job."""
    work.found(settings, JOBS, job_id)
    return [WebhookDeliveryOut.from_row(row) for row in events.deliveries_of(settings, job_id)]
