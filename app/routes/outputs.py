"""Output jobs of a trained job: fly-through videos, meshes and point clouds (queue ``outputs``), and their files.

``POST /jobs/{id}/videos`` and ``POST /jobs/{id}/exports`` queue one (202; 429 beyond ``max_queued_outputs``, a
video or export beyond ``max_output_pixels`` 422); ``GET /outputs/{id}`` follows it;
``GET /outputs/{id}/file`` downloads what a succeeded one made (409 before: a partial file is never served).
The rules (which jobs can be rendered from, camera-path limits, where files live) are in :mod:`app.core.outputs`.
"""

from __future__ import annotations

from typing import Annotated

from celery import Celery
from fastapi import APIRouter, HTTPException, Path, Query
from fastapi.responses import FileResponse

from app.api_reference import EXAMPLE_ID, NOT_RENDERABLE_EXAMPLE, error_responses
from app.core import jobstore, storage
from app.core import outputs as store
from app.core.disk_space import require_room
from app.core.jobstore import JOBS
from app.core.lease import QueueFull
from app.core.models import JobRow, OutputRow
from app.core.outputs import OUTPUTS
from app.core.redact import public_error
from app.core.settings import Settings
from app.core.tokens import Principal
from app.deps import ID_DOC, CeleryDep, JobId, PrincipalDep, SettingsDep
from app.routes import work
from app.schemas import ExportRequest, OutputOut, VideoRequest
from voxnerf.cameras.paths import CameraPathError

router = APIRouter(tags=["outputs"])
OutputId = Annotated[str, Path(pattern=jobstore.ID_RE.pattern, description=f"output id, {ID_DOC}")]


def _source_or_error(settings: Settings, job_id: str) -> tuple[JobRow, bool]:
    """Job ``job_id`` and whether its outputs are partial; 404 for an unknown job, 409 for one not to render
    from."""
    job = work.found(settings, JOBS, job_id)
    try:
        return job, store.trained_source(settings, job)
    except store.NotRenderable as err:
        raise HTTPException(409, str(err)) from None


def _queue(settings: Settings, celery: Celery, job_id: str, kind: str, params: dict, total: int | None,
           partial: bool, principal: Principal) -> OutputOut:
    """Add the output's row (made by ``principal``, within its queue limit) and publish its task; a broker that
    refuses it leaves the output failed (503). No row is added when the data directory has no room for the file
    (507, :func:`app.core.disk_space.require_room`)."""
    require_room(settings, what=f"a {kind} output")
    try:
        row = store.create_output(settings, job_id, kind, params, total, partial, principal)
    except QueueFull as full:
        raise HTTPException(429, str(full)) from None
    work.send_or_503(settings, celery, OUTPUTS, row.id)
    return OutputOut.from_row(row)


def _output_or_404(settings: Settings, output_id: str) -> OutputRow:
    return work.found(settings, OUTPUTS, output_id)


QUEUE_ERRORS = error_responses(
    404, 409, 422, 429, 503, 507, e409=NOT_RENDERABLE_EXAMPLE,
    e429="100 outputs are queued already (the limit is 100, VOXNERF_MAX_QUEUED_OUTPUTS); wait for some to start, or "
    "cancel some")


@router.post("/jobs/{job_id}/videos", status_code=202, response_model=OutputOut,
             summary="Render a fly-through video (MP4) of a trained job", responses=QUEUE_ERRORS)
def create_video(job_id: JobId, body: VideoRequest, settings: SettingsDep, celery: CeleryDep,
                 principal: PrincipalDep) -> OutputOut:
    """Queue a video on the ``outputs`` queue: along a nerfstudio ``camera_path``, or a generated ``path``
    (``interpolate`` through the training cameras, or an ``orbit``). 202 with the output; follow it at
    ``GET /outputs/{id}`` and download it from its ``file_url`` once it has succeeded."""
    job, partial = _source_or_error(settings, job_id)
    try:
        params, frames = store.video_params(settings, body.model_dump())
        store.check_output_cost(settings, job, "video", params, frames)
    except (CameraPathError, store.OutputTooCostly) as err:
        raise HTTPException(422, str(err)) from None
    return _queue(settings, celery, job_id, "video", params, frames, partial, principal)


