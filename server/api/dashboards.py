"""``/ws/dashboard``: a read-only fan-out of every update (see ``eventocc.server.hub``)."""

from __future__ import annotations

import asyncio
import contextlib

from fastapi import APIRouter
from fastapi.websockets import WebSocket

from eventocc.server.api.deps import LiveDep

CLOSE_STALLED = 1013
"""A dashboard that fell too far behind (it may reconnect)."""

sockets = APIRouter(tags=["dashboards"])


@sockets.websocket("/dashboard")
async def dashboard_socket(websocket: WebSocket, live: LiveDep) -> None:
    await websocket.accept()
    viewer = live.hub.subscribe(f"{websocket.client}")
    tasks = {
        asyncio.create_task(live.hub.serve(viewer, websocket.send_text)),
        asyncio.create_task(_until_closed(websocket)),
        asyncio.create_task(viewer.wait_evicted()),
    }
    try:
        await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for task in tasks:
            task.cancel()
        live.hub.unsubscribe(viewer)
    if viewer.evicted:
        with contextlib.suppress(Exception):
            await asyncio.wait_for(websocket.close(CLOSE_STALLED, "too slow, reconnect"), 1.0)


async def _until_closed(websocket: WebSocket) -> None:
    """Viewers send nothing we need, text or binary: this only notices them go."""
    while (await websocket.receive())["type"] != "websocket.disconnect":
        pass
