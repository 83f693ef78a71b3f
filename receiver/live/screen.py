"""What the server's transmitter page shows, asked over the server's REST API.

The virtual camera needs it to simulate that screen; a daemon on a live camera pointed at the
page needs it to keep its receiver built for the page's link settings (``ScreenWatch``), as a
person would otherwise have to with ``--profile``, ``--cells`` and ``--refresh-hz``.
"""

from __future__ import annotations

import http.client
import logging
import threading
import urllib.error
import urllib.request
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Annotated

from pydantic import AwareDatetime, BaseModel, Field, ValidationError

from eventocc.occ.profiles import LinkSettings
from eventocc.receiver.live.sources import SourceError

log = logging.getLogger(__name__)

MAX_FRAME_INDEX = 1 << 53
"""A page counts its frames in a JavaScript number, exact up to 2**53: no page shows more."""
MessageId = Annotated[str, Field(pattern=r"^[0-9A-Za-z_-]{1,64}$")]
"""A message id goes into URL paths, so it must be one plain path segment."""
PAGE_GONE_S = 90.0
"""A page reports its status every second while open, and at once when it pauses or is hidden
(closing it hides it); a browser may slow a hidden tab's reports to one a minute: a page
silent this long was closed."""


class StatusError(ValueError):
    """What the server says its transmitter shows cannot be used (a profile, cell count or
    refresh rate no receiver can be built for, or not the server's format at all)."""


@dataclass(frozen=True)
class Showing:
    """What the transmitter shows: a message, its link settings and the frame on screen now."""

    message_id: str
    link: LinkSettings
    refresh_hz: float
    """As the page measured it (``link`` holds it to the whole hertz)."""
    frame_now: int
    packed: bool = False
    """The page sends packed frames (its auto mode), this segment's first symbol at stream
    position ``symbol_start`` (``eventocc.occ.packing``)."""
    symbol_start: int = 0

    def same_stream(self, other: Showing) -> bool:
        return (self.message_id, self.link, self.packed, self.symbol_start) == (
            other.message_id,
            other.link,
            other.packed,
            other.symbol_start,
        )


@dataclass(frozen=True)
class Idle:
    """Nothing blinks on the screen: a paused page holds one still frame, a closed one shows
    nothing; either way a camera sees no message."""

    reason: str


class _Status(BaseModel):
    """The fields of ``GET /api/transmitter/status`` the receiver reads."""

    message_id: MessageId | None = None
    profile: str | None = None
    cells: int | None = None
    playing: bool = False
    frame_index: int = Field(0, ge=0, le=MAX_FRAME_INDEX)
    refresh_hz: float | None = None
    packed: bool = False
    symbol_start: int = Field(0, ge=0, le=MAX_FRAME_INDEX)
    received: AwareDatetime

    def showing(self) -> Showing | Idle:
        age_s = (datetime.now(UTC) - self.received).total_seconds()
        if age_s > PAGE_GONE_S:
            return Idle(f"no transmitter page plays (none reported for {PAGE_GONE_S:.0f} s)")
        if not self.message_id:
            return Idle("the transmitter page has no message to play")
        if not self.playing:
            return Idle("the transmitter page is paused")
        hz = self.refresh_hz or 60.0
        link = LinkSettings(self.profile, self.cells, hz)  # raises for what cannot be received
        frame_now = min(self.frame_index + max(0, round(age_s * hz)), MAX_FRAME_INDEX)
        return Showing(self.message_id, link, hz, frame_now, self.packed, self.symbol_start)


class _Listed(BaseModel):
    id: MessageId
    profile: str
    cells: int


class _Messages(BaseModel):
    """``GET /api/messages``, newest first."""

    messages: list[_Listed]


class _Meta(_Listed):
    """``GET /api/messages/{id}``, for a stand-in message."""


class _Message(BaseModel):
    """``GET /api/messages/{id}``, for the name of a message being watched."""

    name: str


class _Defaults(BaseModel):
    """``GET /api/profiles``."""

    default_profile: str
    default_cells: int


