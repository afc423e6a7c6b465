"""Who may talk to the service: loopback only without a token, no cross-site state changes, safe headers.

:class:`RequestGuardMiddleware` (pure ASGI, outermost) applies three rules to every HTTP request:

1. **Closed by default**: with no ``VOXNERF_API_TOKEN`` (and no ``VOXNERF_ALLOW_UNAUTHENTICATED_REMOTE``),
   a client whose address is not loopback gets 403, whatever way the app is served (``voxnerf serve``,
   ``uvicorn --factory``, a container's published port).
2. **No cross-site writes**: a POST, PUT, PATCH or DELETE whose ``Sec-Fetch-Site`` is ``cross-site``, or whose
   ``Origin`` is not the origin named by its ``Host``, gets 403, with or without a token. A web page can send a
   multipart form to 127.0.0.1 ("simple" requests need no pre-flight); browsers mark it with these headers.
   Requests without ``Origin`` (curl, scripts) and the dashboard's own same-origin fetches pass.
3. **Headers**: every response carries ``X-Content-Type-Options: nosniff``, ``X-Frame-Options: DENY`` and a
   Content-Security-Policy that allows only the service's own scripts, styles and connections (images and
   videos also from ``blob:``, which the dashboard makes from fetched files) and no framing.

:func:`check_bind` is the same rule at start-up, for the address a server binds; :func:`log_exposure` says
at start-up which clients will be served.
"""

from __future__ import annotations

import ipaddress
import json
import logging
from urllib.parse import urlsplit

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from app.core.settings import Settings
from voxnerf.errors import VoxNeRFError

log = logging.getLogger(__name__)

STATE_CHANGING = frozenset({"POST", "PUT", "PATCH", "DELETE"})
DEFAULT_PORTS = {"http": 80, "https": 443}
IN_PROCESS_CLIENTS = frozenset({"testclient"})  # the client address Starlette's TestClient reports
CONTENT_SECURITY_POLICY = (
    "default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' blob:; media-src 'self' blob:; "
    "connect-src 'self'; object-src 'none'; base-uri 'none'; form-action 'self'; frame-ancestors 'none'"
)
SECURITY_HEADERS = [
    (b"content-security-policy", CONTENT_SECURITY_POLICY.encode()),
    (b"x-content-type-options", b"nosniff"),
    (b"x-frame-options", b"DENY"),
]
REMOTE_REFUSED = (
    "no VOXNERF_API_TOKEN is set, so this service answers only loopback clients: set a token "
    "(or VOXNERF_ALLOW_UNAUTHENTICATED_REMOTE=1 to serve everyone without one)"
)
CROSS_SITE_REFUSED = "cross-site request refused: {why} (state-changing requests must come from this origin)"


class UnsafeBindError(VoxNeRFError):
    """A server was asked to listen beyond loopback with no API token and no explicit opt-out."""


def is_loopback(host: str | None) -> bool:
    """True for ``localhost`` and addresses in 127.0.0.0/8 or ::1 (IPv4-mapped included); False otherwise,
    including for an empty or unparsable ``host`` and for ``0.0.0.0`` / ``::`` (every interface)."""
    if not host:
        return False
    if host.lower() == "localhost":
        return True
    try:
        address = ipaddress.ip_address(host.strip("[]"))
    except ValueError:
        return False
    mapped = getattr(address, "ipv4_mapped", None)
    return (mapped or address).is_loopback


def is_local_client(client: tuple[str, int] | None) -> bool:
    """Whether an ASGI ``scope["client"]`` is on this machine: a loopback address, no address (a Unix
    socket), or Starlette's in-process TestClient (no network involved)."""
    return client is None or client[0] in IN_PROCESS_CLIENTS or is_loopback(client[0])


def remote_allowed(settings: Settings) -> bool:
    """Whether clients beyond loopback may be served: a token is set, or the opt-out is."""
    return settings.api_token is not None or settings.allow_unauthenticated_remote


