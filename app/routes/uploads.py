"""``/uploads``: upload sessions, one file sent in parts that can be resent after a dropped connection (the rules
are in :mod:`app.uploads.sessions`); completing one stores the file as ``POST /scenes`` stores a zip or capture."""

from __future__ import annotations

import hashlib
import tempfile
from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, Header, Request, Response
from fastapi import Path as PathParam
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse
from pydantic import BaseModel, ConfigDict, Field
from starlette.requests import ClientDisconnect

from app.api_reference import EXAMPLE_ID, error_responses
from app.core.settings import Settings
from app.core.tokens import Principal
from app.deps import CeleryDep, PrincipalDep, SettingsDep, require_owner
from app.routes.scenes import store_file, stored_answer, upload_slot
from app.schemas import ImportOut, SceneOut
from app.uploads import sessions, staging
from app.uploads.rules import UploadError

router = APIRouter(tags=["uploads"])
SessionId = Annotated[str, PathParam(pattern=sessions.SESSION_ID_RE.pattern, description="upload session id")]
PartNumber = Annotated[int, PathParam(ge=0, le=100_000, description="part number, from 0")]
SESSION_GONE_EXAMPLE = f"no upload session {EXAMPLE_ID} (completed, deleted or expired)"
NOT_YOURS_EXAMPLE = (f"upload session {EXAMPLE_ID} was made by 'alice'; token 'bob' (scope write) may read, send parts "
                     "to, complete or delete only its own work (scope admin acts on all)")


def _require_session_owner(settings: Settings, upload_id: str, principal: Principal) -> None:
    """403 unless ``principal`` opened the session or is an admin (404 when there is no such session): a session's
    parts, its completion and the scene it becomes belong to the token that opened it."""
    require_owner(principal, f"upload session {upload_id}", sessions.owner(settings, upload_id),
                  "read, send parts to, complete or delete")


