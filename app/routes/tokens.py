"""``/tokens``: named API tokens for admins (scope admin: :func:`app.core.tokens.required_scope`): list them, make
one (its token and webhook secret are answered once), revoke one. ``voxnerf tokens`` does the same on the
service's database from the command line."""

from __future__ import annotations

import logging

from fastapi import APIRouter, HTTPException, Path, Response

from app.api_reference import error_responses
from app.core import tokens
from app.deps import PrincipalDep, SettingsDep
from app.schemas import TokenCreate, TokenCreated, TokenOut

log = logging.getLogger(__name__)
router = APIRouter(tags=["tokens"])


@router.get("/tokens", response_model=list[TokenOut], summary="List named tokens, revoked ones included (admin)")
def list_tokens(settings: SettingsDep) -> list[TokenOut]:
    """Every named token: its name, scope, queue limit, when it was made and revoked; never the token itself."""
    return [TokenOut.from_row(row) for row in tokens.list_tokens(settings)]


@router.post("/tokens", status_code=201, response_model=TokenCreated,
             summary="Make a named token; the answer holds the token and its webhook secret, once (admin)",
             responses=error_responses(409, 422, e409="a token named 'ci' exists already (revoked or not): names are "
                                       "never reused, since the work it made is recorded under it",
                                       e422="token name 'CI!': use 1 to 64 lowercase letters, digits, '-' or '_', "
                                       "starting with a letter or digit"))
def create_token(body: TokenCreate, settings: SettingsDep, principal: PrincipalDep) -> TokenCreated:
    """422 for a bad name, 409 for a name given before (revoked or not)."""
    try:
        made = tokens.create_token(settings, body.name, body.scope, body.max_queued)
    except tokens.TokenError as err:
        raise HTTPException(err.status, str(err)) from None
    log.info("token %r (scope %s) made by %r", made.name, made.scope, principal.name)
    return TokenCreated.from_new(made)


@router.delete("/tokens/{name}", status_code=204, summary="Revoke a named token: refused with 401 from now on (admin)",
               responses=error_responses(404, e404="no token named 'ci'"))
def revoke_token(
    name: str = Path(max_length=64, description="the token's name"), *, settings: SettingsDep, principal: PrincipalDep
) -> Response:
    """404 for an unknown name; revoking a revoked token changes nothing."""
    try:
        tokens.revoke_token(settings, name)
    except tokens.TokenError as err:
        raise HTTPException(err.status, str(err)) from None
    log.info("token %r revoked by %r", name, principal.name)
    return Response(status_code=204)
