"""``/scenes``: upload (zip or files), list, show, delete; and ``POST /scenes/{id}/jobs`` to train on one."""

from __future__ import annotations

import contextlib
import logging
from collections.abc import AsyncIterator
from pathlib import Path
from typing import BinaryIO

from fastapi import APIRouter, HTTPException, Request, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse
from pydantic import ValidationError
from starlette.datastructures import UploadFile

from app import webhooks
from app.api_reference import EXAMPLE_ID, error_responses
from app.core import jobstore, storage
from app.core.disk_space import require_room
from app.core.imports import IMPORTS
from app.core.jobstore import JOBS
from app.core.lease import QueueFull
from app.core.models import ImportRow
from app.core.scene_store import StoredScene
from app.core.settings import Settings
from app.core.tokens import Principal
from app.deps import CeleryDep, PrincipalDep, SceneId, SettingsDep, require_owner
from app.routes import work
from app.routes.render import RenderSlots
from app.schemas import ImportOut, JobOptions, JobOut, SceneOut
from app.uploads import staging
from app.uploads.form import read_form
from voxnerf.config import TrainConfig
from voxnerf.data.importers.splits import PaperSplitRule

log = logging.getLogger(__name__)
router = APIRouter(tags=["scenes"])
UPLOAD_RETRY_AFTER_S = 10  # what a client refused for too many uploads in progress is told to wait

UPLOAD_BODY = {
    "required": True,
    "content": {
        "multipart/form-data": {
            "schema": {
                "type": "object",
                "properties": {
                    "file": {
                        "type": "string",
                        "format": "binary",
                        "description": "a .zip of the scene directory (transforms.json), or of a COLMAP "
                        "project (sparse/0 or sparse with cameras.bin|txt, and images/) or a ScanNet export "
                        "(color/, depth/, pose/, intrinsic/), imported into a scene; or a capture whose import "
                        "is queued (answered 202 with the import): a video (MP4, MOV), a ROS 1 .bag, a ROS 2 "
                        "bag's .mcap or .db3, or a .zip of photos alone (posed by structure from motion), of a ROS "
                        "2 bag folder or of a Stray Scanner recording; see docs/scene-format.md",
                    },
                    "files": {
                        "type": "array",
                        "items": {"type": "string", "format": "binary"},
                        "description": "or the scene's files, each part's filename its path in the scene "
                        "(transforms.json, images/0001.png, prior.ply...)",
                    },
                    "name": {"type": "string", "description": "display name (default: the zip's file name)"},
                    "splits": {
                        "type": "string",
                        "enum": ["paper"],
                        "description": "for an upload to import: write the paper's train / interpolation / "
                        "extrapolation splits (default: none, the loader's default split applies)",
                    },
                },
            },
            "example": {"file": "(the bytes of redkitchen.zip)", "name": "redkitchen"},
        }
    },
}


def _display_name(value: object, fallback: str) -> str:
    text = value if isinstance(value, str) and value.strip() else fallback
    return "".join(ch for ch in text if ch.isprintable())[:255] or "scene"


def _split_rule(value: object, is_zip: bool):
    """The form field ``splits`` as an importer's split rule; 422 for a bad value or a files upload."""
    rule = staging.split_rule(value)  # UploadError: answered as 422 by app.main's handler
    if rule is not None and not is_zip:
        raise HTTPException(422, "splits: only an upload to import (in field 'file') takes splits")
    return rule


@router.post(
    "/scenes",
    status_code=201,
    response_model=SceneOut,
    responses={202: {"model": ImportOut, "description": "a capture whose import is queued: follow it at "
                     "/imports/{id}; its scene exists once it has succeeded"},
               **error_responses(413, 415, 422, 429, 503, 507,
                                 e422="entry room/transforms.json: frames[3].transform_matrix is not a 4x4 matrix")},
    openapi_extra={"requestBody": UPLOAD_BODY},
    summary="Upload a scene (zip in field 'file', or its files in fields 'files'); COLMAP, ScanNet, Record3D and "
    "Polycam zips are imported; videos, photos, ROS bags and Stray recordings are queued for import",
)
async def create_scene(
    request: Request, settings: SettingsDep, celery: CeleryDep, principal: PrincipalDep
) -> SceneOut | JSONResponse:
    """A multipart form: a .zip in field ``file`` (a scene directory, or a COLMAP, ScanNet, Record3D or Polycam
    export, imported at once), a capture in ``file`` (a video, photos, a ROS bag or a Stray recording: its import
    is queued, answered 202 with the import), or the scene's files in fields ``files``. The upload is unpacked and
    validated in a sandboxed process (sizes, pixels, file types, poses, the prior) before the scene exists: 201
    with the scene and its summary. Example: ``curl -H "Authorization: Bearer $TOKEN" -F file=@room.zip
    http://127.0.0.1:8000/scenes``."""
    async with upload_slot(request, settings):
        declared = _declared_length(request)  # the body is not read yet: a refused upload writes nothing
        await run_in_threadpool(require_room, settings, declared, what=f"an upload of {declared} bytes")
        stored = await _receive_scene(request, settings, principal)
    return stored_answer(settings, celery, stored)


