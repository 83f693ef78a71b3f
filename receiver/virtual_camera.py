"""The virtual event camera as a live source: it watches what the server's transmitter plays.

It asks the server which message, profile, cell count and frame the transmitter page shows,
fetches that message, and simulates an event camera watching that screen in real time, so the
whole loop (upload -> transmitter -> camera -> receiver -> dashboard) closes without hardware.
When the transmitter switches to another message the simulation restarts on it. Until a
transmitter page reports, the camera watches the newest uploaded message from its first frame,
as if a page were showing it.
"""

from __future__ import annotations

import json
import logging
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass, replace
from datetime import UTC, datetime

import numpy as np

from occ.stream import StreamEncoder
from receiver.camera import CameraModel
from receiver.events import empty_events
from receiver.sources import SourceError, paced

log = logging.getLogger(__name__)

MOTIONS = ("static", "handheld")
WAIT_S = 1.0
"""How often to ask again while there is nothing to watch."""
DISTANCE_M = 2.5
"""Camera to marker centre: about 5 pixels per cell on the default sensor."""


def default_camera() -> CameraModel:
    """A quarter-size paper camera (320x180): with the sensor below the marker makes about
    1 M events/s, so the simulator and the pipeline keep close to real time on one core."""
    return CameraModel.paper().resized(320, 180)


def virtual_sensor():
    from receiver.sim import SensorModel

    # Coarser contrast steps and a refractory period than the ideal sensor: ~5x fewer events
    # per refresh, still a few per cell edge, which is all the receiver needs.
    return replace(
        SensorModel.preset("ideal"), threshold_on=1.0, threshold_off=1.0, refractory_us=200.0
    )


@dataclass(frozen=True)
class Showing:
    """What the transmitter shows: a message, its link settings and the frame on screen now."""

    message_id: str
    profile: str
    cells: int
    refresh_hz: float
    frame_now: int

    def same_stream(self, other: Showing) -> bool:
        return (self.message_id, self.profile, self.cells) == (
            other.message_id,
            other.profile,
            other.cells,
        )


