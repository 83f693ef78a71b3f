"""The FastAPI app factory: the API, one lifespan for the live state, and the static pages."""

from __future__ import annotations

from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from dataclasses import replace
from html import escape
from importlib import resources
from pathlib import Path

from fastapi import FastAPI
from fastapi.responses import FileResponse, HTMLResponse
from fastapi.staticfiles import StaticFiles
from fastapi_offline import FastAPIOffline

from eventocc import __version__
from eventocc.server.api import api_router
from eventocc.server.api.encoding import EncoderCache
from eventocc.server.api.errors import add_error_handlers
from eventocc.server.api.origins import OriginCheck
from eventocc.server.api.state import LiveState
from eventocc.server.api.uploads import UploadBudget
from eventocc.server.hub import Hub
from eventocc.server.link_mode import LIVE_POLICY, LinkMode
from eventocc.server.receptions import ReceptionStore
from eventocc.server.settings import Settings
from eventocc.server.store import MessageStore

WEB_DIR = Path(str(resources.files("eventocc.web")))
"""The pages, shipped as package data: a checkout's ``web/``, or the installed copy."""

UVICORN_OPTIONS = {"ws_per_message_deflate": False}
"""For every way the app is served. No per-message deflate on websockets: updates are small
JSON, and compressing each one for each viewer (one zlib stream per connection) took a third
more server CPU with 100 dashboards (bench/live.py) to save little bandwidth."""


@asynccontextmanager
async def lifespan(app: FastAPI) -> AsyncIterator[None]:
    """The live state for the app's lifetime; the receptions' database closes with it."""
    store, settings = app.state.store, app.state.settings
    min_px = {"robust": settings.auto_min_px_robust, "fast": settings.auto_min_px_fast}
    link = LinkMode(config=replace(LIVE_POLICY, min_px=min_px))
    app.state.live = LiveState(Hub(), ReceptionStore(store.path), store, link=link)
    try:
        yield
    finally:
        app.state.live.receptions.close()


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings()
    app = FastAPIOffline(  # the docs' assets served by the app: /docs works offline
        title="eventocc",
        summary="Screen-to-event-camera link: upload messages, play them as a dynamic marker.",
        version=__version__,
        lifespan=lifespan,
    )
    app.state.settings = settings
    app.state.store = MessageStore(settings.db_path)
    app.state.encoders = EncoderCache(app.state.store, settings.encoder_cache_size)
    app.state.upload_budget = UploadBudget(settings.upload_budget)
    app.include_router(api_router)
    add_error_handlers(app)
    app.add_middleware(OriginCheck, allowed=settings.allowed_origins)
    _add_pages(app, WEB_DIR)
    return app


def _add_pages(app: FastAPI, web_dir: Path) -> None:
    """``/static/*`` serves ``web/``; every ``web/<page>.html`` is also served at ``/<page>``,
    and ``/`` lists them."""
    pages = sorted(p.stem for p in web_dir.glob("*.html"))
    app.mount("/static", StaticFiles(directory=web_dir), name="static")

    for page in pages:
        app.add_api_route(
            f"/{page}", _serve_file(web_dir / f"{page}.html"), include_in_schema=False
        )

    links = "".join(f'<li><a href="/{escape(p)}">{escape(p)}</a></li>' for p in pages)
    index = (
        '<!doctype html><html lang="en"><head><meta charset="utf-8"><title>eventocc</title>'
        '<meta name="viewport" content="width=device-width, initial-scale=1">'
        '<link rel="stylesheet" href="/static/style.css"></head>'
        f'<body class="index"><main><h1>eventocc</h1><ul>{links}'
        '<li><a href="/docs">API</a></li></ul></main></body></html>'
    )
    app.add_api_route("/", lambda: HTMLResponse(index), include_in_schema=False)
    # Browsers ask every page's site for /favicon.ico: an icon, not a 404 in the log.
    icon = web_dir / "favicon.svg"
    app.add_api_route(
        "/favicon.ico",
        lambda: FileResponse(icon, media_type="image/svg+xml"),
        include_in_schema=False,
    )


def _serve_file(path: Path) -> Callable[[], FileResponse]:
    def serve() -> FileResponse:
        return FileResponse(path)

    return serve
