"""Who may talk to the service: loopback only without a token, its own host names only, no cross-site state
changes, safe headers.

:class:`RequestGuardMiddleware` (pure ASGI, outermost) applies these rules to every HTTP request:

1. **Closed by default**: with no token (neither ``VOXNERF_API_TOKEN`` nor an active named token of
   ``voxnerf tokens create``, :func:`app.core.tokens.service_has_token`) and no
   ``VOXNERF_ALLOW_UNAUTHENTICATED_REMOTE``, a client that is not on this machine gets 403, whatever way the app
   is served (``voxnerf serve``, ``uvicorn --factory``, a container's published port). A request that carries
   ``Forwarded``, ``Via`` or any ``X-Forwarded-*`` header came through a proxy and counts as remote, unless it
   comes from an address of ``VOXNERF_TRUSTED_PROXIES``: then the client is the address that proxy names
   (:func:`request_is_local`).
2. **Its own host names only**: a ``Host`` header other than ``localhost``, a loopback address or a name of
   ``VOXNERF_ALLOWED_HOSTS`` gets 400, token or not. A web page on ``evil.example`` that re-resolves its name
   to 127.0.0.1 (DNS rebinding) is same-origin to the browser, so only the ``Host`` it sends tells it apart.
3. **No cross-site writes**: a POST, PUT, PATCH or DELETE whose ``Sec-Fetch-Site`` is ``cross-site``, or whose
   ``Origin`` is not the origin named by its ``Host``, gets 403, with or without a token. A web page can send a
   multipart form to 127.0.0.1 ("simple" requests need no pre-flight); browsers mark it with these headers.
   Requests without ``Origin`` (curl, scripts) and the dashboard's own same-origin fetches pass.
4. **Headers**: every response carries ``X-Content-Type-Options: nosniff``, ``X-Frame-Options: DENY`` and a
   Content-Security-Policy that allows only the service's own scripts, styles and connections (images and
   videos also from ``blob:``, which the dashboard makes from fetched files) and no framing.

:func:`check_bind` is the same rule at start-up, for the address a server binds; :func:`log_exposure` says
at start-up which clients will be served. :data:`SERVER_OPTIONS` is how every entry point runs uvicorn: with
its own reading of ``X-Forwarded-For`` off, so that rule 1 alone decides what a proxy's headers mean.
"""

from __future__ import annotations

import ipaddress
import json
import logging
from collections.abc import Iterable, Sequence
from urllib.parse import urlsplit

import anyio.to_thread
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from app.core import tokens
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
    "no VOXNERF_API_TOKEN is set and no named token is active, so this service answers only loopback clients: "
    "set a token or make one with voxnerf tokens create (or VOXNERF_ALLOW_UNAUTHENTICATED_REMOTE=1 to serve "
    "everyone without one)"
)
CROSS_SITE_REFUSED = "cross-site request refused: {why} (state-changing requests must come from this origin)"
PROXIED_REFUSED = (
    "this request came through a proxy ({headers}) from {peer}, which VOXNERF_TRUSTED_PROXIES does not name, so "
    "it counts as a remote client; no VOXNERF_API_TOKEN is set and no named token is active, so only loopback "
    "clients are answered"
)
HOST_REFUSED = (
    "Host {host!r} is not a name this service answers to (a web page that re-resolves its own name to this "
    "machine sends it): use localhost, 127.0.0.1 or [::1], or add the name to VOXNERF_ALLOWED_HOSTS"
)
# uvicorn's options for every entry point: it must not rewrite the client address from X-Forwarded-For (it
# trusts 127.0.0.1 by default); RequestGuardMiddleware reads the proxy headers itself.
SERVER_OPTIONS = {"proxy_headers": False}


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


def _proxy_header_names(headers: Iterable[tuple[bytes, bytes]]) -> list[str]:
    """The proxy headers among ``headers`` (lower-case names): ``Forwarded``, ``Via``, ``X-Forwarded-*``."""
    names = {name.lower() for name, _ in headers}
    found = [n for n in names if n in (b"forwarded", b"via") or n.startswith(b"x-forwarded-")]
    return sorted(n.decode("latin-1") for n in found)


