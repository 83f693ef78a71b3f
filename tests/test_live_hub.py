"""The dashboard fan-out: bounded per-viewer queues, decimation, eviction, late joiners."""

from __future__ import annotations

import asyncio
import json

import pytest

from eventocc.server.hub import Hub


def texts(n: int, start: int = 0) -> list[dict]:
    return [{"type": "pose", "i": i} for i in range(start, start + n)]


def test_every_viewer_gets_every_update_in_order() -> None:
    async def scenario() -> list[list[int]]:
        hub = Hub(queue_size=8)
        viewers = [hub.subscribe(f"v{i}") for i in range(3)]
        for update in texts(5):
            hub.publish(update)
        return [[json.loads(await v.next())["i"] for _ in range(5)] for v in viewers]

    assert asyncio.run(scenario()) == [[0, 1, 2, 3, 4]] * 3


def test_a_slow_viewer_is_decimated_and_keeps_the_newest() -> None:
    async def scenario():
        hub = Hub(queue_size=4, evict_after=1000)
        slow, fast = hub.subscribe("slow"), hub.subscribe("fast")
        got_fast = []
        for update in texts(10):
            hub.publish(update)
            got_fast.append(json.loads(await fast.next())["i"])
        return hub, slow, got_fast

    hub, slow, got_fast = asyncio.run(scenario())
    assert got_fast == list(range(10))
    assert slow.backlog == 4, "the queue must never grow past its bound"
    assert slow.dropped == 6 and hub.dropped == 6
    assert not slow.evicted


def test_a_stalled_viewer_is_evicted_without_touching_the_others() -> None:
    async def scenario():
        hub = Hub(queue_size=2, evict_after=5)
        stalled, live = hub.subscribe("stalled"), hub.subscribe("live")
        seen = []
        for update in texts(20):
            hub.publish(update)
            seen.append(json.loads(await live.next())["i"])
        return hub, stalled, seen, await stalled.next()

    hub, stalled, seen, after = asyncio.run(scenario())
    assert seen == list(range(20))
    assert stalled.evicted and hub.evicted == 1 and hub.viewer_count == 1
    assert after is None, "an evicted viewer's next() ends its sender"


def test_taking_updates_resets_the_stall_count() -> None:
    async def scenario() -> bool:
        hub = Hub(queue_size=1, evict_after=3)
        viewer = hub.subscribe("v")
        for update in texts(30):  # it lags by two every time, but keeps taking
            hub.publish(update)
            hub.publish(update)
            await viewer.next()
        return viewer.evicted

    assert asyncio.run(scenario()) is False


def test_late_joiners_start_from_the_latest_of_each_topic() -> None:
    async def scenario() -> list[dict]:
        hub = Hub()
        hub.publish({"type": "transmitter", "frame": 1}, topic="transmitter")
        hub.publish({"type": "transmitter", "frame": 2}, topic="transmitter")
        hub.publish({"type": "pose", "i": 7}, topic="r1:pose")
        hub.publish({"type": "reception"})  # no topic: news only for those watching
        hub.forget("r1:")
        viewer = hub.subscribe("late")
        return [json.loads(await viewer.next()) for _ in range(viewer.backlog)]

    assert asyncio.run(scenario()) == [{"type": "transmitter", "frame": 2}]


def test_serve_stops_when_evicted_and_unsubscribes() -> None:
    async def scenario() -> tuple[list[str], int]:
        hub = Hub(queue_size=4)
        viewer = hub.subscribe("v")
        sent: list[str] = []

        async def send(text: str) -> None:
            sent.append(text)
            if len(sent) == 2:
                viewer.evict()

        for update in texts(3):
            hub.publish(update)
        await asyncio.wait_for(hub.serve(viewer, send), 1.0)
        return sent, hub.viewer_count

    sent, count = asyncio.run(scenario())
    assert len(sent) == 2 and count == 0


@pytest.mark.parametrize("options", [{"queue_size": 0}, {"evict_after": 0}])
def test_bounds_must_be_positive(options: dict) -> None:
    with pytest.raises(ValueError, match="must be positive"):
        Hub(**options)
