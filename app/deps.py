"""Dependencies shared by the routes: settings, the Celery client, the request's principal (bearer-token auth and
the scope rule), ownership checks, id validation."""

from __future__ import annotations

from typing import Annotated

from celery import Celery
from fastapi import Depends, HTTPException, Path, Request

from app.core import tokens
from app.core.jobstore import ID_RE
from app.core.settings import Settings
from app.core.tokens import Principal


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


def require_token(request: Request, settings: SettingsDep) -> Principal:
    """The one place a request's principal is resolved (:func:`app.core.tokens.resolve`) and its scope checked
    (:func:`app.core.tokens.scope_refusal`); it is kept in ``request.state.principal``. 401 without a valid
    token when the service has one (a revoked token included), 403 naming the scope needed when the token's
    scope does not reach it."""
    principal = tokens.resolve(settings, request.headers.get("authorization"))
    if principal is None:
        raise HTTPException(
            status_code=401,
            detail="missing, unknown or revoked bearer token: send 'Authorization: Bearer <token>' "
            "(VOXNERF_API_TOKEN, or a token made with voxnerf tokens create)",
            headers={"WWW-Authenticate": "Bearer"},
        )
    route = request.scope.get("route")  # the matched route's template (/tokens/{name}), whatever the mount point
    if why := tokens.scope_refusal(principal, request.method, getattr(route, "path", request.url.path)):
        raise HTTPException(status_code=403, detail=why)
    request.state.principal = principal
    return principal


PrincipalDep = Annotated[Principal, Depends(require_token)]


def require_owner(principal: Principal, what: str, created_by: str | None, acts: str = "cancel or delete") -> None:
    """403 unless ``principal`` may ``acts`` (cancel or delete...) ``what`` (``"job <id>"``...), made by
    ``created_by`` (:func:`app.core.tokens.may_act_on`)."""
    if not tokens.may_act_on(principal, created_by):
        raise HTTPException(status_code=403, detail=tokens.ownership_refusal(principal, what, created_by, acts))