def _joined(headers: Iterable[tuple[bytes, bytes]], name: bytes) -> str:
    """Every ``name`` header's value, in order, joined by commas (a header may be sent more than once)."""
    return ",".join(value.decode("latin-1") for key, value in headers if key.lower() == name)


def _forwarded_for(headers: Sequence[tuple[bytes, bytes]]) -> list[str]:
    """The client addresses the proxies named, nearest proxy last: each ``for=`` of ``Forwarded`` (RFC 7239)
    when it has any, else ``X-Forwarded-For``; ports and brackets removed (``"[::1]:80"`` -> ``::1``)."""
    forwarded = _joined(headers, b"forwarded")
    found = []
    for element in forwarded.split(","):
        for pair in element.split(";"):
            key, _, value = pair.strip().partition("=")
            if key.strip().lower() == "for":
                found.append(value.strip().strip('"'))
    if not found:
        found = [entry.strip() for entry in _joined(headers, b"x-forwarded-for").split(",") if entry.strip()]
    return [_address_of(entry) for entry in found]


def _address_of(node: str) -> str:
    """The address of a proxy header's node: ``1.2.3.4:5`` -> ``1.2.3.4``, ``[::1]:5`` -> ``::1``; anything
    else (``unknown``, an obfuscated ``_name``, a bare IPv6 address) as it is."""
    if node.startswith("["):
        return node[1:].partition("]")[0]
    host, colon, port = node.rpartition(":")
    return host if colon and port.isdigit() and ":" not in host else node


def _in_networks(address: str, networks: Sequence[ipaddress.IPv4Network | ipaddress.IPv6Network]) -> bool:
    try:
        parsed = ipaddress.ip_address(address)
    except ValueError:
        return False
    parsed = getattr(parsed, "ipv4_mapped", None) or parsed
    return any(parsed in network for network in networks)


def request_is_local(
    client: tuple[str, int] | None,
    headers: Sequence[tuple[bytes, bytes]],
    trusted_proxies: Sequence[ipaddress.IPv4Network | ipaddress.IPv6Network],
) -> bool:
    """Whether a request comes from this machine (the one rule: no token needed when it does).

    A peer that is not one of ``trusted_proxies``: local when it is (:func:`is_local_client`) and the request
    carries no ``Forwarded``, ``Via`` or ``X-Forwarded-*`` header (with one it came through a proxy, and every
    client of a proxy on this machine would look local). A trusted proxy: local only when the client it names
    (the nearest address in ``Forwarded``'s ``for=`` or in ``X-Forwarded-For`` that is not itself a trusted
    proxy; the farthest when all are) is loopback; a request from it that names no client is remote."""
    if client is None or not _in_networks(client[0], trusted_proxies):
        return is_local_client(client) and not _proxy_header_names(headers)
    named = _forwarded_for(headers)
    untrusted = [address for address in named if not _in_networks(address, trusted_proxies)]
    return is_loopback(untrusted[-1]) if untrusted else bool(named) and is_loopback(named[0])


def host_allowed(host: str | None, allowed_hosts: Sequence[str]) -> bool:
    """Whether a ``Host`` header names this service: ``localhost`` or a loopback address (any port), or an
    entry of ``allowed_hosts`` (a name, ``*.example.org`` for its subdomains, ``*`` for any). No header,
    or one that is no host name, is refused."""
    try:
        name = urlsplit(f"//{host}").hostname if host else None
    except ValueError:
        return False
    if not name or "/" in host or "@" in host:
        return False
    name = name.rstrip(".")
    if is_loopback(name):
        return True
    for entry in (e.lower().strip("[]").rstrip(".") for e in allowed_hosts):
        if entry == "*" or name == entry or (entry.startswith("*.") and name.endswith(entry[1:])):
            return True
    return False


