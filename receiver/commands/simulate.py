"""``eventocc-receiver simulate``: record the virtual event camera watching a message stream."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from eventocc.occ.profiles import DEFAULT_PROFILE, PROFILE_NAMES
from eventocc.occ.stream import StreamEncoder
from eventocc.receiver.commands import add_command
from eventocc.receiver.sim import (
    HandHeldMotion,
    Optics,
    Scene,
    SensorModel,
    StaticMotion,
    TumMotion,
    simulate,
)
from eventocc.receiver.sim.recording import write_recording
from eventocc.receiver.sim.scene import marker_size_for_cell_px
from eventocc.receiver.sim.sensor import PRESETS

log = logging.getLogger(__name__)


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub, "simulate", help="simulate an event camera watching the marker", doc=__doc__
    )
    p.add_argument("--message", type=Path, required=True, help="file whose bytes are sent")
    p.add_argument("--profile", choices=PROFILE_NAMES, default=DEFAULT_PROFILE, help="link profile")
    p.add_argument("--cells", type=int, default=16, help="payload cells across (N)")
    p.add_argument(
        "--motion", choices=("static", "handheld"), default="static", help="the camera's motion"
    )
    p.add_argument("--trajectory", type=Path, help="TUM file of T_world_cam (overrides --motion)")
    p.add_argument(
        "--distance", type=float, help="metres to the marker (default 1.25 static, 0.6 hand-held)"
    )
    p.add_argument("--flow", type=float, default=1.0, help="hand-held mean marker flow, px/ms")
    p.add_argument(
        "--marker-size",
        type=float,
        default=0.272,
        help="side of the white ring's outer boundary, metres",
    )
    p.add_argument(
        "--px-per-cell",
        type=float,
        help="size the marker so a cell spans this many pixels at --distance, facing the "
        "camera (overrides --marker-size)",
    )
    p.add_argument("--duration", type=float, default=5.0, help="seconds")
    p.add_argument("--preset", choices=tuple(PRESETS), default="gen4-indoor", help="sensor model")
    p.add_argument("--lux", type=float, help="ambient light (default: the preset's)")
    p.add_argument(
        "--start-refresh",
        type=int,
        default=0,
        help="the transmitter's refresh index at the recording's start",
    )
    p.add_argument(
        "--seed", type=int, default=0, help="random seed of the sensor noise and the hand's path"
    )
    p.add_argument(
        "--events", default="events.raw", help="events file name; its extension picks the format"
    )
    p.add_argument("--out", type=Path, required=True, help="output directory")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    try:
        return _run(args)
    except ValueError as exc:  # options the scene refuses: say what, no traceback
        print(f"eventocc-receiver simulate: error: {exc}", file=sys.stderr)
        return 2


def _run(args: argparse.Namespace) -> int:
    if args.trajectory is not None:
        motion = TumMotion(str(args.trajectory))
    elif args.motion == "static":
        motion = StaticMotion(distance_m=args.distance or 1.25)
    else:
        motion = HandHeldMotion(
            distance_m=args.distance or 0.6, flow_px_per_ms=args.flow, seed=args.seed
        )
    encoder = StreamEncoder(
        args.message.read_bytes(), name=args.message.name, profile=args.profile, cells=args.cells
    )
    marker_size = args.marker_size
    if args.px_per_cell is not None:
        if not args.px_per_cell > 0:
            raise ValueError(f"--px-per-cell must be positive, got {args.px_per_cell:g}")
        if args.trajectory is not None and args.distance is None:
            raise ValueError("--px-per-cell with --trajectory needs --distance (metres)")
        distance = args.distance or (1.25 if args.motion == "static" else 0.6)
        camera = Scene(encoder).camera
        marker_size = marker_size_for_cell_px(
            args.px_per_cell, encoder.geometry, distance, camera.K[0, 0]
        )
    scene = Scene(
        encoder=encoder,
        marker_size_m=marker_size,
        motion=motion,
        sensor=SensorModel.preset(args.preset, lux=args.lux),
        optics=Optics.preset(args.preset),
        start_refresh=args.start_refresh,
        seed=args.seed,
    )
    summary = write_recording(simulate(scene, args.duration), args.out, events_name=args.events)
    log.info(
        "wrote %d events (%.2f s) to %s", summary["events"], summary["duration_s"], summary["dir"]
    )
    return 0