@router.post("/jobs/{job_id}/exports", status_code=202, response_model=OutputOut,
             summary="Export a mesh or a point cloud (PLY) of a trained job", responses=QUEUE_ERRORS)
def create_export(job_id: JobId, body: ExportRequest, settings: SettingsDep, celery: CeleryDep,
                  principal: PrincipalDep) -> OutputOut:
    """Queue a geometry export on the ``outputs`` queue: a triangle mesh or a coloured point cloud, binary PLY in
    scene units. 202 with the output; follow it at ``GET /outputs/{id}``."""
    job, partial = _source_or_error(settings, job_id)
    params = body.model_dump(exclude={"kind"})
    try:
        store.check_output_cost(settings, job, body.kind, params, None)
    except store.OutputTooCostly as err:
        raise HTTPException(422, str(err)) from None
    return _queue(settings, celery, job_id, body.kind, params, None, partial, principal)


@router.get("/jobs/{job_id}/outputs", response_model=list[OutputOut], summary="Output jobs of a job, newest first",
            responses=error_responses(404))
def list_outputs(job_id: JobId, settings: SettingsDep, limit: int = Query(100, ge=1, le=1000)) -> list[OutputOut]:
    """The videos, meshes and point clouds made (or being made) from the job, newest first."""
    work.found(settings, JOBS, job_id)
    return [OutputOut.from_row(row) for row in OUTPUTS.newest(settings, limit, job_id=job_id)]


@router.get("/outputs/{output_id}", response_model=OutputOut, summary="State, progress, ETA, error, summary",
            responses=error_responses(404, e404=f"no output {EXAMPLE_ID}"))
def get_output(output_id: OutputId, settings: SettingsDep) -> OutputOut:
    """The output's state and progress (frames or views done of total); once it has succeeded, what it made and
    its ``file_url``."""
    return OutputOut.from_row(_output_or_404(settings, output_id))


@router.post("/outputs/{output_id}/cancel", status_code=202, response_model=OutputOut, summary="Cancel an output",
             responses=error_responses(404, 409, e404=f"no output {EXAMPLE_ID}",
                                       e409=f"output {EXAMPLE_ID} already succeeded"))
def cancel_output(output_id: OutputId, settings: SettingsDep, principal: PrincipalDep) -> OutputOut:
    """Cancel a queued output at once, a running one at its next frame or view (nothing is kept); 403 for another
    token's output (scope write)."""
    return OutputOut.from_row(work.cancel(settings, OUTPUTS, output_id, principal))


@router.get(
    "/outputs/{output_id}/file",
    response_class=FileResponse,
    responses={
        200: {"content": {"video/mp4": {}, "application/octet-stream": {}}, "description": "the MP4 or PLY"},
        **error_responses(404, 409, 503, e404=f"no output {EXAMPLE_ID}",
                          e409=f"output {EXAMPLE_ID} is running; its file is served once it has succeeded"),
    },
    summary="Download a succeeded output (video/mp4, or PLY as application/octet-stream)",
)
def get_output_file(output_id: OutputId, settings: SettingsDep) -> FileResponse:
    """The MP4 or PLY of a succeeded output (409 before: a partial file is never served)."""
    row = _output_or_404(settings, output_id)
    if row.state != "succeeded":
        raise HTTPException(409, f"output {output_id} is {row.state}; its file is served once it has succeeded")
    try:
        path = store.output_file(settings, row)
    except storage.StorageError as err:
        detail = public_error(f"the output cannot be fetched from the store: {err}", settings)
        raise HTTPException(503, detail) from None
    except FileNotFoundError:
        raise HTTPException(404, f"output {output_id}: its file is gone from the data directory") from None
    return FileResponse(path, media_type=store.MEDIA_TYPES[row.kind], filename=f"{row.id}-{row.file_name}")
