"""Webhooks: a job's ``callback_url`` is checked when the job is made, and each of its state changes is POSTed
there, signed, by the API process (:func:`deliver_due`, run every ``webhook_poll_s`` by ``app.main``).

The delivery rows are written beside the job's ``state`` events (:mod:`app.core.events`); here they are sent. One
attempt: the URL's host is resolved and checked again (a host that now resolves to a private address is refused:
DNS rebinding), the request goes to the address that was checked (the ``Host`` header and TLS name stay the URL's),
no redirect is followed, and a 2xx answer delivers it. A failed attempt is retried after ``webhook_retry_s``,
doubling each time, until ``webhook_max_attempts``; every attempt is logged on the delivery
(``GET /jobs/{id}/deliveries``).

The body is ``{"event_id", "job_id", "state", "job"}`` (``job`` as ``GET /jobs/{id}`` returns it at that event),
with the headers ``X-VoxNeRF-Event-Id``, ``X-VoxNeRF-Timestamp`` (UNIX seconds) and ``X-VoxNeRF-Signature:
sha256=<hex HMAC-SHA256(secret, "<timestamp>.<body>")>``, the secret being the creating principal's
(:func:`app.core.tokens.webhook_secret`).
"""

from __future__ import annotations

import asyncio
import hashlib
import hmac
import ipaddress
import json
import logging
import socket
import time
from urllib.parse import urlsplit

import httpx
from fastapi.concurrency import run_in_threadpool

from app.core import events
from app.core.jobstore import JOBS
from app.core.models import WebhookDeliveryRow
from app.core.settings import Settings
from app.core.tokens import TokenError, webhook_secret
from app.schemas import JobOut

log = logging.getLogger(__name__)

SIGNATURE_HEADER = "X-VoxNeRF-Signature"
TIMESTAMP_HEADER = "X-VoxNeRF-Timestamp"
EVENT_ID_HEADER = "X-VoxNeRF-Event-Id"
DELIVERIES_PER_ROUND = 20


class CallbackRefused(ValueError):
    """A callback URL that may not be used (the API answers 422 at job creation; a delivery attempt fails)."""


def _public(address: ipaddress.IPv4Address | ipaddress.IPv6Address) -> bool:
    """Whether an address is a public unicast one: not private, loopback, link-local, multicast, reserved or
    unspecified (an IPv4-mapped IPv6 address is judged as its IPv4 address)."""
    if isinstance(address, ipaddress.IPv6Address) and address.ipv4_mapped is not None:
        address = address.ipv4_mapped
    return address.is_global and not address.is_multicast


def checked_addresses(url: str, allow_private: bool) -> list[str]:
    """The addresses ``url``'s host resolves to, all of them allowed as a webhook target; raises
    :class:`CallbackRefused` naming why not: not http(s), no host, credentials in the URL, a host that does not
    resolve, or one address that is not public while ``allow_private`` is off."""
    parts = urlsplit(url)
    if parts.scheme not in ("http", "https"):
        raise CallbackRefused(f"callback_url must be an http or https URL, not {parts.scheme or 'no'} scheme")
    if not parts.hostname:
        raise CallbackRefused("callback_url names no host")
    if parts.username is not None or parts.password is not None:
        raise CallbackRefused("callback_url must not carry credentials: deliveries are signed instead")
    try:
        port = parts.port or (443 if parts.scheme == "https" else 80)
    except ValueError:
        raise CallbackRefused("callback_url has an invalid port") from None
    try:
        found = socket.getaddrinfo(parts.hostname, port, type=socket.SOCK_STREAM)
    except (socket.gaierror, UnicodeError) as err:
        raise CallbackRefused(f"callback_url host {parts.hostname!r} does not resolve ({err})") from None
    addresses = list(dict.fromkeys(str(info[4][0]).split("%")[0] for info in found))
    if not allow_private:
        refused = [a for a in addresses if not _public(ipaddress.ip_address(a))]
        if refused:
            raise CallbackRefused(
                f"callback_url host {parts.hostname!r} resolves to {', '.join(refused)}: a private, loopback, "
                "link-local or reserved address is not a webhook target unless VOXNERF_WEBHOOK_ALLOW_PRIVATE is set"
            )
    return addresses


