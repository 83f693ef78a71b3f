"""Refuse what other web sites' pages ask a browser to do here.

A browser names the page behind a request in its ``Origin`` header, on every websocket
handshake and on every request but a plain GET or HEAD. Without this check, any page a
person opened could upload or delete messages through their browser (a form or a
``no-cors`` fetch needs no permission), post a transmitter status, or read the dashboards'
websocket. Requests without an ``Origin`` come from programs (curl, the receiver daemon),
which a browser page cannot pose as: they pass, and the token is what stops them.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterable
from urllib.parse import urlsplit

from starlette.datastructures import Headers
from starlette.types import ASGIApp, Receive, Scope, Send

log = logging.getLogger(__name__)

READ_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
CLOSE_POLICY_VIOLATION = 1008


def same_origin(origin: str, host: str | None) -> bool:
    """Whether a page at ``origin`` is served by this server, reached as ``host``."""
    parts = urlsplit(origin)
    return parts.scheme in {"http", "https"} and host is not None and parts.netloc == host.lower()


class OriginCheck:
    """ASGI middleware: a state-changing request or a websocket from a page of another origin
    (not this server's, nor one of ``allowed``) is refused with 403."""

    def __init__(self, app: ASGIApp, allowed: Iterable[str] = ()) -> None:
        self.app = app
        self.allowed = frozenset(origin.rstrip("/").lower() for origin in allowed)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "websocket" or (
            scope["type"] == "http" and scope["method"] not in READ_METHODS
        ):
            headers = Headers(scope=scope)
            origin = headers.get("origin")
            if origin is not None and not self.admits(origin, headers.get("host")):
                log.warning("refused %s from a page of %s", scope["path"], origin)
                await self.refuse(scope, receive, send, origin)
                return
        await self.app(scope, receive, send)

    def admits(self, origin: str, host: str | None) -> bool:
        return origin.lower() in self.allowed or same_origin(origin.lower(), host)

    @staticmethod
    async def refuse(scope: Scope, receive: Receive, send: Send, origin: str) -> None:
        detail = (
            f"refused: a page of {origin} may not change anything here; open this server's "
            "own pages, or add the origin to the server's allowed_origins"
        )
        if scope["type"] == "websocket":
            await receive()  # websocket.connect; closing before accepting answers 403
            await send({"type": "websocket.close", "code": CLOSE_POLICY_VIOLATION})
            return
        body = json.dumps({"detail": detail}).encode()
        await send(
            {
                "type": "http.response.start",
                "status": 403,
                "headers": [
                    (b"content-type", b"application/json"),
                    (b"content-length", str(len(body)).encode()),
                ],
            }
        )
        await send({"type": "http.response.body", "body": body})
