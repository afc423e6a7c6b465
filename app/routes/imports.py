"""``/imports``: capture imports queued by ``POST /scenes`` (a ROS bag): list, follow, cancel. The scene an import
makes is named by its ``scene_id`` once it has succeeded. The lifecycle is :mod:`app.core.imports`'."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Path, Query

from app.api_reference import EXAMPLE_ID, error_responses
from app.core import jobstore
from app.core.imports import IMPORTS, remove_raw
from app.deps import ID_DOC, PrincipalDep, SettingsDep
from app.routes import work
from app.schemas import ImportOut, JobState

router = APIRouter(tags=["imports"])
ImportId = Annotated[str, Path(pattern=jobstore.ID_RE.pattern, description=f"import id, {ID_DOC}")]


@router.get("/imports", response_model=list[ImportOut], summary="List capture imports, newest first")
def list_imports(
    settings: SettingsDep,
    state: Annotated[JobState | None, Query(description="only imports in this state")] = None,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
) -> list[ImportOut]:
    """The capture imports ``POST /scenes`` queued (videos, photos, ROS bags, Stray recordings), newest first."""
    return [ImportOut.from_row(row) for row in IMPORTS.newest(settings, limit, state=state)]


@router.get("/imports/{import_id}", response_model=ImportOut, summary="State, stage and progress of an import",
            responses=error_responses(404, e404=f"no import {EXAMPLE_ID}"))
def get_import(import_id: ImportId, settings: SettingsDep) -> ImportOut:
    """The import's state, stage and progress; once it has succeeded, ``scene_id`` names the scene it made and
    ``summary`` is what its importer wrote."""
    return ImportOut.from_row(work.found(settings, IMPORTS, import_id))


@router.post("/imports/{import_id}/cancel", status_code=202, response_model=ImportOut, summary="Cancel an import",
             responses=error_responses(404, 409, e404=f"no import {EXAMPLE_ID}",
                                       e409=f"import {EXAMPLE_ID} already succeeded"))
def cancel_import(import_id: ImportId, settings: SettingsDep, principal: PrincipalDep) -> ImportOut:
    """A queued import is cancelled at once; a running one when its worker next checks (between the importer's
    stages). The raw capture of one cancelled while queued goes at once. 403 for another token's import (scope
    write), 409 for one that has already succeeded or failed."""
    row = work.cancel(settings, IMPORTS, import_id, principal)
    if row.state == "cancelled" and row.started_at is None:  # no worker ever held it: none will remove it
        remove_raw(settings, import_id)
    return ImportOut.from_row(row)