class TransmitterClient:
    """Reads the server's view of its transmitter page. Nothing it reads is trusted: an answer
    the receiver cannot use raises ``StatusError``, one it cannot get ``OSError``."""

    def __init__(
        self, server_url: str, *, who: str = "the receiver", stand_in: str | None = None
    ) -> None:
        """``stand_in``: the message a page is taken to play from frame 0 until one reports
        (None: the newest upload)."""
        if not server_url.startswith(("http://", "https://")):
            raise SourceError(f"{who} needs the server's http(s) URL, got {server_url!r}")
        self.server_url = server_url.rstrip("/")
        self.stand_in = stand_in

    def get(self, path: str) -> bytes | None:
        """The body of GET ``path``; None on 404 (nothing there yet)."""
        try:
            with urllib.request.urlopen(self.server_url + path, timeout=5) as response:
                return response.read()
        except urllib.error.HTTPError as error:
            if error.code == 404:
                return None
            raise
        except http.client.HTTPException as error:  # not HTTP: as good as unreachable
            raise ConnectionError(f"{self.server_url} answered {path} wrongly: {error!r}") from None

    def showing(self) -> Showing | Idle:
        """What the transmitter shows now; until a page reports, the stand-in message (or the
        newest upload) from frame 0, as if a page played it."""
        status = self.get("/api/transmitter/status")
        try:
            if status is not None:
                return _Status.model_validate_json(status).showing()
            if self.stand_in is not None:
                meta = self.get(f"/api/messages/{self.stand_in}")
                if meta is None:
                    return Idle(f"no page has reported and message {self.stand_in} is gone")
                listed: _Listed = _Meta.model_validate_json(meta)
            else:
                body = self.get("/api/messages") or '{"messages": []}'
                listing = _Messages.model_validate_json(body)
                if not listing.messages:
                    return Idle("no message has been uploaded")
                listed = listing.messages[0]
            return Showing(listed.id, LinkSettings(listed.profile, listed.cells), 60.0, 0)
        except ValueError as error:  # pydantic's ValidationError, or LinkSettings refusing
            raise StatusError(
                f"{self.server_url} says its transmitter shows what no receiver can read: "
                f"{_one_line(error)}"
            ) from None

    def message(self, message_id: str) -> tuple[str, bytes]:
        """The name and bytes of a message; ``LookupError`` if the server has none by that id."""
        meta = self.get(f"/api/messages/{message_id}")
        data = self.get(f"/api/messages/{message_id}/content")
        if meta is None or data is None:
            raise LookupError(f"message {message_id} is gone")
        try:
            return _Message.model_validate_json(meta).name, data
        except ValidationError as error:
            raise StatusError(
                f"{self.server_url} describes message {message_id} wrongly: {_one_line(error)}"
            ) from None

    def link_settings(self, fallback: LinkSettings) -> LinkSettings:
        """What the transmitter sends now, else the server's defaults (the receiver must be
        built before anything plays); ``fallback``, said in the log, if the server cannot
        tell: a receiver starts whether or not the server is up, and follows it later."""
        try:
            showing = self.showing()
            if isinstance(showing, Showing):
                return showing.link
            defaults = _Defaults.model_validate_json(self.get("/api/profiles") or "{}")
            return LinkSettings(defaults.default_profile, defaults.default_cells)
        except (OSError, ValueError) as error:
            problem = _asking_failed(self.server_url, error)
            log.warning("%s; assuming %s until it answers", problem, fallback)
            return fallback


def _asking_failed(server_url: str, error: Exception) -> str:
    """What went wrong asking the server, on one line."""
    if isinstance(error, OSError):
        return f"cannot ask {server_url} what it transmits: {error}"
    if isinstance(error, StatusError):
        return str(error)
    return f"{server_url} answers what no receiver can read: {_one_line(error)}"


def _one_line(error: Exception) -> str:
    """An error's message on one line (pydantic lists each problem on lines of its own)."""
    if isinstance(error, ValidationError):
        return "; ".join(
            f"{'.'.join(map(str, e['loc'])) or 'the answer'}: {e['msg']}" for e in error.errors()
        )
    return str(error)


class ScreenWatch:
    """The link settings of the transmitter page, asked every ``every_s`` in a thread, for a
    daemon whose camera watches that page (``link``, as the virtual camera has). While the
    server cannot be asked, or says what no receiver can read, ``link`` stays as it was and
    the log says why, once."""

    def __init__(self, client: TransmitterClient, fallback: LinkSettings, every_s: float = 2.0):
        self.client = client
        self.every_s = every_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="screen-watch", daemon=True)
        self._problem: str | None = None
        self.link: LinkSettings = client.link_settings(fallback)  # a camera must not wait

    def start(self) -> ScreenWatch:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10)

    def _run(self) -> None:
        while not self._stop.wait(self.every_s):
            self.poll()

    def poll(self) -> None:
        """Ask once; keep the link settings if the answer cannot be used."""
        try:
            showing, problem = self.client.showing(), None
        except (OSError, StatusError) as error:
            showing, problem = None, _asking_failed(self.client.server_url, error)
        if problem != self._problem:
            if problem is not None:
                log.warning("%s; keeping %s", problem, self.link)
            else:
                log.info("%s answers again", self.client.server_url)
            self._problem = problem
        if isinstance(showing, Showing):
            self.link = showing.link
