"""``/api/messages``: upload, list, read, download and delete messages.

Every upload gets a new id, even for bytes already stored: a message is the bytes *plus* its
name, profile and cell count. The bytes themselves are stored once per sha256.
"""

from __future__ import annotations

import unicodedata
from pathlib import PurePosixPath
from typing import Annotated

from fastapi import APIRouter, Depends, HTTPException, Query, Request, Response, status
from starlette.concurrency import run_in_threadpool

from eventocc.server.api.deps import (
    CellsQuery,
    MessageDep,
    SettingsDep,
    StoreDep,
    UploadBudgetDep,
    require_write_token,
)
from eventocc.server.api.downloads import download
from eventocc.server.api.encoding import describe, link_facts, new_encoder
from eventocc.server.api.schemas import MessagePublic, MessagesPublic, MessageText, ProfileName
from eventocc.server.api.uploads import UPLOAD_MEDIA_TYPES, read_upload
from eventocc.server.store import StoredMessage

router = APIRouter(prefix="/messages", tags=["messages"])

MAX_NAME_BYTES = 255
"""A file name's limit on common file systems, in UTF-8 bytes (the link's too)."""
INVISIBLE = frozenset({"Cc", "Cf", "Cs", "Zl", "Zp"})
"""Unicode categories a name may not hold: controls (C0, DEL, C1), format characters (among
them the bidirectional override U+202E, which shows ``evil<U+202E>txt.exe`` as
``evilexe.txt``), surrogates, and line and paragraph separators."""
JOINERS = frozenset("\u200c\u200d")
"""The two format characters scripts and emoji need in names."""

UPLOAD_BODY = {
    "required": True,
    "content": {
        "application/octet-stream": {"schema": {"type": "string", "format": "binary"}},
        "multipart/form-data": {
            "schema": {
                "type": "object",
                "properties": {"file": {"type": "string", "format": "binary"}},
                "required": ["file"],
            }
        },
        "application/json": {"schema": MessageText.model_json_schema()},
    },
}


def clean_name(name: str) -> str:
    """The file name without any directory part; 422 if nothing usable is left."""
    base = PurePosixPath(name.replace("\\", "/")).name.strip()
    hidden = [c for c in base if unicodedata.category(c) in INVISIBLE and c not in JOINERS]
    size = len(base.encode(errors="replace"))
    if hidden:
        because = f"{_describe(hidden[0])} is not shown as itself"
    elif base in {"", ".", ".."}:
        because = "no file name is left"
    elif size > MAX_NAME_BYTES:
        because = f"it is {size} bytes of UTF-8"
    else:
        return base
    raise HTTPException(
        status.HTTP_422_UNPROCESSABLE_CONTENT,
        f"bad message name {name!r} ({because}): give a file name of 1..{MAX_NAME_BYTES} "
        "bytes of UTF-8 without control or format characters",
    )


def _describe(char: str) -> str:
    return f"U+{ord(char):04X} ({unicodedata.name(char, 'a control character')})"


@router.post(
    "",
    status_code=status.HTTP_201_CREATED,
    dependencies=[Depends(require_write_token)],
    openapi_extra={"requestBody": UPLOAD_BODY},
    responses={
        413: {"description": "The message is over the upload limit."},
        503: {"description": "Other uploads hold the server's upload memory: retry later."},
        415: {"description": f"Content-Type is not one of {', '.join(UPLOAD_MEDIA_TYPES)}."},
        422: {"description": "Empty message, malformed body or unusable options."},
    },
)
async def create_message(
    request: Request,
    response: Response,
    store: StoreDep,
    settings: SettingsDep,
    budget: UploadBudgetDep,
    name: Annotated[str | None, Query(description="Defaults to the uploaded file's name.")] = None,
    profile: ProfileName | None = None,
    cells: CellsQuery = None,
) -> MessagePublic:
    """Store a message: a raw body, a multipart ``file`` or JSON ``{"text": ...}``.

    Every upload gets a new id; identical bytes are stored once (content-addressed by sha256).
    A message the link format cannot send with this profile and cell count is refused (422)."""
    with budget.claim() as claim:  # until the message is stored
        upload = await read_upload(request, settings.max_upload_bytes, claim)
        if name is None:
            name = upload.filename or ("message.txt" if upload.is_text else "message.bin")
        name = clean_name(name)
        profile_name = profile.value if profile else settings.default_profile
        cells = cells or settings.default_cells

        def encode_and_store() -> StoredMessage:  # CPU and disk work: off the event loop
            # The encoder is built first, so a message the link refuses is never stored.
            encoder = new_encoder(upload.data, name=name, profile=profile_name, cells=cells)
            facts = link_facts(encoder)
            return store.add(upload.data, name=name, profile=profile_name, cells=cells, facts=facts)

        message = await run_in_threadpool(encode_and_store)
    response.headers["Location"] = f"{request.url.path}/{message.id}"
    return describe(message)


@router.get("")
def read_messages(store: StoreDep) -> MessagesPublic:
    """All messages, newest first."""
    return MessagesPublic(messages=[describe(m) for m in store.messages()])


@router.get("/{message_id}", responses={404: {"description": "No such message."}})
def read_message(message: MessageDep) -> MessagePublic:
    return describe(message)


@router.get(
    "/{message_id}/content",
    response_class=Response,
    responses={
        200: {"content": {"application/octet-stream": {}}, "description": "The stored bytes."},
        404: {"description": "No such message."},
    },
)
def read_message_content(message: MessageDep, store: StoreDep) -> Response:
    """Download the message under its original name."""
    return download(store.content(message), message.name)


@router.delete(
    "/{message_id}",
    status_code=status.HTTP_204_NO_CONTENT,
    dependencies=[Depends(require_write_token)],
    responses={404: {"description": "No such message."}},
)
def delete_message(message: MessageDep, store: StoreDep) -> None:
    store.delete(message.id)