def remote_allowed(settings: Settings) -> bool:
    """Whether clients beyond loopback may be served: the opt-out is set, or the service has a token
    (``VOXNERF_API_TOKEN`` or an active named token: the job store is read, so call it off the event loop)."""
    return settings.allow_unauthenticated_remote or tokens.service_has_token(settings)


def check_bind(host: str, settings: Settings) -> None:
    """Refuse (:class:`UnsafeBindError`) to serve on a non-loopback ``host`` without a token (``VOXNERF_API_TOKEN``
    or an active named token) unless the opt-out is set; with the opt-out, log a WARNING. Call before anything
    starts."""
    if is_loopback(host) or remote_allowed(settings):
        return
    raise UnsafeBindError(
        f"refusing to serve on {host} without VOXNERF_API_TOKEN or a named token: set a token or make one with "
        "voxnerf tokens create, bind 127.0.0.1, or set VOXNERF_ALLOW_UNAUTHENTICATED_REMOTE=1 to let anyone who "
        "reaches the port control the service"
    )


def log_exposure(settings: Settings) -> None:
    """At start-up: say who will be served; a loud WARNING when remote clients need no token."""
    has_token = tokens.service_has_token(settings)
    if has_token:
        log.info("a token is set (VOXNERF_API_TOKEN or a named token): every endpoint but /healthz and the "
                 "dashboard shell needs one")
    elif settings.allow_unauthenticated_remote:
        log.warning(
            "SERVING WITHOUT AUTHENTICATION TO EVERY CLIENT (VOXNERF_ALLOW_UNAUTHENTICATED_REMOTE is set, no "
            "VOXNERF_API_TOKEN): anyone who can reach this port can upload, train, render and delete"
        )
    else:
        log.info("no API token set: answering loopback clients only")
    if not has_token and "*" in settings.allowed_hosts:
        log.warning("VOXNERF_ALLOWED_HOSTS holds '*' and no VOXNERF_API_TOKEN is set: any web page whose name "
                    "resolves to this machine (DNS rebinding) can use the service")


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


async def _refuse(send: Send, detail: str, status: int = 403) -> None:
    body = json.dumps({"detail": detail}).encode()
    headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
    await send({"type": "http.response.start", "status": status, "headers": headers + SECURITY_HEADERS})
    await send({"type": "http.response.body", "body": body})


class RequestGuardMiddleware:
    """The four rules of this module for ``settings`` (see the module docstring)."""

    def __init__(self, app: ASGIApp, settings: Settings) -> None:
        self.app = app
        self.settings = settings
        self.trusted_proxies = [ipaddress.ip_network(e, strict=False) for e in settings.trusted_proxies]

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        client = scope.get("client")
        if not request_is_local(client, scope["headers"], self.trusted_proxies) and not (
            await anyio.to_thread.run_sync(remote_allowed, self.settings)
        ):
            await _refuse(send, self._remote_refusal(client, scope["headers"]))
            return
        headers = {name.lower(): value for name, value in scope["headers"]}
        host = headers[b"host"].decode("latin-1") if b"host" in headers else None
        in_process = client is not None and client[0] in IN_PROCESS_CLIENTS  # no network, so no browser
        if not in_process and not host_allowed(host, self.settings.allowed_hosts):
            await _refuse(send, HOST_REFUSED.format(host=host or ""), status=400)
            return
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

    def _remote_refusal(self, client: tuple[str, int] | None, headers: Sequence[tuple[bytes, bytes]]) -> str:
        """Why a request is refused as remote: it came through a proxy that is not trusted, or its client
        (the peer, or the one a trusted proxy named) is not on this machine."""
        proxied = _proxy_header_names(headers)
        if proxied and (client is None or not _in_networks(client[0], self.trusted_proxies)):
            peer = client[0] if client else "a Unix socket"
            return PROXIED_REFUSED.format(headers=", ".join(proxied), peer=peer)
        return REMOTE_REFUSED
