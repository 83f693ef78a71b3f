"""What the server's transmitter page shows, asked over the server's REST API.

The virtual camera needs it to simulate that screen; a daemon on a live camera pointed at the
page needs it to keep its receiver built for the page's link settings (``ScreenWatch``), as a
person would otherwise have to with ``--profile``, ``--cells`` and ``--refresh-hz``.
"""

from __future__ import annotations

import json
import logging
import threading
import urllib.error
import urllib.request
from dataclasses import dataclass
from datetime import UTC, datetime

from eventocc.occ.profiles import LinkSettings
from eventocc.receiver.live.sources import SourceError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Showing:
    """What the transmitter shows: a message, its link settings and the frame on screen now."""

    message_id: str
    link: LinkSettings
    refresh_hz: float
    """As the page measured it (``link`` holds it to the whole hertz)."""
    frame_now: int

    def same_stream(self, other: Showing) -> bool:
        return (self.message_id, self.link) == (other.message_id, other.link)


class TransmitterClient:
    """Reads the server's view of its transmitter page."""

    def __init__(self, server_url: str, *, who: str = "the receiver") -> None:
        if not server_url.startswith(("http://", "https://")):
            raise SourceError(f"{who} needs the server's http(s) URL, got {server_url!r}")
        self.server_url = server_url.rstrip("/")

    def get(self, path: str) -> bytes | None:
        """The body of GET ``path``; None on 404 (nothing there yet)."""
        try:
            with urllib.request.urlopen(self.server_url + path, timeout=5) as response:
                return response.read()
        except urllib.error.HTTPError as error:
            if error.code == 404:
                return None
            raise

    def showing(self) -> Showing | None:
        """What the transmitter shows now; its newest upload from frame 0 if no page reported."""
        status = self.get("/api/transmitter/status")
        if status is not None:
            s = json.loads(status)
            if not (s["playing"] and s["message_id"]):
                return None
            hz = s["refresh_hz"] or 60.0
            age_s = (datetime.now(UTC) - datetime.fromisoformat(s["received"])).total_seconds()
            frame_now = s["frame_index"] + max(0, round(age_s * hz))
            link = LinkSettings(s["profile"], s["cells"], hz)
            return Showing(s["message_id"], link, hz, frame_now)
        messages = json.loads(self.get("/api/messages") or b'{"messages": []}')["messages"]
        if not messages:
            return None
        newest = messages[0]
        return Showing(newest["id"], LinkSettings(newest["profile"], newest["cells"]), 60.0, 0)

    def link_settings(self) -> LinkSettings:
        """What the transmitter sends now, else the server's defaults (the receiver must be
        built before anything plays). Raises ``SourceError`` if the server does not answer."""
        try:
            showing = self.showing()
            if showing is not None:
                return showing.link
            defaults = json.loads(self.get("/api/profiles") or b"{}")
            return LinkSettings(defaults["default_profile"], defaults["default_cells"])
        except OSError as error:
            raise SourceError(f"cannot ask {self.server_url} what it transmits: {error}") from None


class ScreenWatch:
    """The link settings of the transmitter page, asked every ``every_s`` in a thread, for a
    daemon whose camera watches that page (``link``, as the virtual camera has)."""

    def __init__(self, client: TransmitterClient, fallback: LinkSettings, every_s: float = 2.0):
        self.client = client
        self.every_s = every_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="screen-watch", daemon=True)
        self._unreachable = False
        try:
            self.link: LinkSettings = client.link_settings()
        except SourceError as error:  # a live camera must not wait for the server
            log.warning("%s; assuming %s until it answers", error, fallback)
            self.link, self._unreachable = fallback, True

    def start(self) -> ScreenWatch:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10)

    def _run(self) -> None:
        while not self._stop.wait(self.every_s):
            try:
                showing = self.client.showing()
            except (OSError, ValueError, KeyError) as error:
                if not self._unreachable:
                    url = self.client.server_url
                    log.warning("cannot ask %s what it transmits: %s", url, error)
                self._unreachable = True
                continue
            if self._unreachable:
                log.info("%s answers again", self.client.server_url)
            self._unreachable = False
            if showing is not None:
                self.link = showing.link
