"""Dependencies shared by the routes: settings, the Celery client, bearer-token auth, id validation."""

from __future__ import annotations

import secrets
from typing import Annotated

from celery import Celery
from fastapi import Depends, HTTPException, Path, Request

from app.core.jobstore import ID_RE
from app.core.settings import Settings
from app.core.tokens import LEGACY_ADMIN, LOCAL


def app_settings(request: Request) -> Settings:
    """The settings this app was built with (``create_app(settings)``; the environment's by default)."""
    return request.app.state.settings


def app_celery(request: Request) -> Celery:
    """The app's Celery client (publishing only)."""
    return request.app.state.celery


SettingsDep = Annotated[Settings, Depends(app_settings)]
CeleryDep = Annotated[Celery, Depends(app_celery)]

ID_DOC = "32 lowercase hex digits"
SceneId = Annotated[str, Path(pattern=ID_RE.pattern, description=f"scene id, {ID_DOC}")]
JobId = Annotated[str, Path(pattern=ID_RE.pattern, description=f"job id, {ID_DOC}")]


def has_valid_token(request: Request, settings: Settings) -> bool:
    """Whether the request may act as the token holder: ``Authorization: Bearer <VOXNERF_API_TOKEN>``, or
    any request when no token is set (the service then answers loopback clients only)."""
    if settings.api_token is None:
        return True
    scheme, _, token = request.headers.get("authorization", "").partition(" ")
    expected = settings.api_token.get_secret_value().encode()
    return scheme.lower() == "bearer" and secrets.compare_digest(token.strip().encode(), expected)


def require_token(request: Request, settings: SettingsDep) -> None:
    """Refuse with 401 unless the request carries ``Authorization: Bearer <VOXNERF_API_TOKEN>`` (when set)."""
    if not has_valid_token(request, settings):
        raise HTTPException(
            status_code=401,
            detail="missing or wrong bearer token: send 'Authorization: Bearer <VOXNERF_API_TOKEN>'",
            headers={"WWW-Authenticate": "Bearer"},
        )


def principal_name(request: Request, settings: Settings) -> str:
    """The name of who makes the request (recorded on what it creates; its webhook secret signs the deliveries):
    the authenticated principal's, else ``admin`` (the API token's holder) or ``local`` (no token set)."""
    principal = getattr(request.state, "principal", None)
    if principal is not None:
        return principal.name
    return LEGACY_ADMIN if settings.api_token is not None else LOCAL