def stored_answer(settings: Settings, celery, stored: StoredScene | ImportRow) -> SceneOut | JSONResponse:
    """What an upload answers (``POST /scenes``, ``POST /uploads/{id}/complete``): the new scene (201), or the
    queued import of a capture (202, its message sent to the import workers)."""
    if isinstance(stored, ImportRow):
        work.send_or_503(settings, celery, IMPORTS, stored.id)
        body = ImportOut.from_row(IMPORTS.get(settings, stored.id)).model_dump(mode="json")
        return JSONResponse(body, status_code=202, headers={"Location": f"/imports/{stored.id}"})
    return SceneOut.from_row(jobstore.get_scene(settings, stored.id))


@contextlib.asynccontextmanager
async def upload_slot(request: Request, settings: Settings) -> AsyncIterator[None]:
    """One of the ``max_concurrent_uploads`` uploads this API process takes at once, held for the block; 429 with
    Retry-After when none is free (asked before a body is read: a refused upload costs no disk and no thread)."""
    slots = _upload_slots(request, settings)
    if not slots.try_acquire():
        raise HTTPException(
            429,
            f"{slots.limit} uploads are already in progress on this API process "
            f"(VOXNERF_MAX_CONCURRENT_UPLOADS); retry in {UPLOAD_RETRY_AFTER_S} s",
            headers={"Retry-After": str(UPLOAD_RETRY_AFTER_S)},
        )
    try:
        yield
    finally:
        slots.release()


def _declared_length(request: Request) -> int:
    """The request's ``Content-Length`` (0 when absent or not a number: a chunked body is checked once it is
    unpacked, and cut off at ``max_upload_bytes`` meanwhile)."""
    value = request.headers.get("content-length", "")
    return int(value) if value.isdigit() else 0


def _upload_slots(request: Request, settings: Settings) -> RenderSlots:
    """This app's counter of uploads in progress, made on first use (only the event loop touches it)."""
    state = request.app.state
    if not hasattr(state, "upload_slots"):
        state.upload_slots = RenderSlots(settings.max_concurrent_uploads)
    return state.upload_slots


async def _receive_scene(request: Request, settings: Settings, principal: Principal) -> StoredScene | ImportRow:
    """Read the form (file parts spooled to disk), then stage, validate and store the scene in a thread (or queue
    the import of a capture), made by ``principal``."""
    async with read_form(request, settings) as form:
        archive = form.get("file")
        parts = [p for p in form.getlist("files") if isinstance(p, UploadFile)]
        if isinstance(archive, UploadFile) and parts:
            raise HTTPException(
                422, "send either a zip in field 'file' or the scene's files in 'files', not both"
            )
        splits = _split_rule(form.get("splits"), isinstance(archive, UploadFile))
        if isinstance(archive, UploadFile):
            stored = await run_in_threadpool(
                store_file, settings, archive.file, archive.filename, form.get("name"), splits, principal
            )
        elif parts:
            named = [(p.filename or "", p.file) for p in parts]
            stored = await run_in_threadpool(
                staging.store_parts, settings, _display_name(form.get("name"), "scene"), named, principal
            )
        else:
            raise HTTPException(
                422,
                "no scene: send a multipart form with a .zip in field 'file', or the files in field 'files'",
            )
    return stored


def store_file(settings: Settings, source: BinaryIO | Path, filename: str | None, name: object,
               splits: PaperSplitRule | None, principal: Principal | None = None) -> StoredScene | ImportRow:
    """Store an upload sent as one file (``filename``, display name ``name`` or the file name's stem): a capture
    recognised by its first bytes is queued for import, anything else is a zip to validate and store. ``source``
    is a stream to copy, or a file (an upload session's, :mod:`app.routes.uploads`) moved into staging."""
    base = (filename or "scene").rsplit("/", 1)[-1]
    stem = base.rsplit(".", 1)[0] if "." in base[1:] else base  # room.zip, robot.bag -> room, robot
    display = _display_name(name, stem)
    if isinstance(source, Path):
        with open(source, "rb") as head:
            capture = staging.capture_kind(head)
    else:
        capture = staging.capture_kind(source)
    if capture is not None:
        return staging.store_capture(settings, display, source, capture, splits, principal)
    return staging.store_zip(settings, display, source, splits, principal)


