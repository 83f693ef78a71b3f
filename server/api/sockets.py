"""What the websocket routes share: reading text frames, and closing with a reason."""

from __future__ import annotations

import contextlib
import logging

from fastapi.websockets import WebSocket, WebSocketDisconnect

log = logging.getLogger(__name__)

CLOSE_BAD_FRAME = 1007
"""A text frame the route cannot read."""
CLOSE_BINARY_FRAME = 1003
"""A binary frame: every route here speaks JSON text."""
MAX_REASON_BYTES = 120
"""A close reason must fit in a control frame (123 bytes, UTF-8)."""


class MalformedFrame(ValueError):
    """A frame the route cannot read: the connection is closed with ``code`` and the reason."""

    def __init__(self, reason: str, code: int = CLOSE_BAD_FRAME) -> None:
        super().__init__(reason)
        self.code = code


async def receive_text(websocket: WebSocket) -> str:
    """The next text frame; ``WebSocketDisconnect`` once the peer has gone, ``MalformedFrame``
    for a binary frame."""
    message = await websocket.receive()
    if message["type"] == "websocket.disconnect":
        raise WebSocketDisconnect(message.get("code", 1000), message.get("reason"))
    text = message.get("text")
    if text is None:
        raise MalformedFrame("send JSON as text frames, not binary ones", CLOSE_BINARY_FRAME)
    return text


def close_reason(text: str) -> str:
    """``text`` cut to what a close frame holds, never inside a UTF-8 sequence."""
    return text.encode()[:MAX_REASON_BYTES].decode(errors="ignore")


async def refuse(websocket: WebSocket, code: int, reason: str) -> None:
    log.warning("refused %s from %s: %s", websocket.url.path, websocket.client, reason)
    with contextlib.suppress(WebSocketDisconnect, RuntimeError):  # it may have gone already
        await websocket.close(code=code, reason=close_reason(reason))
