"""Who is asking, and what they may do: named API tokens with scopes, the principal of a request, and the one
scope rule.

A request's **principal** (:class:`Principal`) is resolved by :func:`resolve` from its ``Authorization: Bearer``
header: the legacy ``VOXNERF_API_TOKEN`` is principal ``admin`` (scope admin); a named token (``voxnerf tokens
create``) is its row's name and scope; a service with neither ("tokenless": it answers loopback clients only,
:mod:`app.origin_guard`) treats every request as principal ``local`` with scope admin. Once any named token is
active the service *has a token* exactly as with ``VOXNERF_API_TOKEN``: every request needs one, and remote
clients are served (:func:`service_has_token`).

Scopes (:func:`required_scope`, :func:`scope_refusal`): ``read`` may GET and HEAD; ``write`` may also upload,
train, render, make outputs and imports, and cancel or delete its **own** work (:func:`may_act_on`); ``admin``
may do everything, the token routes (``/tokens``) included, and act on anyone's work.

Tokens are ``vxn_`` and 43 urlsafe characters (32 random bytes), so a leaked one is easy to grep for; only their
SHA-256 is stored (a hash of a high-entropy secret needs no salt or stretching), and the token itself is
shown once, when it is made. Each token also has a random ``webhook_secret`` that signs the webhooks of its work
(:func:`webhook_secret`).
"""

from __future__ import annotations

import contextlib
import hashlib
import hmac
import os
import re
import secrets
import tempfile
import time
from dataclasses import dataclass
from typing import Literal

from sqlalchemy import func, select, update
from sqlalchemy.exc import IntegrityError

from app.core.db import may_hold_rows, session_scope
from app.core.models import TOKEN_SCOPES, TokenRow
from app.core.settings import Settings
from voxnerf.errors import VoxNeRFError

Scope = Literal["read", "write", "admin"]
TOKEN_PREFIX = "vxn_"
TOKEN_BYTES = 32
NAME_RE = re.compile(r"^[a-z0-9][a-z0-9_-]{0,63}$")
LEGACY_ADMIN = "admin"  # the principal of VOXNERF_API_TOKEN
LOCAL = "local"  # the principal of every request to a tokenless service
RESERVED_NAMES = frozenset({LEGACY_ADMIN, LOCAL})
LAST_USED_EVERY_S = 60.0  # last_used_at is written at most this often per token
READ_METHODS = frozenset({"GET", "HEAD"})
TOKEN_ROUTES = "/tokens"  # every path under it needs scope admin
LEGACY_WEBHOOK_MESSAGE = b"voxnerf-webhook"
LOCAL_WEBHOOK_SECRET_FILE = "webhook_secret"


class TokenError(VoxNeRFError):
    """A token request that cannot be done (a bad or taken name, an unknown token); ``status`` is the HTTP answer."""

    def __init__(self, message: str, status: int = 422) -> None:
        super().__init__(message)
        self.status = status


@dataclass(frozen=True)
class Principal:
    """Who a request acts for: ``name`` (a token's name, ``admin`` for ``VOXNERF_API_TOKEN``, ``local`` on a
    tokenless service), its ``scope``, and its own queue limit (None: the service's per-token default)."""

    name: str
    scope: Scope
    max_queued: int | None = None


@dataclass(frozen=True)
class NewToken:
    """A token just made: the only moment its plaintext exists outside the client's hands."""

    name: str
    scope: Scope
    token: str
    webhook_secret: str
    max_queued: int | None
    created_at: float


def token_hash(token: str) -> str:
    """The stored form of a token: its SHA-256, hex."""
    return hashlib.sha256(token.encode()).hexdigest()


def check_name(name: str) -> str:
    """``name`` when it may name a token: a slug (lowercase letters, digits, ``-`` and ``_``, at most 64, starting
    with a letter or digit) that is not one of the built-in principals; TokenError (422) otherwise."""
    if not NAME_RE.match(name):
        raise TokenError(f"token name {name!r}: use 1 to 64 lowercase letters, digits, '-' or '_', starting with a "
                         "letter or digit")
    if name in RESERVED_NAMES:
        raise TokenError(f"token name {name!r} is reserved ({LEGACY_ADMIN!r} is VOXNERF_API_TOKEN's holder, "
                         f"{LOCAL!r} every client of a tokenless service)")
    return name