@router.get("/scenes", response_model=list[SceneOut], summary="List scenes, newest first")
def list_scenes(settings: SettingsDep) -> list[SceneOut]:
    """Every stored scene with its summary (frames, splits, image size, prior, depth), newest first."""
    return [SceneOut.from_row(row) for row in jobstore.list_scenes(settings)]


def _scene_or_404(settings, scene_id: str):
    row = jobstore.get_scene(settings, scene_id)
    if row is None:
        raise HTTPException(404, f"no scene {scene_id}")
    return row


@router.get("/scenes/{scene_id}", response_model=SceneOut, summary="One scene and its summary",
            responses=error_responses(404, e404=f"no scene {EXAMPLE_ID}"))
def get_scene(scene_id: SceneId, settings: SettingsDep) -> SceneOut:
    """The scene's name, size and summary (what the upload's validation found), and for an imported upload what
    its importer wrote."""
    return SceneOut.from_row(_scene_or_404(settings, scene_id))


@router.delete("/scenes/{scene_id}", status_code=204, summary="Delete a scene (refused while a job uses it)",
               responses=error_responses(404, 409, e404=f"no scene {EXAMPLE_ID}",
                                         e409=f"scene {EXAMPLE_ID} is used by 1 active job(s): {EXAMPLE_ID}; "
                                         "cancel or wait for them first"))
def delete_scene(scene_id: SceneId, settings: SettingsDep, principal: PrincipalDep) -> Response:
    """Delete the scene's row and files (here and in the object store; its finished jobs stay); 409 while a queued
    or running job uses it, 403 for another token's scene (scope write)."""
    require_owner(principal, f"scene {scene_id}", _scene_or_404(settings, scene_id).created_by)
    try:
        deleted = jobstore.delete_scene(settings, scene_id)
    except jobstore.SceneBusy as busy:
        raise HTTPException(409, f"scene {scene_id} is {busy}; cancel or wait for them first") from None
    if not deleted:
        raise HTTPException(404, f"no scene {scene_id}")
    log.info("scene %s deleted by %r", scene_id, principal.name)
    staging.remove_scene_files(settings, scene_id)
    try:
        storage.delete_scene(settings, scene_id)
    except Exception:  # the scene is gone for the service; its unreferenced copy in the store is only waste
        log.error("scene %s: deleting its copy in the object store failed", scene_id, exc_info=True)
    return Response(status_code=204)


@router.post(
    "/scenes/{scene_id}/jobs",
    status_code=202,
    response_model=JobOut,
    summary="Start training a scene",
    responses=error_responses(404, 422, 429, 503, e404=f"no scene {EXAMPLE_ID}",
                              e429="100 jobs are queued already (the limit is 100, VOXNERF_MAX_QUEUED_JOBS); "
                              "wait for some to start, or cancel some"),
)
def create_job(
    scene_id: SceneId, options: JobOptions, settings: SettingsDep, celery: CeleryDep, response: Response,
    principal: PrincipalDep,
) -> JobOut:
    """Queue a training job on the scene with the given options (the ``voxnerf train`` flags; at least one of
    ``max_seconds`` and ``max_iters``): 202 with the job, ``Location: /jobs/{id}``; follow it at ``GET /jobs/{id}``
    or its events. ``callback_url`` (optional) receives its state changes (see docs/integration.md, "Live events and
    webhooks"): a URL whose host resolves to a private or loopback address is refused with 422 unless
    VOXNERF_WEBHOOK_ALLOW_PRIVATE is set."""
    values = options.model_dump(exclude_none=True, exclude={"callback_url"})
    if options.callback_url is not None:
        try:
            webhooks.checked_addresses(options.callback_url, settings.webhook_allow_private)
        except webhooks.CallbackRefused as refused:
            raise HTTPException(422, str(refused)) from None
    try:  # TrainConfig's own cross-field rules; the worker adds device and checkpoint_every_s the same way
        TrainConfig(**values, device=settings.device, checkpoint_every_s=settings.checkpoint_every_s)
    except ValidationError as err:
        raise HTTPException(422, f"invalid training options: {err}") from None
    _scene_or_404(settings, scene_id)
    try:
        job = jobstore.create_job(settings, scene_id, values, principal, callback_url=options.callback_url)
    except QueueFull as full:
        raise HTTPException(429, str(full)) from None
    if job is None:
        raise HTTPException(404, f"no scene {scene_id}")
    work.send_or_503(settings, celery, JOBS, job.id)
    response.headers["Location"] = f"/jobs/{job.id}"
    return JobOut.from_row(JOBS.get(settings, job.id))
