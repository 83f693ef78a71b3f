"""What the live routes share, built once in the app's lifespan: the dashboards' hub, the
receptions store, the receivers connected now, the transmitter's latest status and counters."""

from __future__ import annotations

import asyncio
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

from eventocc.occ.report import FrameStats, Hello
from eventocc.server.api.schemas import TransmitterStatusPublic
from eventocc.server.hub import Hub
from eventocc.server.link_mode import LinkMode
from eventocc.server.receptions import ReceptionStore
from eventocc.server.store import MessageStore

GOODPUT_WINDOW_S = 60.0


@dataclass(eq=False)
class ReceiverSession:
    """One receiver's connection, the only one allowed to speak for it while it lasts."""

    hello: Hello
    replaced: asyncio.Event = field(default_factory=asyncio.Event)
    """Set when a newer connection of the same receiver took over."""

    @property
    def receiver(self) -> str:
        """The receiver's public id, under which everything it sends is kept and shown."""
        return self.hello.public_id


@dataclass
class LiveState:
    hub: Hub
    receptions: ReceptionStore
    messages: MessageStore
    receivers: dict[str, ReceiverSession] = field(default_factory=dict)
    """The connection of each receiver connected right now, by public id."""
    transmitter: TransmitterStatusPublic | None = None
    """The latest playback status a transmitter page reported (news only: not stored)."""
    frames_decoded: int = 0
    reports_rejected: int = 0
    stream_seen: dict[tuple[str, int], float] = field(default_factory=dict)
    """(receiver, stream id) -> monotonic time of its first progress report: goodput's start."""
    recent_receptions: deque[tuple[float, int]] = field(default_factory=deque)
    """(monotonic time, bits) of the receptions in the last ``GOODPUT_WINDOW_S``."""
    link: LinkMode = field(default_factory=LinkMode)
    """The transmitter's mode and, in auto, the settings chosen for it and why."""
    _link_published: float = 0.0

    def goodput_bps(self) -> float:
        """Verified message bits per second over the last ``GOODPUT_WINDOW_S``, all receivers."""
        recent = self.recent_receptions
        while recent and recent[0][0] < time.monotonic() - GOODPUT_WINDOW_S:
            recent.popleft()
        return sum(bits for _, bits in recent) / GOODPUT_WINDOW_S

    def set_transmitter(self, latest: TransmitterStatusPublic) -> None:
        """Keep a transmitter's status and tell the dashboards: the one path for REST and
        websocket reports alike."""
        self.transmitter = latest
        if latest.refresh_hz is not None:
            self.link.set_display_hz(latest.refresh_hz, latest.hold)
        self.hub.publish(transmitter_update(latest), topic="transmitter")

    def set_link_mode(self, mode: str, pinned: str | None) -> None:
        self.link.set_mode(mode, pinned, time.monotonic())
        self.publish_link()

    def link_frame(self, receiver: str, report: FrameStats) -> None:
        """A receiver's frame report, for auto mode's controller; the dashboards hear of a
        change at once, and of the goodput about once a second."""
        now = time.monotonic()
        if self.link.on_frame(receiver, report, now) or now - self._link_published >= 1.0:
            self.publish_link()

    def publish_link(self) -> None:
        self._link_published = time.monotonic()
        self.hub.publish({"type": "link_mode", **self.link_public()}, topic="link_mode")

    def link_public(self) -> dict[str, Any]:
        return self.link.public(time.monotonic())

    def claim(self, hello: Hello) -> ReceiverSession:
        """Bind the receiver to a new connection. Only the receiver itself knows its secret
        id, so a second connection with it is that receiver again, restarted while the server
        still holds its old connection (dead, or about to notice): the newer one wins."""
        session = ReceiverSession(hello)
        older = self.receivers.get(session.receiver)
        if older is not None:
            older.replaced.set()
        self.receivers[session.receiver] = session
        self.announce_receivers()
        return session

    def release(self, session: ReceiverSession) -> bool:
        """Forget a connection that ended; False if a newer one had replaced it."""
        if self.receivers.get(session.receiver) is not session:
            return False
        del self.receivers[session.receiver]
        self.link.forget(session.receiver)
        self.hub.forget(f"{session.receiver}:")
        self.announce_receivers()
        return True

    def announce_receivers(self) -> None:
        receivers = [
            {"receiver": s.receiver, "version": s.hello.version} for s in self.receivers.values()
        ]
        self.hub.publish({"type": "receivers", "receivers": receivers}, topic="receivers")


def transmitter_update(latest: TransmitterStatusPublic) -> dict[str, Any]:
    return {"type": "transmitter", **latest.model_dump(mode="json")}
