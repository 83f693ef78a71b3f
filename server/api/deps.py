"""Dependencies shared by the routers: the app's state, fetch-or-404, the write token."""

from __future__ import annotations

import secrets
from typing import Annotated

from fastapi import Depends, HTTPException, Path, Query, Request, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from starlette.requests import HTTPConnection

from eventocc.occ.marker import MAX_CELLS, MIN_CELLS
from eventocc.server.api.encoding import EncoderCache
from eventocc.server.api.schemas import MESSAGE_ID_PATTERN
from eventocc.server.api.state import LiveState
from eventocc.server.api.uploads import UploadBudget
from eventocc.server.settings import Settings
from eventocc.server.store import MessageStore, StoredMessage


def get_store(request: Request) -> MessageStore:
    return request.app.state.store


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def get_encoders(request: Request) -> EncoderCache:
    return request.app.state.encoders


def get_upload_budget(request: Request) -> UploadBudget:
    return request.app.state.upload_budget


def get_live(connection: HTTPConnection) -> LiveState:
    """Also for websockets, hence the connection rather than a request."""
    return connection.app.state.live


StoreDep = Annotated[MessageStore, Depends(get_store)]
SettingsDep = Annotated[Settings, Depends(get_settings)]
EncodersDep = Annotated[EncoderCache, Depends(get_encoders)]
LiveDep = Annotated[LiveState, Depends(get_live)]
UploadBudgetDep = Annotated[UploadBudget, Depends(get_upload_budget)]


def get_message(
    store: StoreDep,
    message_id: Annotated[str, Path(pattern=MESSAGE_ID_PATTERN, description="Message id.")],
) -> StoredMessage:
    message = store.get(message_id)
    if message is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"no message with id {message_id!r}")
    return message


MessageDep = Annotated[StoredMessage, Depends(get_message)]

CellsQuery = Annotated[
    int | None, Query(ge=MIN_CELLS, le=MAX_CELLS, description="Payload cells across (N).")
]

_bearer = HTTPBearer(auto_error=False, description="Needed for writes when a token is configured.")


def require_write_token(
    settings: SettingsDep,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> None:
    if settings.token is None:
        return
    expected = settings.token.get_secret_value().encode()
    given = credentials.credentials.encode() if credentials else b""
    if not secrets.compare_digest(given, expected):
        raise HTTPException(
            status.HTTP_401_UNAUTHORIZED,
            "this server needs 'Authorization: Bearer <token>' for writes",
            headers={"WWW-Authenticate": "Bearer"},
        )