def check_bind(host: str, settings: Settings) -> None:
    """Refuse (:class:`UnsafeBindError`) to serve on a non-loopback ``host`` without a token unless the
    opt-out is set; with the opt-out, log a WARNING. Call before anything starts."""
    if is_loopback(host) or settings.api_token is not None:
        return
    if not settings.allow_unauthenticated_remote:
        raise UnsafeBindError(
            f"refusing to serve on {host} without VOXNERF_API_TOKEN: set a token, bind 127.0.0.1, or set "
            "VOXNERF_ALLOW_UNAUTHENTICATED_REMOTE=1 to let anyone who reaches the port control the service"
        )


def log_exposure(settings: Settings) -> None:
    """At start-up: say who will be served; a loud WARNING when remote clients need no token."""
    if settings.api_token is not None:
        log.info("API token set: every endpoint but /healthz and the dashboard shell needs it")
    elif settings.allow_unauthenticated_remote:
        log.warning(
            "SERVING WITHOUT AUTHENTICATION TO EVERY CLIENT (VOXNERF_ALLOW_UNAUTHENTICATED_REMOTE is set, no "
            "VOXNERF_API_TOKEN): anyone who can reach this port can upload, train, render and delete"
        )
    else:
        log.info("no API token set: answering loopback clients only")


def _origin_key(scheme: str, netloc: str) -> tuple[str, int | None] | None:
    """``(hostname, port)`` of ``scheme://netloc``, the scheme's default port filled in; None if unparsable."""
    try:
        parts = urlsplit(f"{scheme}://{netloc}")
        port = parts.port or DEFAULT_PORTS.get(scheme)
    except ValueError:
        return None
    return (parts.hostname, port) if parts.hostname else None


def cross_site_reason(method: str, headers: dict[bytes, bytes]) -> str | None:
    """Why a request is a cross-site state change (a sentence), or None when it may pass.

    ``headers``: the request's headers, lower-case names. The ``Origin`` must name the same host and port
    as ``Host`` (the scheme is the origin's own: a TLS proxy in front keeps the ``Host``)."""
    if method not in STATE_CHANGING:
        return None
    if headers.get(b"sec-fetch-site", b"").decode("latin-1").lower() == "cross-site":
        return "Sec-Fetch-Site is cross-site"
    origin = headers.get(b"origin")
    if origin is None:
        return None
    origin_text = origin.decode("latin-1")
    scheme, _, netloc = origin_text.partition("://")
    host = headers.get(b"host", b"").decode("latin-1")
    own = _origin_key(scheme.lower(), host) if scheme.lower() in DEFAULT_PORTS else None
    if own is None or _origin_key(scheme.lower(), netloc) != own:
        return f"Origin {origin_text!r} is not this service's ({host or 'no Host header'})"
    return None


async def _refuse(send: Send, detail: str) -> None:
    body = json.dumps({"detail": detail}).encode()
    headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
    await send({"type": "http.response.start", "status": 403, "headers": headers + SECURITY_HEADERS})
    await send({"type": "http.response.body", "body": body})


class RequestGuardMiddleware:
    """The three rules of this module for ``settings`` (see the module docstring)."""

    def __init__(self, app: ASGIApp, settings: Settings) -> None:
        self.app = app
        self.settings = settings

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        if not remote_allowed(self.settings) and not is_local_client(scope.get("client")):
            await _refuse(send, REMOTE_REFUSED)
            return
        headers = {name.lower(): value for name, value in scope["headers"]}
        if why := cross_site_reason(scope["method"], headers):
            await _refuse(send, CROSS_SITE_REFUSED.format(why=why))
            return

        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                present = {name.lower() for name, _ in message.get("headers", [])}
                extra = [(name, value) for name, value in SECURITY_HEADERS if name not in present]
                message = {**message, "headers": [*message.get("headers", []), *extra]}
            await send(message)

        await self.app(scope, receive, send_with_headers)
