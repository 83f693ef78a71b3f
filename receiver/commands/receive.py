"""``eventocc-receiver receive``: the live receiver daemon.

Reads events from a source, runs the receiver pipeline on them, and streams poses, frame
statistics, progress and finished messages to an eventocc server over a websocket, while
keeping the full-rate trajectory and the finished messages in the output folder. If the server
is away, reports that matter (poses, messages) wait in the output folder's spool and are sent
when it is back. Ctrl-C stops it.

Sources: ``sim:`` (default) the virtual event camera watching what the server's transmitter
plays (``sim:MESSAGE_ID``: that message until a transmitter page reports, else the newest
upload; a paused or closed page shows it nothing); ``file:PATH`` or ``PATH`` a recording;
``nd:``, ``metavision:[SERIAL]``, ``dv:`` a live camera through an optional backend;
``nd-replay:PATH`` a recording replayed as a USB camera through the neuromorphic-drivers path
(its pace, USB ring and backlog).

A live camera's own event-rate limiter (on by default, see ``--max-event-rate``) and biases are
set from ``--camera-config FILE`` and the options below; its temperature and light reading,
where it gives them, go to the dashboard.

The receiver follows the link settings (profile, cells, refresh rate) of the server's
transmitter page: the virtual camera's, and a live camera's, which is taken to watch that page.
``--profile``, ``--cells`` and ``--refresh-hz`` pin them; a recording uses them or the defaults.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading
from pathlib import Path

from eventocc.occ.profiles import DEFAULT_PROFILE, PROFILE_NAMES, LinkSettings
from eventocc.receiver.camera import CameraModel
from eventocc.receiver.commands import add_command
from eventocc.receiver.live.controls import add_camera_arguments, camera_settings
from eventocc.receiver.live.daemon import (
    Daemon,
    DaemonConfig,
    LinkFollower,
    OutputFolder,
    Screen,
)
from eventocc.receiver.live.screen import ScreenWatch, TransmitterClient
from eventocc.receiver.live.sources import EventSource, RecordingSource
from eventocc.receiver.live.uri import open_source
from eventocc.receiver.live.virtual_camera import DEFAULT_MOTION, MOTIONS, VirtualCamera

log = logging.getLogger(__name__)

DEFAULT_LINK = LinkSettings(DEFAULT_PROFILE, 16)
"""What a receiver that cannot ask assumes, unless told (``--profile``, ``--cells``)."""


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub, "receive", help="run the live receiver daemon (events -> server)", doc=__doc__
    )
    p.add_argument(
        "--source",
        default="sim:",
        help="sim:[MESSAGE_ID] | file:PATH | PATH | nd: | metavision:[SERIAL] | dv: | "
        "nd-replay:PATH (default: sim:)",
    )
    p.add_argument(
        "--pace",
        choices=("realtime", "fast"),
        default="realtime",
        help="recordings: replay at the recorded pace (skipping ahead, as a live camera does, "
        "when the pipeline falls a second behind), or every event as fast as the pipeline runs",
    )
    p.add_argument(
        "--calibration",
        type=Path,
        help="camera calibration file (default: the virtual camera's 320x180 for sim:, "
        "else the paper's 1280x720)",
    )
    p.add_argument(
        "--profile",
        choices=PROFILE_NAMES,
        help=f"pin the link profile (default: the transmitter's; recordings: {DEFAULT_PROFILE})",
    )
    p.add_argument(
        "--cells",
        type=int,
        help="pin the payload side N (default: the transmitter's; recordings: 16)",
    )
    p.add_argument(
        "--refresh-hz",
        type=float,
        help="pin the display's refresh rate in Hz (default: the transmitter page's; "
        "recordings: 60)",
    )
    p.add_argument("--marker-size", type=float, default=0.272, help="marker side on screen, metres")
    p.add_argument(
        "--motion",
        choices=MOTIONS,
        default=DEFAULT_MOTION,
        help=f"sim: a tripod, or a gentle hand-held wander (default {DEFAULT_MOTION}); a "
        "simulation slower than real time skips ahead to stay live, and says so",
    )
    p.add_argument(
        "--server",
        default=os.environ.get("EVENTOCC_SERVER", "http://127.0.0.1:8000"),
        help="the eventocc server's URL (env EVENTOCC_SERVER; default http://127.0.0.1:8000)",
    )
    p.add_argument(
        "--token",
        default=os.environ.get("EVENTOCC_TOKEN"),
        help="the server's token, if it has one (default: env EVENTOCC_TOKEN)",
    )
    p.add_argument(
        "--out",
        type=Path,
        default=Path("out/receiver"),
        help="output folder: trajectory.tum (verified poses), trajectory_all.tum, messages/, "
        "spool.db (default out/receiver)",
    )
    p.add_argument(
        "--pose-hz",
        type=float,
        default=100.0,
        help="poses sent to the server per second, at most (the file keeps all; default 100)",
    )
    add_camera_arguments(p)
    p.set_defaults(func=run)


def websocket_url(http_url: str) -> str:
    if not http_url.startswith(("http://", "https://")):
        raise ValueError(f"--server must be an http:// or https:// URL, got {http_url!r}")
    return "ws" + http_url.removeprefix("http")


def _camera(args: argparse.Namespace) -> CameraModel:
    if args.calibration is not None:
        from eventocc.receiver.calibration import load_calibration

        return load_calibration(args.calibration)
    if args.source.startswith("sim:"):
        from eventocc.receiver.live.virtual_camera import default_camera

        return default_camera()
    return CameraModel.paper()


def _screen(source: EventSource, server_url: str) -> tuple[Screen | None, LinkSettings]:
    """What tells the daemon the screen's link settings, and what it sends now: the virtual
    camera knows what it simulates; a live camera is taken to watch the server's transmitter
    page; a recording shows whatever it recorded (the defaults, unless pinned)."""
    if isinstance(source, VirtualCamera):
        return source, source.server.link_settings(DEFAULT_LINK)
    if isinstance(source, RecordingSource):
        return None, DEFAULT_LINK
    watch = ScreenWatch(TransmitterClient(server_url), DEFAULT_LINK).start()
    return watch, watch.link


def run(args: argparse.Namespace) -> int:
    from eventocc.receiver.live.publisher import Publisher
    from eventocc.receiver.live.spool import Spool
    from eventocc.receiver.pipeline.config import LIVE_CPU_SHARE, DetectorParams, ReceiverConfig
    from eventocc.receiver.pipeline.receiver import Receiver

    camera = _camera(args)
    source = open_source(
        args.source,
        realtime=args.pace == "realtime",
        live_settings=camera_settings(args),
        server_url=args.server,
        camera=camera,
        motion=args.motion,
    )
    if (source.width, source.height) != (camera.width, camera.height):
        raise ValueError(
            f"the source is {source.width}x{source.height} but the calibration is "
            f"{camera.width}x{camera.height}; pass the matching --calibration"
        )

    def build(link: LinkSettings) -> Receiver:
        return Receiver(
            ReceiverConfig(
                camera,
                cells=link.cells,
                profile=link.profile,
                refresh_hz=link.refresh_hz,
                marker_size_m=args.marker_size,
                # A real-time source must not fall behind while detection keeps failing.
                detector=DetectorParams(
                    max_cpu_share=LIVE_CPU_SHARE if args.pace == "realtime" else None
                ),
            )
        )

    screen, sending = _screen(source, args.server)
    follower = LinkFollower(
        build, screen, sending, profile=args.profile, cells=args.cells, refresh_hz=args.refresh_hz
    )
    output = OutputFolder(args.out)
    spool = Spool(output.root / "spool.db")
    stop = threading.Event()
    publisher = Publisher(websocket_url(args.server), spool, token=args.token, on_fatal=stop.set)
    daemon = Daemon(
        source,
        follower.pipeline(),
        publisher.start(),
        output,
        DaemonConfig(pose_hz=args.pose_hz),
        follower,
    )
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    log.info(
        "receiver %s: %s, %s -> %s; output in %s",
        spool.receiver_id,
        args.source,
        follower.receiving,
        args.server,
        output.root,
    )
    try:
        summary = daemon.run(stop)
    except KeyboardInterrupt:
        summary = daemon.summary
    finally:
        if isinstance(screen, ScreenWatch):
            screen.stop()
        publisher.close()
        left = len(spool)
        spool.close()
    log.info(
        "stopped after %d events: %d poses, %d frames, %d messages; %d reports left in the spool",
        summary.events,
        summary.poses,
        summary.frames,
        len(summary.messages),
        left,
    )
    if publisher.error is not None:
        print(f"eventocc-receiver receive: error: {publisher.error}", file=sys.stderr)
        return 1
    return 0
