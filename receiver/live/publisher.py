"""Send the daemon's reports to the server's ``/ws/receiver``, surviving the server going away.

The pipeline thread calls ``publish``; a background thread runs an asyncio loop that keeps one
websocket open. Durable reports (finished messages, poses) go through the on-disk ``Spool`` and
are deleted only when the server acknowledges them, so they survive both a server restart and a
daemon restart. Ephemeral reports (frame statistics, progress, health, thumbnails) are news: only
the newest of each kind waits, in memory, and it is dropped while the server is away.

Reconnects back off exponentially (with jitter) from ``backoff_s[0]`` up to ``backoff_s[1]``.
"""

from __future__ import annotations

import asyncio
import json
import logging
import random
import threading
from collections.abc import Callable
from dataclasses import dataclass

from pydantic import BaseModel
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidStatus

from eventocc.occ.report import Hello
from eventocc.receiver.live.spool import Spool

log = logging.getLogger(__name__)

CLOSE_CODES_FATAL = {4401: "the server refused our token", 4400: "the server refused our Hello"}
"""Close codes after which reconnecting cannot help (see ``eventocc.server.api.receivers``)."""
SEND_BATCH = 256


@dataclass
class PublisherStats:
    connected: bool = False
    connections: int = 0
    sent: int = 0
    acknowledged_seq: int = 0
    ephemeral_dropped: int = 0


class PublisherError(RuntimeError):
    """The server refused this receiver for good (wrong token, bad handshake)."""


class Publisher:
    def __init__(
        self,
        url: str,
        spool: Spool,
        *,
        token: str | None = None,
        backoff_s: tuple[float, float] = (0.25, 30.0),
        on_fatal: Callable[[], None] = lambda: None,
    ) -> None:
        """``on_fatal`` is called (from the publisher thread) if the server refuses us for good."""
        if not url.startswith(("ws://", "wss://")):
            raise ValueError(f"server URL must start with ws:// or wss://, got {url!r}")
        self.url = url.rstrip("/") + "/ws/receiver"
        self.spool = spool
        self.hello = Hello(receiver_id=spool.receiver_id, token=token)
        self.backoff_s = backoff_s
        self.on_fatal = on_fatal
        self.stats = PublisherStats()
        self.error: PublisherError | None = None
        self._ephemeral: dict[str, str] = {}
        """Newest unsent ephemeral report per kind (JSON text)."""
        self._lock = threading.Lock()
        self._loop = asyncio.new_event_loop()
        self._wake = asyncio.Event()
        self._stop = asyncio.Event()
        self._thread = threading.Thread(target=self._run, name="eventocc-publisher", daemon=True)

    # --- called from the pipeline thread ---

    def start(self) -> Publisher:
        self._thread.start()
        return self

    def publish(self, report: BaseModel, *, durable: bool) -> None:
        text = report.model_dump_json()
        if durable:
            self.spool.append(text)
        else:
            with self._lock:
                kind = getattr(report, "type", type(report).__name__)
                self.stats.ephemeral_dropped += kind in self._ephemeral
                self._ephemeral[kind] = text
        self._call_soon(self._wake.set)

    def close(self, drain_timeout_s: float = 5.0) -> None:
        """Stop, after trying for up to ``drain_timeout_s`` to deliver what the spool holds."""
        if self._thread.is_alive() and self._call_soon(self._begin_stop, drain_timeout_s):
            self._thread.join()

    def _call_soon(self, callback: Callable[..., None], *args: object) -> bool:
        """Run ``callback`` on the publisher's loop; False once the loop has stopped for good."""
        # Under the lock so that the loop cannot close between the check and the call: after a
        # fatal refusal the thread closes it while the pipeline may still publish or close.
        with self._lock:
            if self._loop.is_closed():
                return False
            self._loop.call_soon_threadsafe(callback, *args)
            return True

    # --- the publisher thread ---

    def _run(self) -> None:
        self._loop.run_until_complete(self._keep_connected())
        with self._lock:
            self._loop.close()

    def _begin_stop(self, drain_timeout_s: float) -> None:
        self._stop.set()
        self._wake.set()
        self._loop.call_later(drain_timeout_s, self._abandon)

    def _abandon(self) -> None:
        for task in asyncio.all_tasks(self._loop):
            task.cancel()

    async def _keep_connected(self) -> None:
        delay = self.backoff_s[0]
        while True:
            try:
                await self._session()  # returns only once stopping and the spool is drained
                return
            except PublisherError as error:
                self.error = error
                log.error("%s; not reconnecting", error)
                self.on_fatal()
                return
            except (OSError, InvalidHandshake, ConnectionClosed, TimeoutError) as error:
                log.warning(
                    "server %s unreachable (%s); retrying in %.1f s", self.url, error, delay
                )
            except asyncio.CancelledError:
                return
            finally:
                self.stats.connected = False
            try:
                await asyncio.sleep(delay * random.uniform(0.8, 1.2))
            except asyncio.CancelledError:  # close() gave up waiting for the server
                return
            delay = min(delay * 2, self.backoff_s[1])

    def _drained(self) -> bool:
        return len(self.spool) == 0

    async def _session(self) -> None:
        try:
            async with connect(self.url, open_timeout=5) as ws:
                await ws.send(self.hello.model_dump_json())
                welcome = json.loads(await asyncio.wait_for(ws.recv(), 5.0))
                acked = int(welcome["last_seq"])
                self.spool.acknowledge(acked)
                self.stats.acknowledged_seq = max(self.stats.acknowledged_seq, acked)
                self.stats.connected = True
                self.stats.connections += 1
                log.info("connected to %s; %d reports spooled", self.url, len(self.spool))
                await self._exchange(ws, acked)
        except ConnectionClosed as closed:
            reason = CLOSE_CODES_FATAL.get(closed.rcvd.code if closed.rcvd else 0)
            if reason:
                raise PublisherError(f"{reason}: {closed.rcvd.reason}") from None
            raise
        except InvalidStatus as error:
            raise PublisherError(f"{self.url} is not an eventocc server: {error}") from None

    async def _exchange(self, ws: ClientConnection, sent_seq: int) -> None:
        acks = asyncio.create_task(self._read_acks(ws))
        try:
            while not (self._stop.is_set() and self._drained()):
                self._wake.clear()
                for text in self._take_ephemeral():
                    await ws.send(f'{{"seq":null,"report":{text}}}')
                    self.stats.sent += 1
                for seq, text in self.spool.pending(sent_seq, SEND_BATCH):
                    await ws.send(f'{{"seq":{seq},"report":{text}}}')
                    sent_seq = seq
                    self.stats.sent += 1
                if acks.done():
                    acks.result()  # the connection dropped: raise why
                waker = asyncio.create_task(self._wake.wait())
                await asyncio.wait({waker, acks}, return_when=asyncio.FIRST_COMPLETED)
                waker.cancel()
        finally:
            acks.cancel()

    async def _read_acks(self, ws: ClientConnection) -> None:
        async for text in ws:
            message = json.loads(text)
            if message.get("type") == "ack":
                self.spool.acknowledge(message["seq"])
                self.stats.acknowledged_seq = message["seq"]
                self._wake.set()  # maybe the drain we wait for is complete
        raise ConnectionError("the server closed the connection")

    def _take_ephemeral(self) -> list[str]:
        with self._lock:
            texts, self._ephemeral = list(self._ephemeral.values()), {}
        return texts