def signature(secret: bytes, timestamp: str, body: bytes) -> str:
    """``sha256=<hex HMAC-SHA256(secret, "<timestamp>.<body>")>``, the value of ``X-VoxNeRF-Signature``."""
    return "sha256=" + hmac.new(secret, timestamp.encode() + b"." + body, hashlib.sha256).hexdigest()


def _body(job_id: str, event_seq: int, event_data: dict) -> bytes:
    job = JobOut.from_row(events.job_from_columns(event_data)).model_dump(mode="json")
    return json.dumps({"event_id": event_seq, "job_id": job_id, "state": job["state"], "job": job},
                      separators=(",", ":")).encode()


async def _post(client: httpx.AsyncClient, url: str, address: str, headers: dict, body: bytes) -> int:
    """POST ``body`` to ``url`` connecting to ``address`` (the one checked): the Host header and, for https, the
    TLS server name (SNI and certificate check) stay the URL's host. The answer's status."""
    target = httpx.URL(url)
    pinned = target.copy_with(host=address)
    extensions = {"sni_hostname": target.host} if target.scheme == "https" else {}
    response = await client.post(pinned, content=body, headers={**headers, "Host": target.netloc.decode("ascii")},
                                 extensions=extensions)
    return response.status_code


async def _attempt(settings: Settings, client: httpx.AsyncClient, delivery: WebhookDeliveryRow) -> None:
    """Send one attempt of ``delivery`` (taken) and log it; schedule the next attempt when this one failed."""
    job = await run_in_threadpool(JOBS.get, settings, delivery.job_id)
    event = await run_in_threadpool(events.event, settings, delivery.job_id, delivery.event_seq)
    status, error, final = None, None, False
    if job is None or event is None or not job.callback_url:
        error, final = "the job, its event or its callback_url is gone", True
    else:
        try:
            secret = await run_in_threadpool(webhook_secret, settings, job.created_by or "")
            addresses = await run_in_threadpool(checked_addresses, job.callback_url, settings.webhook_allow_private)
            body = _body(job.id, event.seq, event.data)
            timestamp = str(int(time.time()))
            headers = {
                "Content-Type": "application/json",
                "User-Agent": "VoxNeRF-Webhook",
                EVENT_ID_HEADER: str(event.seq),
                TIMESTAMP_HEADER: timestamp,
                SIGNATURE_HEADER: signature(secret, timestamp, body),
            }
            status = await _post(client, job.callback_url, addresses[0], headers, body)
            if not 200 <= status < 300:
                error = f"the receiver answered HTTP {status}" + (" (redirects are not followed)"
                                                                 if 300 <= status < 400 else "")
        except TokenError as err:  # its maker's token is gone (or VOXNERF_API_TOKEN unset): nothing signs it
            error, final = f"cannot sign: {err}", True
        except CallbackRefused as err:
            error = str(err)
        except httpx.HTTPError as err:
            error = f"{type(err).__name__}: {err}" if str(err) else type(err).__name__
    attempt = delivery.attempts + 1
    retry = None
    if error is not None and not final and attempt < settings.webhook_max_attempts:
        retry = settings.webhook_retry_s * 2 ** (attempt - 1)
    if error is not None:
        log.warning("webhook of job %s, event %s, attempt %d: %s", delivery.job_id, delivery.event_seq, attempt,
                    error)
    await run_in_threadpool(events.record_attempt, settings, delivery, status, error, retry)


async def deliver_due(settings: Settings) -> int:
    """Send every webhook delivery that is due (at most :data:`DELIVERIES_PER_ROUND`, at once), each attempt
    bounded by ``webhook_timeout_s``; how many were attempted."""
    lease_s = 2 * settings.webhook_timeout_s + 30  # another API process leaves a taken delivery alone this long
    taken = await run_in_threadpool(events.take_due_deliveries, settings, lease_s, DELIVERIES_PER_ROUND)
    if not taken:
        return 0
    async with httpx.AsyncClient(timeout=settings.webhook_timeout_s, follow_redirects=False,
                                 trust_env=False) as client:
        await asyncio.gather(*(_attempt(settings, client, delivery) for delivery in taken))
    return len(taken)
