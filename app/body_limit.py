"""ASGI middleware bounding request bodies while they stream in (413 with a JSON ``detail``), and counting them.

The limit is checked against ``Content-Length`` before the first byte is read and against the bytes
received so far, so an oversized upload is cut off without being buffered anywhere.
"""

from __future__ import annotations

from collections.abc import Callable

from fastapi import HTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send


class BodyLimitMiddleware:
    """``limit_for(method, path) -> bytes`` picks the limit of each request."""

    def __init__(self, app: ASGIApp, limit_for: Callable[[str, str], int]) -> None:
        self.app = app
        self.limit_for = limit_for

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        limit = self.limit_for(scope["method"], scope["path"])
        too_large = HTTPException(413, f"request body larger than {limit} bytes")
        declared = dict(scope["headers"]).get(b"content-length")
        received = 0

        async def limited_receive() -> Message:
            nonlocal received
            if declared is not None and declared.isdigit() and int(declared) > limit:
                raise too_large
            message = await receive()
            received += len(message.get("body", b""))
            if received > limit:
                raise too_large
            return message

        await self.app(scope, limited_receive, send)


class BodyCountMiddleware:
    """``count(n)`` for each ``n`` bytes of body received by a request for which ``counts(method, path)`` holds
    (the metrics' upload bytes)."""

    def __init__(self, app: ASGIApp, counts: Callable[[str, str], bool], count: Callable[[int], None]) -> None:
        self.app = app
        self.counts = counts
        self.count = count

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or not self.counts(scope["method"], scope["path"]):
            await self.app(scope, receive, send)
            return

        async def counted_receive() -> Message:
            message = await receive()
            if received := len(message.get("body", b"")):
                self.count(received)
            return message

        await self.app(scope, counted_receive, send)
