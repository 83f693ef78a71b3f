"""Fan-out of live updates to any number of dashboard viewers, each behind a bounded queue.

Every update is encoded to JSON once and the same text goes to every viewer. Publishing never
waits: a viewer whose queue is full loses its oldest pending update (it is decimated: it still
sees the newest pose, just fewer of them), and a viewer that takes nothing for ``evict_after``
consecutive updates is stalled and gets evicted. So one slow phone can neither slow the others
nor grow the server's memory.

The hub also keeps the latest update of each *topic* (the transmitter's status, each receiver's
newest pose, ...) so a viewer that joins late starts from the current picture.
"""

from __future__ import annotations

import asyncio
import json
import logging
from collections import deque
from collections.abc import Awaitable, Callable
from typing import Any

log = logging.getLogger(__name__)

__all__ = ["Hub", "Viewer"]


class Viewer:
    """One dashboard connection's pending updates (pre-encoded JSON texts)."""

    def __init__(self, name: str, queue_size: int) -> None:
        self.name = name
        self._pending: deque[str] = deque()
        self._queue_size = queue_size
        self._ready = asyncio.Event()
        self._evicted = asyncio.Event()
        self.dropped = 0
        """Updates this viewer lost because it fell behind."""
        self.drops_in_a_row = 0
        self.evicted = False

    def offer(self, text: str) -> bool:
        """Queue ``text``; True if the oldest pending update had to go to make room."""
        full = len(self._pending) >= self._queue_size
        if full:
            self._pending.popleft()
            self.dropped += 1
            self.drops_in_a_row += 1
        self._pending.append(text)
        self._ready.set()
        return full

    async def next(self) -> str | None:
        """The oldest pending update; None once the viewer has been evicted."""
        while not self._pending and not self.evicted:
            self._ready.clear()
            await self._ready.wait()
        if self.evicted:
            return None
        self.drops_in_a_row = 0
        return self._pending.popleft()

    def evict(self) -> None:
        self.evicted = True
        self._pending.clear()
        self._ready.set()
        self._evicted.set()

    async def wait_evicted(self) -> None:
        """Returns once evicted, even while a send to this viewer is stuck in the network."""
        await self._evicted.wait()

    @property
    def backlog(self) -> int:
        return len(self._pending)


class Hub:
    def __init__(self, *, queue_size: int = 64, evict_after: int = 1000) -> None:
        if queue_size < 1 or evict_after < 1:
            raise ValueError(
                f"queue_size and evict_after must be positive, got {queue_size}, {evict_after}"
            )
        self.queue_size = queue_size
        self.evict_after = evict_after
        self._viewers: set[Viewer] = set()
        self._latest: dict[str, str] = {}
        self.published = 0
        self.dropped = 0
        """Updates lost by viewers that fell behind (decimation), all time."""
        self.evicted = 0

    @property
    def viewer_count(self) -> int:
        return len(self._viewers)

    def subscribe(self, name: str) -> Viewer:
        viewer = Viewer(name, self.queue_size)
        for text in self._latest.values():
            viewer.offer(text)
        self._viewers.add(viewer)
        return viewer

    def unsubscribe(self, viewer: Viewer) -> None:
        self._viewers.discard(viewer)

    def publish(self, update: dict[str, Any], *, topic: str | None = None) -> None:
        """Queue ``update`` for every viewer; ``topic`` also keeps it for viewers joining later.

        Never blocks: call it from the event loop's thread.
        """
        text = json.dumps(update, separators=(",", ":"))
        self.published += 1
        if topic is not None:
            self._latest[topic] = text
        for viewer in list(self._viewers):
            self.dropped += viewer.offer(text)
            if viewer.drops_in_a_row >= self.evict_after:
                log.warning(
                    "dashboard viewer %s stalled (%d updates untaken): dropping it",
                    viewer.name,
                    viewer.drops_in_a_row,
                )
                self.evicted += 1
                viewer.evict()
                self._viewers.discard(viewer)

    def forget(self, topic_prefix: str) -> None:
        """Drop kept updates whose topic starts with ``topic_prefix`` (a receiver went away)."""
        for topic in [t for t in self._latest if t.startswith(topic_prefix)]:
            del self._latest[topic]

    async def serve(self, viewer: Viewer, send: Callable[[str], Awaitable[None]]) -> None:
        """Send the viewer's updates until it is evicted or ``send`` fails (it disconnected)."""
        try:
            while (text := await viewer.next()) is not None:
                await send(text)
        finally:
            self.unsubscribe(viewer)
