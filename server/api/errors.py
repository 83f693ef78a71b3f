"""How the REST API answers errors that are not an ``HTTPException`` of a route."""

from __future__ import annotations

from fastapi import FastAPI, Request, status
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse

from eventocc.server.store import MessageDeleted


async def request_invalid(request: Request, error: RequestValidationError) -> JSONResponse:
    """422 with where and what each problem is. The input is not echoed back: the client sent
    it, and it may hold what JSON cannot (a body's ``Infinity`` parses as a float)."""
    problems = [{key: e[key] for key in ("type", "loc", "msg")} for e in error.errors()]
    return JSONResponse({"detail": problems}, status_code=status.HTTP_422_UNPROCESSABLE_CONTENT)


async def message_deleted(request: Request, error: MessageDeleted) -> JSONResponse:
    """A message deleted while a request was reading it (its frames, its bytes) is gone: 404,
    as for the requests that come after."""
    return JSONResponse({"detail": str(error)}, status_code=status.HTTP_404_NOT_FOUND)


def add_error_handlers(app: FastAPI) -> None:
    app.add_exception_handler(RequestValidationError, request_invalid)
    app.add_exception_handler(MessageDeleted, message_deleted)