class UploadCreate(BaseModel):
    """A file to send in parts; ``name`` and ``splits`` are those of ``POST /scenes``'s form."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"filename": "kitchen.zip", "total_bytes": 5368709120,
         "sha256": "9f86d081884c7d659a2feaa0c55ad015a3bf4f1b2b0b822cd15d6c15b0f00a08"}]})

    filename: str = Field(min_length=1, max_length=sessions.MAX_FILENAME_CHARS,
                          description="the file's name: a .zip (of a scene, a COLMAP project...), a video or a bag")
    total_bytes: int = Field(gt=0, description="the whole file's size")
    sha256: str | None = Field(None, description="SHA-256 of the whole file (64 hex digits), checked at completion")
    name: str | None = Field(None, max_length=1024, description="display name (default: the file name's stem)")
    splits: str | None = Field(None, description="as POST /scenes's field: 'paper' for an upload to import")


class UploadOut(BaseModel):
    """An upload session: its part size and what it has received (what a client needs to resume)."""

    id: str
    filename: str
    total_bytes: int
    sha256: str | None
    part_bytes: int = Field(description="every part has this many bytes but the last, which has the rest")
    part_count: int
    received_parts: list[int] = Field(description="numbers of the parts received, in order")
    received_bytes: int
    missing_parts: int
    expires_at: float = Field(description="Unix time at which the session expires unless another part arrives")
    created_by: str | None = Field(description="the token that opened the session; only it (or an admin) may use it")

    @classmethod
    def of(cls, state: sessions.SessionState) -> UploadOut:
        session = state.session
        return cls(id=session.id, filename=session.filename, total_bytes=session.total_bytes, sha256=session.sha256,
                   part_bytes=session.part_bytes, part_count=session.part_count,
                   received_parts=sorted(state.received), received_bytes=state.received_bytes,
                   missing_parts=session.part_count - len(state.received), expires_at=state.expires_at,
                   created_by=session.created_by)


class PartOut(BaseModel):
    number: int
    sha256: str
    size: int
    new: bool = Field(description="false when the same bytes had been received already")


@router.post("/uploads", status_code=201, response_model=UploadOut,
             summary="Start an upload session: a file past one request's limit (or on a poor connection) sent in parts",
             responses=error_responses(
                 413, 422, 429, 507, e413="total_bytes: 137438953472 bytes is more than the 68719476736 an upload "
                 "session takes (VOXNERF_MAX_UPLOAD_SESSION_BYTES)",
                 e429="16 upload sessions are open (VOXNERF_MAX_UPLOAD_SESSIONS): complete or delete one, or wait "
                 "for one to expire"))
def create_upload(body: UploadCreate, settings: SettingsDep, principal: PrincipalDep, response: Response) -> UploadOut:
    """Open a session for one file of ``total_bytes`` (a zip or a capture, as ``POST /scenes`` takes): 201 with
    its id, its part size and part count, ``Location: /uploads/{id}``. Send each part with ``PUT
    /uploads/{id}/parts/{n}``, then ``POST /uploads/{id}/complete``. A session no part reaches for
    ``VOXNERF_UPLOAD_SESSION_EXPIRY_S`` expires. The session belongs to the token that opens it: another token
    (but an admin) gets 403 on every route of it."""
    staging.split_rule(body.splits)  # 422 for anything but a known rule
    sha256 = sessions.check_sha256(body.sha256, "sha256")
    name = body.filename.replace("\\", "/").rsplit("/", 1)[-1]
    if not name or not name.isprintable():
        raise UploadError(422, "filename: give the file's name, printable, without a directory")
    state = sessions.create(settings, name, body.total_bytes, sha256, body.name, body.splits or None, principal.name)
    response.headers["Location"] = f"/uploads/{state.session.id}"
    return UploadOut.of(state)


@router.get("/uploads/{upload_id}", response_model=UploadOut, summary="An upload session: the parts received",
            responses=error_responses(403, 404, 410, e403=NOT_YOURS_EXAMPLE, e404=SESSION_GONE_EXAMPLE))
def get_upload(upload_id: SessionId, settings: SettingsDep, principal: PrincipalDep) -> UploadOut:
    """What a client resuming after a dropped connection needs: the parts received and those missing."""
    _require_session_owner(settings, upload_id, principal)
    return UploadOut.of(sessions.state(settings, upload_id))


@router.put(
    "/uploads/{upload_id}/parts/{number}",
    response_model=PartOut,
    summary="Send one part (raw body, its SHA-256 in X-Content-SHA256); resending a received part is harmless",
    openapi_extra={"requestBody": {"required": True, "content": {"application/octet-stream": {
        "schema": {"type": "string", "format": "binary"}, "example": "(the part's bytes)"}}}},
    responses=error_responses(
        403, 404, 409, 410, 413, 422, 507, e403=NOT_YOURS_EXAMPLE, e404=SESSION_GONE_EXAMPLE,
        e409="part 3 was received already with other bytes (SHA-256 ...); delete the session to start again",
        e422="part 3: the bytes received hash to 9f86d0..., not to the X-Content-SHA256 sent"),
)
async def put_part(
    upload_id: SessionId,
    number: PartNumber,
    request: Request,
    settings: SettingsDep,
    x_content_sha256: Annotated[str, Header(description="SHA-256 of the part's bytes, 64 hex digits")],
    principal: PrincipalDep,
    response: Response,
) -> PartOut | Response:
    """The bytes of part ``number`` (every part has the session's part size but the last): 201 when new, 200
    when the same bytes had been received already. Its size and SHA-256 are checked before it is kept; a part
    cut off by a dropped connection leaves nothing, so it is simply sent again."""
    declared = sessions.check_sha256(x_content_sha256, "X-Content-SHA256")
    await run_in_threadpool(_require_session_owner, settings, upload_id, principal)
    session, temp = await run_in_threadpool(sessions.incoming_file, settings, upload_id, number)
    temp_path = Path(temp.name)
    digest = hashlib.sha256()
    size = 0
    limit = session.part_size(number)
    try:
        with temp:
            try:
                async for chunk in request.stream():
                    size += len(chunk)
                    if size > limit:
                        raise UploadError(413, f"part {number}: more than the {limit} bytes this part has")
                    digest.update(chunk)
                    temp.write(chunk)
            except ClientDisconnect:  # nobody reads the answer; the client resends the part, none of it is kept
                return Response(status_code=400)
        new = await run_in_threadpool(
            sessions.add_part, settings, upload_id, number, temp_path, size, digest.hexdigest(), declared
        )
    finally:
        temp_path.unlink(missing_ok=True)
    response.status_code = 201 if new else 200
    return PartOut(number=number, sha256=digest.hexdigest(), size=size, new=new)


@router.post(
    "/uploads/{upload_id}/complete",
    status_code=201,
    response_model=SceneOut,
    summary="Join the parts and store the file as POST /scenes stores an upload (the session is then gone)",
    responses={202: {"model": ImportOut, "description": "a capture whose import is queued, as POST /scenes"},
               **error_responses(403, 404, 409, 410, 413, 415, 422, 429, 503, 507, e403=NOT_YOURS_EXAMPLE,
                                 e404=SESSION_GONE_EXAMPLE,
                                 e409="2 of 40 parts not received yet: 17, 31; send them first")},
)
async def complete_upload(
    upload_id: SessionId, request: Request, settings: SettingsDep, celery: CeleryDep, principal: PrincipalDep
) -> SceneOut | JSONResponse:
    """Join the parts (every one must have arrived), check the whole file's SHA-256 when the session has one, and
    validate and store it as ``POST /scenes`` does: 201 with the scene, or 202 with the queued import of a
    capture. The scene (or import) is the session's owner's."""
    await run_in_threadpool(_require_session_owner, settings, upload_id, principal)
    async with upload_slot(request, settings):
        settings.make_dirs()
        handle, name = tempfile.mkstemp(prefix="session-", suffix=".upload", dir=settings.staging_dir)
        joined = Path(name)
        try:
            with open(handle, "wb"):
                pass
            session = await run_in_threadpool(sessions.assemble, settings, upload_id, joined)
            splits = staging.split_rule(session.splits)
            stored = await run_in_threadpool(store_file, settings, joined, session.filename, session.name, splits,
                                             principal)
        finally:
            joined.unlink(missing_ok=True)
    return stored_answer(settings, celery, stored)


@router.delete("/uploads/{upload_id}", status_code=204, summary="Abandon an upload session and its parts",
               responses=error_responses(403, 404, e403=NOT_YOURS_EXAMPLE, e404=SESSION_GONE_EXAMPLE))
def delete_upload(upload_id: SessionId, settings: SettingsDep, principal: PrincipalDep) -> Response:
    """Remove the session and the parts received (an expired one too)."""
    _require_session_owner(settings, upload_id, principal)
    sessions.delete(settings, upload_id)
    return Response(status_code=204)
