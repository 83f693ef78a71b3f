"""The HTTP and websocket API, one module per resource: REST under ``/api``, websockets under
``/ws``, health and metrics at the root."""

from fastapi import APIRouter

from eventocc.server.api import (
    dashboards,
    frames,
    health,
    messages,
    profiles,
    receivers,
    receptions,
    transmitter,
)

rest = APIRouter(prefix="/api")
for module in (messages, frames, profiles, transmitter, receptions, receivers):
    rest.include_router(module.router)

sockets = APIRouter(prefix="/ws")
for module in (receivers, dashboards, transmitter):
    sockets.include_router(module.sockets)

api_router = APIRouter()
for part in (rest, sockets, health.router):
    api_router.include_router(part)
