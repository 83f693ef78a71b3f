"""Read an uploaded message from a request body in any of the three accepted forms.

- ``application/octet-stream``: the body is the message;
- ``multipart/form-data``: the message is the part named ``file`` (its file name is kept);
- ``application/json``: ``{"text": "..."}``, stored UTF-8 encoded.

The message may be at most ``limit`` bytes (413 otherwise). Multipart and JSON bodies get
``WRAPPER_SLACK`` bytes more for their wrapping, and multipart needs a Content-Length so an
oversized form is refused before it is parsed. Every body held counts against one
``UploadBudget`` for all requests together (503 once it is spent).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

from fastapi import HTTPException, Request, status
from pydantic import ValidationError
from starlette.datastructures import UploadFile

from eventocc.server.api.schemas import MessageText

WRAPPER_SLACK = 64 * 1024
UPLOAD_MEDIA_TYPES = ("application/octet-stream", "multipart/form-data", "application/json")
RETRY_AFTER_S = 2


class UploadBudget:
    """The bytes of upload bodies the server holds at once, over all requests, so that
    concurrent uploads cannot take memory without bound. Used from the event loop's thread
    only."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self.held = 0

    @contextmanager
    def claim(self) -> Iterator[Claim]:
        """A claim on the budget for one request, given back when the request is done."""
        claim = Claim(self)
        try:
            yield claim
        finally:
            self.held -= claim.size


class Claim:
    """One request's share of the budget."""

    def __init__(self, budget: UploadBudget) -> None:
        self.budget = budget
        self.size = 0

    def grow_to(self, size: int) -> None:
        """Hold ``size`` bytes in all; 503 if the budget cannot take them now."""
        more = size - self.size
        if more <= 0:
            return
        if self.budget.held + more > self.budget.limit:
            raise HTTPException(
                status.HTTP_503_SERVICE_UNAVAILABLE,
                "the server is busy with other uploads; retry in a moment",
                headers={"Retry-After": str(RETRY_AFTER_S)},
            )
        self.budget.held += more
        self.size = size


@dataclass(frozen=True, slots=True)
class Upload:
    data: bytes
    filename: str | None
    """The name the client gave the file (multipart only)."""
    is_text: bool


async def read_upload(request: Request, limit: int, claim: Claim) -> Upload:
    """The upload, its body held under ``claim`` (as declared up front, as read when chunked)."""
    media_type = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if media_type == "application/octet-stream":
        upload = Upload(await _read_body(request, limit, limit, claim), None, is_text=False)
    elif media_type == "application/json":
        upload = _parse_json(await _read_body(request, limit + WRAPPER_SLACK, limit, claim))
    elif media_type == "multipart/form-data":
        upload = await _parse_multipart(request, limit, claim)
    else:
        raise HTTPException(
            status.HTTP_415_UNSUPPORTED_MEDIA_TYPE,
            f"unsupported Content-Type {media_type or '(none)'!r}; "
            f"send one of {', '.join(UPLOAD_MEDIA_TYPES)}",
        )
    if len(upload.data) > limit:
        raise _too_large(limit)
    if not upload.data:
        raise HTTPException(
            status.HTTP_422_UNPROCESSABLE_CONTENT, "the message is empty; send at least one byte"
        )
    return upload


def _too_large(limit: int) -> HTTPException:
    return HTTPException(
        status.HTTP_413_CONTENT_TOO_LARGE,
        f"the message is over this server's upload limit of {limit} bytes",
    )


def _declared_length(request: Request) -> int | None:
    value = request.headers.get("content-length")
    return int(value) if value and value.isdigit() else None


async def _read_body(request: Request, body_limit: int, message_limit: int, claim: Claim) -> bytes:
    """The whole body, refused as soon as it passes ``body_limit`` (chunked uploads included)."""
    declared = _declared_length(request)
    if declared is not None and declared > body_limit:
        raise _too_large(message_limit)
    claim.grow_to(declared or 0)
    chunks, size = [], 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > body_limit:
            raise _too_large(message_limit)
        claim.grow_to(size)
        chunks.append(chunk)
    return b"".join(chunks)


def _parse_json(body: bytes) -> Upload:
    try:
        text = MessageText.model_validate_json(body).text
    except ValidationError as error:
        problems = "; ".join(
            f"{'.'.join(map(str, e['loc'])) or 'body'}: {e['msg']}" for e in error.errors()
        )
        raise HTTPException(
            status.HTTP_422_UNPROCESSABLE_CONTENT,
            f'send JSON like {{"text": "..."}} ({problems})',
        ) from None
    return Upload(text.encode(), None, is_text=True)


async def _parse_multipart(request: Request, limit: int, claim: Claim) -> Upload:
    declared = _declared_length(request)
    if declared is None:
        raise HTTPException(
            status.HTTP_411_LENGTH_REQUIRED, "multipart uploads need a Content-Length header"
        )
    if declared > limit + WRAPPER_SLACK:
        raise _too_large(limit)
    claim.grow_to(declared)
    form = await request.form(max_files=1, max_fields=8)
    file = form.get("file")
    if file is None:
        raise _unusable_form("the form has no part named 'file'")
    if not isinstance(file, UploadFile):
        raise _unusable_form(
            "the form's 'file' part is a plain field: send it as a file part, with a filename "
            "(curl -F file=@path)"
        )
    data = await file.read()
    if not data and not file.filename:
        raise _unusable_form("no file was chosen: the 'file' part has no filename and no bytes")
    return Upload(data, file.filename, is_text=False)


def _unusable_form(problem: str) -> HTTPException:
    return HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, f"multipart upload: {problem}")
