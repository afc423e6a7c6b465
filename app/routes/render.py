"""``POST /render``: render a pose of a finished job on a render worker and answer the image bytes."""

from __future__ import annotations

import logging

from fastapi import APIRouter, HTTPException, Response
from kombu.exceptions import KombuError

from app import jobstore
from app.deps import CeleryDep, SettingsDep
from app.schemas import MEDIA_TYPES, RenderRequest
from worker.dispatch import send_render
from worker.render_results import wait_outcome

log = logging.getLogger(__name__)
router = APIRouter(tags=["render"])


@router.post(
    "/render",
    response_class=Response,
    responses={
        200: {"content": {media: {} for media in MEDIA_TYPES.values()}, "description": "the image"},
        409: {"description": "the job has not succeeded"},
        504: {"description": "no render worker answered in time"},
    },
    summary="Render a camera pose of a succeeded job to PNG or EXR",
)
def render(body: RenderRequest, settings: SettingsDep, celery: CeleryDep) -> Response:
    job = jobstore.get_job(settings, body.job_id)
    if job is None:
        raise HTTPException(404, f"no job {body.job_id}")
    if job.state != "succeeded":
        raise HTTPException(409, f"job {body.job_id} is {job.state}; only a succeeded job can be rendered")
    pixels = body.pixels()
    if pixels is not None and pixels > settings.max_render_pixels:
        raise HTTPException(
            422, f"{body.width}x{body.height} exceeds the limit of {settings.max_render_pixels} pixels"
        )
    request_id = jobstore.new_id()
    try:
        send_render(celery, request_id, body.job_id, body.model_dump(), settings.render_timeout_s)
    except (KombuError, OSError) as err:
        raise HTTPException(503, f"the render queue is unavailable ({err}); try again later") from None
    outcome = wait_outcome(settings.render_results_dir, request_id, settings.render_timeout_s)
    if outcome is None:
        raise HTTPException(504, f"no render worker answered within {settings.render_timeout_s:g} s")
    if outcome.status != 200:
        raise HTTPException(outcome.status, outcome.detail)
    return Response(
        outcome.data,
        media_type=outcome.media_type,
        headers={"Content-Disposition": f'inline; filename="{body.job_id}.{body.format}"'},
    )
