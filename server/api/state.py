"""What the live routes share, built once in the app's lifespan: the dashboards' hub, the
receptions store, the receivers connected now, the transmitter's latest status and counters."""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

from eventocc.occ.report import Hello
from eventocc.server.api.schemas import TransmitterStatusPublic
from eventocc.server.hub import Hub
from eventocc.server.receptions import ReceptionStore
from eventocc.server.store import MessageStore

GOODPUT_WINDOW_S = 60.0


@dataclass
class LiveState:
    hub: Hub
    receptions: ReceptionStore
    messages: MessageStore
    receivers: dict[str, Hello] = field(default_factory=dict)
    """Receivers connected right now, by id."""
    transmitter: TransmitterStatusPublic | None = None
    """The latest playback status a transmitter page reported (news only: not stored)."""
    frames_decoded: int = 0
    reports_rejected: int = 0
    stream_seen: dict[tuple[str, int], float] = field(default_factory=dict)
    """(receiver, stream id) -> monotonic time of its first progress report: goodput's start."""
    recent_receptions: deque[tuple[float, int]] = field(default_factory=deque)
    """(monotonic time, bits) of the receptions in the last ``GOODPUT_WINDOW_S``."""

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
        self.hub.publish(transmitter_update(latest), topic="transmitter")

    def announce_receivers(self) -> None:
        receivers = [h.model_dump(mode="json", exclude={"token"}) for h in self.receivers.values()]
        self.hub.publish({"type": "receivers", "receivers": receivers}, topic="receivers")


def transmitter_update(latest: TransmitterStatusPublic) -> dict[str, Any]:
    return {"type": "transmitter", **latest.model_dump(mode="json")}