class VirtualCamera:
    def __init__(
        self,
        server_url: str,
        *,
        camera: CameraModel | None = None,
        motion: str = "static",
        chunk_us: int = 5_000,
        check_every_s: float = 1.0,
        seed: int = 0,
    ) -> None:
        if not server_url.startswith(("http://", "https://")):
            raise SourceError(
                f"the virtual camera needs the server's http(s) URL, got {server_url!r}"
            )
        if motion not in MOTIONS:
            raise SourceError(f"unknown motion {motion!r}; choose one of {', '.join(MOTIONS)}")
        self.server_url = server_url.rstrip("/")
        self.camera = camera or default_camera()
        self.width, self.height = self.camera.width, self.camera.height
        self.motion = motion
        self.chunk_us = chunk_us
        self.check_every_s = check_every_s
        self.seed = seed
        self._waiting_for: str | None = None
        self.receiving: tuple[str, int] | None = None
        """The receiver's profile and cells, once ``link_settings`` chose them."""

    # --- asking the server ---

    def _get(self, path: str) -> bytes | None:
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
        status = self._get("/api/transmitter/status")
        if status is not None:
            s = json.loads(status)
            if not (s["playing"] and s["message_id"]):
                return None
            hz = s["refresh_hz"] or 60.0
            age_s = (datetime.now(UTC) - datetime.fromisoformat(s["received"])).total_seconds()
            frame_now = s["frame_index"] + max(0, round(age_s * hz))
            return Showing(s["message_id"], s["profile"], s["cells"], hz, frame_now)
        messages = json.loads(self._get("/api/messages") or b'{"messages": []}')["messages"]
        if not messages:
            return None
        newest = messages[0]
        return Showing(newest["id"], newest["profile"], newest["cells"], 60.0, 0)

    def link_settings(self, profile: str | None, cells: int | None) -> tuple[str, int]:
        """Profile and cells to receive with: as given, else what the transmitter shows now,
        else the server's defaults (the receiver must be built before anything plays)."""
        try:
            showing = self.showing()
            if showing is None:
                defaults = json.loads(self._get("/api/profiles") or b"{}")
                showing = Showing("", defaults["default_profile"], defaults["default_cells"], 0, 0)
        except OSError as error:
            raise SourceError(f"cannot ask {self.server_url} what it transmits: {error}") from None
        self.receiving = (profile or showing.profile, cells or showing.cells)
        return self.receiving

    def encoder(self, showing: Showing) -> StreamEncoder:
        meta = json.loads(self._get(f"/api/messages/{showing.message_id}") or b"null")
        data = self._get(f"/api/messages/{showing.message_id}/content")
        if meta is None or data is None:
            raise LookupError(f"message {showing.message_id} is gone")
        return StreamEncoder(data, name=meta["name"], profile=showing.profile, cells=showing.cells)

    # --- simulating ---

    def scene(self, encoder: StreamEncoder, showing: Showing):
        from receiver.sim import Display, HandHeldMotion, Scene, StaticMotion

        motion = (
            HandHeldMotion(distance_m=DISTANCE_M, flow_px_per_ms=0.2, seed=self.seed)
            if self.motion == "handheld"
            else StaticMotion(distance_m=DISTANCE_M)
        )
        return Scene(
            encoder=encoder,
            start_refresh=showing.frame_now,
            motion=motion,
            camera=self.camera,
            sensor=virtual_sensor(),
            display=Display(refresh_hz=showing.refresh_hz),
            seed=self.seed,
        )

    def chunks(self) -> Iterator[np.ndarray]:
        """Endless: simulated events of whatever the transmitter shows, at real-time pace.

        While nothing plays it yields an empty chunk every ``WAIT_S``: a heartbeat, so the
        daemon keeps reporting its health.
        """
        from receiver.sim import simulate

        t_offset = 0
        while True:
            showing = self._something_to_watch()
            if showing is None:
                yield empty_events()
                time.sleep(WAIT_S)
                continue
            log.info(
                "virtual camera watching message %s (%s, %d cells) from frame %d",
                showing.message_id,
                showing.profile,
                showing.cells,
                showing.frame_now,
            )
            if self.receiving not in (None, (showing.profile, showing.cells)):
                log.warning(
                    "the transmitter sends %s with %d cells but the receiver expects %s with %d: "
                    "restart it with matching --profile/--cells",
                    showing.profile,
                    showing.cells,
                    *self.receiving,
                )
            try:
                scene = self.scene(self.encoder(showing), showing)
            except (OSError, LookupError) as error:
                log.warning("virtual camera cannot fetch message %s: %s", showing.message_id, error)
                yield empty_events()
                time.sleep(WAIT_S)
                continue
            next_check = time.monotonic() + self.check_every_s
            last_t = t_offset
            for events in paced(simulate(scene, duration_s=24 * 3600, chunk_us=self.chunk_us)):
                events["t"] += t_offset  # one continuous clock across restarts
                last_t = int(events["t"][-1]) if len(events) else last_t
                yield events
                if time.monotonic() >= next_check:
                    next_check = time.monotonic() + self.check_every_s
                    now = self._something_to_watch()
                    if now is None or not now.same_stream(showing):
                        break
            t_offset = last_t + 1

    def _something_to_watch(self) -> Showing | None:
        """``showing()``, with a failure logged once rather than raised: the camera waits."""
        try:
            showing = self.showing()
            reason = "nothing is playing"
        except (OSError, LookupError) as error:
            showing, reason = None, f"server unreachable ({error})"
        if showing is None and reason != self._waiting_for:
            log.info("virtual camera waiting: %s", reason)
        self._waiting_for = None if showing is not None else reason
        return showing