def create_token(settings: Settings, name: str, scope: str, max_queued: int | None = None) -> NewToken:
    """Make a token ``name`` with ``scope``; its plaintext and webhook secret are in the answer and nowhere else.
    TokenError: a bad name or scope or limit (422), a name given before, revoked or not (409: work is recorded
    under names, so one is never given to a second token)."""
    check_name(name)
    if scope not in TOKEN_SCOPES:
        raise TokenError(f"scope {scope!r}: use one of {', '.join(TOKEN_SCOPES)}")
    if max_queued is not None and max_queued < 1:
        raise TokenError(f"max_queued {max_queued}: a token's queue limit is at least 1")
    token = TOKEN_PREFIX + secrets.token_urlsafe(TOKEN_BYTES)
    row = TokenRow(name=name, scope=scope, token_sha256=token_hash(token), webhook_secret=secrets.token_hex(32),
                   max_queued=max_queued, created_at=time.time())
    try:
        with session_scope(settings) as session:
            if session.scalar(select(TokenRow.id).where(TokenRow.name == name)) is not None:
                raise TokenError(f"a token named {name!r} exists already (revoked or not): names are never reused, "
                                 "since the work it made is recorded under it", status=409)
            session.add(row)
    except IntegrityError:  # made at the same moment by another process
        raise TokenError(f"a token named {name!r} exists already", status=409) from None
    return NewToken(name, scope, token, row.webhook_secret, max_queued, row.created_at)  # type: ignore[arg-type]


def list_tokens(settings: Settings) -> list[TokenRow]:
    """Every token, revoked ones included, oldest first (rows hold no plaintext token)."""
    with session_scope(settings) as session:
        return list(session.scalars(select(TokenRow).order_by(TokenRow.created_at, TokenRow.id)))


def _named(session, name: str) -> TokenRow:
    row = session.scalar(select(TokenRow).where(TokenRow.name == name))
    if row is None:
        raise TokenError(f"no token named {name!r}", status=404)
    return row


def revoke_token(settings: Settings, name: str) -> TokenRow:
    """Revoke token ``name`` (from the next request on, it is answered 401); revoking a revoked token changes
    nothing. TokenError (404) for an unknown name."""
    with session_scope(settings) as session:
        row = _named(session, name)
        if row.revoked_at is None:
            row.revoked_at = time.time()
        return row


def any_active(settings: Settings) -> bool:
    """Whether some named token is not revoked (the service then has a token). A job store that does not exist
    yet has none, and is not created by asking."""
    if not may_hold_rows(settings):
        return False
    with session_scope(settings) as session:
        count = session.scalar(select(func.count()).select_from(TokenRow).where(TokenRow.revoked_at.is_(None)))
    return bool(count)


def service_has_token(settings: Settings) -> bool:
    """Whether requests need a token: ``VOXNERF_API_TOKEN`` is set or a named token is active."""
    return settings.api_token is not None or any_active(settings)


def _bearer(authorization: str | None) -> str | None:
    scheme, _, token = (authorization or "").partition(" ")
    return token.strip() if scheme.lower() == "bearer" and token.strip() else None


def resolve(settings: Settings, authorization: str | None) -> Principal | None:
    """The principal of a request whose ``Authorization`` header is ``authorization``; None when the service
    has a token and the request carries no valid one (unknown, wrong or revoked: the API answers 401)."""
    token = _bearer(authorization)
    legacy = settings.api_token.get_secret_value().encode() if settings.api_token is not None else None
    if token is not None and legacy is not None and secrets.compare_digest(token.encode(), legacy):
        return Principal(LEGACY_ADMIN, "admin")
    if token is not None and token.startswith(TOKEN_PREFIX):
        return _named_principal(settings, token)
    if settings.api_token is None and not any_active(settings):
        return Principal(LOCAL, "admin")
    return None


def _named_principal(settings: Settings, token: str) -> Principal | None:
    """The active token whose hash is ``token``'s, its use noted (at most once a minute); None when there is none."""
    digest = token_hash(token)
    now = time.time()
    with session_scope(settings) as session:
        row = session.scalar(select(TokenRow).where(TokenRow.token_sha256 == digest))
        if row is None or row.revoked_at is not None or not hmac.compare_digest(row.token_sha256, digest):
            return None
        if row.last_used_at is None or now - row.last_used_at >= LAST_USED_EVERY_S:
            session.execute(update(TokenRow).where(TokenRow.id == row.id).values(last_used_at=now))
        return Principal(row.name, row.scope, row.max_queued)  # type: ignore[arg-type]


# ------------------------------------------------------------------------------------------------ the scope rule


def required_scope(method: str, path: str) -> Scope:
    """The scope a request needs: admin for the token routes, read for GET and HEAD, write for anything else."""
    if path == TOKEN_ROUTES or path.startswith(TOKEN_ROUTES + "/"):
        return "admin"
    return "read" if method.upper() in READ_METHODS else "write"


