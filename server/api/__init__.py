"""The REST API, mounted under ``/api``: one router per resource."""

from fastapi import APIRouter

from eventocc.server.api import frames, messages, profiles, transmitter

api_router = APIRouter(prefix="/api")
for module in (messages, frames, profiles, transmitter):
    api_router.include_router(module.router)
