"""``POST /render``: render a pose of a trained job on a render worker and answer the image bytes.

A succeeded job renders; so does a running job from its latest checkpoint (a newer one is picked up by the next
render), and a cancelled or failed one from the last checkpoint it kept, each answered with ``X-VoxNeRF-Partial:
true`` (:func:`app.core.outputs.render_source`). Every image says which checkpoint made it
(``X-VoxNeRF-Iteration``) and the job's state when it was asked (``X-VoxNeRF-Job-State``).

Each API process serves at most ``max_concurrent_renders`` renders at once. The limit is taken on the event
loop before a worker thread is used, so a burst above it is answered 429 at once (with ``Retry-After``)
instead of queueing threads that each wait up to ``render_timeout_s`` for a render worker.
"""

from __future__ import annotations

import logging
import time

from celery import Celery
from fastapi import APIRouter, HTTPException, Request, Response
from fastapi.concurrency import run_in_threadpool
from kombu.exceptions import KombuError
from redis import RedisError

from app.api_reference import EXAMPLE_ID, error_responses
from app.core import jobstore
from app.core.dispatch import send_render
from app.core.jobstore import JOBS
from app.core.outputs import NotRenderable, render_source
from app.core.redact import public_error
from app.core.render_request import RenderRequest
from app.core.render_results import receive_outcome
from app.core.settings import Settings
from app.deps import CeleryDep, SettingsDep
from app.routes import work
from voxnerf.inference.encoding import MEDIA_TYPES

log = logging.getLogger(__name__)
router = APIRouter(tags=["render"])

RETRY_AFTER_S = 1  # what a refused client is told to wait: about one render of a small image
PARTIAL_HEADER = "X-VoxNeRF-Partial"  # "true" on a render of an unfinished model: not a succeeded job's
ITERATION_HEADER = "X-VoxNeRF-Iteration"  # the training iteration of the checkpoint that rendered
STATE_HEADER = "X-VoxNeRF-Job-State"  # the job's state when the render was asked (running: a live checkpoint)
NO_CHECKPOINT_YET_EXAMPLE = (f"job {EXAMPLE_ID} has no checkpoint yet: training writes its first about 60 s after its "
                             "set-up (VOXNERF_CHECKPOINT_EVERY_S), and renders start from it")


class RenderSlots:
    """A non-blocking counter of renders in progress, used only from the event loop (no lock needed)."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self.in_use = 0

    def try_acquire(self) -> bool:
        if self.in_use >= self.limit:
            return False
        self.in_use += 1
        return True

    def release(self) -> None:
        self.in_use -= 1


def _queue_unavailable(err: Exception, settings: Settings) -> HTTPException:
    """503 with Retry-After: the broker (or Redis, which carries the outcome back) cannot be reached."""
    return HTTPException(
        503,
        public_error(f"the render queue is unavailable ({err}); try again later", settings),
        headers={"Retry-After": str(RETRY_AFTER_S)},
    )


def _render(body: RenderRequest, settings: Settings, celery: Celery) -> Response:
    """The blocking part (job store, broker, waiting for the worker's outcome); runs in a worker thread.

    The outcome comes back through Redis (BLPOP) or, with the embedded broker, as files in
    ``data_dir/render-results``; see :mod:`app.core.render_results`.
    """
    job = work.found(settings, JOBS, body.job_id)
    try:
        partial = render_source(settings, job)
    except NotRenderable as err:
        raise HTTPException(409, str(err)) from None
    pixels, limit = body.pixels(), settings.render_pixel_limit()
    if pixels is not None and pixels > limit:
        raise HTTPException(422, f"{body.width}x{body.height} exceeds the limit of {limit} pixels")
    request_id = jobstore.new_id()
    try:
        send_render(celery, request_id, body.job_id, body.model_dump(), settings.render_timeout_s,
                    job.checkpoint_iteration)
    except (KombuError, OSError) as err:
        raise _queue_unavailable(err, settings) from None
    try:
        outcome = receive_outcome(settings, request_id, settings.render_timeout_s)
    except RedisError as err:
        raise _queue_unavailable(err, settings) from None
    if outcome is None:
        raise HTTPException(504, f"no render worker answered within {settings.render_timeout_s:g} s")
    if outcome.status != 200:
        raise HTTPException(outcome.status, outcome.detail)
    headers = {"Content-Disposition": f'inline; filename="{body.job_id}.{body.format}"', STATE_HEADER: job.state}
    if partial:
        headers[PARTIAL_HEADER] = "true"
    if outcome.iteration is not None:
        headers[ITERATION_HEADER] = str(outcome.iteration)
    return Response(outcome.data, media_type=outcome.media_type, headers=headers)


@router.post(
    "/render",
    response_class=Response,
    responses={
        200: {
            "content": {media: {} for media in MEDIA_TYPES.values()},
            "description": f"the image; headers {ITERATION_HEADER}: the iteration of the checkpoint that rendered, "
                           f"{STATE_HEADER}: the job's state, {PARTIAL_HEADER}: true unless the job succeeded (a "
                           "running job's latest checkpoint, or a cancelled or failed job's last one)",
        },
        **error_responses(
            404, 409, 422, 429, 500, 503, 504, e409=NO_CHECKPOINT_YET_EXAMPLE,
            e422="1920x1440 exceeds the limit of 2073600 pixels",
            e429="8 renders are already in progress on this API process (VOXNERF_MAX_CONCURRENT_RENDERS); retry "
            "in 1 s",
            e503="the render queue is unavailable (Connection refused); try again later"),
    },
    summary="Render a camera pose of a trained job (succeeded, or from the latest checkpoint of a running, "
            "cancelled or failed one) to PNG or EXR",
)
async def render(
    body: RenderRequest, request: Request, settings: SettingsDep, celery: CeleryDep
) -> Response:
    """Render one view of a trained job on a render worker and answer the image: PNG (one of rgb, depth,
    opacity) or EXR (any of them as float channels). Missing intrinsics are the scene's first training camera's;
    ``camera_model`` renders through a lens. 429 with ``Retry-After`` beyond ``VOXNERF_MAX_CONCURRENT_RENDERS``
    renders in progress on this API process."""
    slots: RenderSlots = request.app.state.render_slots
    if not slots.try_acquire():
        raise HTTPException(
            429,
            f"{slots.limit} renders are already in progress on this API process "
            f"(VOXNERF_MAX_CONCURRENT_RENDERS); retry in {RETRY_AFTER_S} s",
            headers={"Retry-After": str(RETRY_AFTER_S)},
        )
    started, status = time.perf_counter(), 500
    try:
        response = await run_in_threadpool(_render, body, settings, celery)
        status = response.status_code
        return response
    except HTTPException as err:
        status = err.status_code
        raise
    finally:
        slots.release()
        request.app.state.metrics.render_seconds.labels(status=str(status)).observe(time.perf_counter() - started)