def scope_refusal(principal: Principal, method: str, path: str) -> str | None:
    """Why ``principal`` may not make this request (a sentence for a 403), or None when its scope allows it."""
    needed = required_scope(method, path)
    if TOKEN_SCOPES.index(principal.scope) >= TOKEN_SCOPES.index(needed):
        return None
    return (f"{method.upper()} {path} needs scope {needed}; token {principal.name!r} has scope {principal.scope}")


def may_act_on(principal: Principal, created_by: str | None) -> bool:
    """Whether ``principal`` may cancel or delete work made by ``created_by``: admin anything, others their own
    (work recorded before tokens existed, ``created_by`` null, is the admin's)."""
    return principal.scope == "admin" or (created_by is not None and created_by == principal.name)


def ownership_refusal(principal: Principal, what: str, created_by: str | None, acts: str = "cancel or delete") -> str:
    """The 403 sentence when :func:`may_act_on` says no for ``what`` (``"job <id>"``...), which the principal
    would ``acts`` (``"cancel or delete"``...)."""
    owner = repr(created_by) if created_by else "no token (made before tokens existed)"
    return (f"{what} was made by {owner}; token {principal.name!r} (scope {principal.scope}) may {acts} "
            "only its own work (scope admin acts on all)")


@dataclass(frozen=True)
class QueueQuota:
    """How many rows of each kind of queued work ``principal`` may have queued, and where that limit is set."""

    principal: str
    limit: int
    source: str


def queue_quota(settings: Settings, principal: Principal) -> QueueQuota | None:
    """``principal``'s queue limit: its token's own, else ``VOXNERF_MAX_QUEUED_PER_TOKEN``; None when neither is
    set (only the service-wide limits apply)."""
    if principal.max_queued is not None:
        return QueueQuota(principal.name, principal.max_queued, "set for this token with --max-queued")
    if settings.max_queued_per_token is not None:
        return QueueQuota(principal.name, settings.max_queued_per_token, "VOXNERF_MAX_QUEUED_PER_TOKEN")
    return None


# ------------------------------------------------------------------------------------------------ webhook secrets


def webhook_secret(settings: Settings, principal_name: str) -> bytes:
    """The key that signs the webhooks of work made by ``principal_name``: a named token's ``webhook_secret``;
    for ``admin`` (``VOXNERF_API_TOKEN``) HMAC-SHA256(key=the token, msg=b"voxnerf-webhook"); for ``local`` a
    random secret kept in ``<data_dir>/webhook_secret`` (mode 0600, made on first use). TokenError (404) for a
    name with no token (``admin`` with no ``VOXNERF_API_TOKEN`` set included)."""
    if principal_name == LEGACY_ADMIN:
        if settings.api_token is None:
            raise TokenError("no VOXNERF_API_TOKEN is set, so principal 'admin' has no webhook secret", status=404)
        return hmac.new(settings.api_token.get_secret_value().encode(), LEGACY_WEBHOOK_MESSAGE, "sha256").digest()
    if principal_name == LOCAL:
        return _local_webhook_secret(settings)
    with session_scope(settings) as session:
        return bytes.fromhex(_named(session, principal_name).webhook_secret)


def show_secret(settings: Settings, name: str) -> str:
    """Token ``name``'s webhook secret as stored (hex), for ``voxnerf tokens show-secret``."""
    with session_scope(settings) as session:
        return _named(session, check_name(name)).webhook_secret


def _local_webhook_secret(settings: Settings) -> bytes:
    """``<data_dir>/webhook_secret``'s 32 bytes, made once: written whole to a private temporary file (0600) that
    is then hard-linked into place, which fails when the file exists, so two processes starting together agree
    on the one that won and neither reads a half-written secret."""
    path = settings.data_dir / LOCAL_WEBHOOK_SECRET_FILE
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    if not path.exists():
        fd, temporary = tempfile.mkstemp(prefix=".webhook_secret-", dir=settings.data_dir)  # mode 0600
        try:
            with os.fdopen(fd, "wb") as out:
                out.write(secrets.token_bytes(TOKEN_BYTES))
            with contextlib.suppress(FileExistsError):
                os.link(temporary, path)
        finally:
            os.unlink(temporary)
    secret = path.read_bytes()
    if len(secret) != TOKEN_BYTES:
        raise TokenError(f"{path}: holds {len(secret)} bytes, not a {TOKEN_BYTES}-byte webhook secret (remove it to "
                         "make a new one)", status=500)
    return secret
