"""Dependencies shared by the routes: settings, the Celery client, bearer-token auth, id validation."""

from __future__ import annotations

import secrets
from typing import Annotated

from celery import Celery
from fastapi import Depends, HTTPException, Path, Request

from app.jobstore import ID_RE
from app.settings import Settings


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def get_celery(request: Request) -> Celery:
    return request.app.state.celery


SettingsDep = Annotated[Settings, Depends(get_settings)]
CeleryDep = Annotated[Celery, Depends(get_celery)]

ID_DOC = "32 lowercase hex digits"
SceneId = Annotated[str, Path(pattern=ID_RE.pattern, description=f"scene id, {ID_DOC}")]
JobId = Annotated[str, Path(pattern=ID_RE.pattern, description=f"job id, {ID_DOC}")]


def require_token(request: Request, settings: SettingsDep) -> None:
    """Refuse with 401 unless the request carries ``Authorization: Bearer <VOXNERF_API_TOKEN>`` (when set)."""
    if settings.api_token is None:
        return
    scheme, _, token = request.headers.get("authorization", "").partition(" ")
    expected = settings.api_token.get_secret_value().encode()
    if scheme.lower() != "bearer" or not secrets.compare_digest(token.strip().encode(), expected):
        raise HTTPException(
            status_code=401,
            detail="missing or wrong bearer token: send 'Authorization: Bearer <VOXNERF_API_TOKEN>'",
            headers={"WWW-Authenticate": "Bearer"},
        )
