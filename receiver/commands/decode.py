"""``eventocc-receiver decode``: recover messages and the camera trajectory from a recording."""

from __future__ import annotations

import argparse
import json
import logging
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from eventocc.occ.profiles import DEFAULT_PROFILE, PROFILE_NAMES
from eventocc.receiver.commands import add_command, read_with_progress
from eventocc.receiver.pipeline.config import ReceiverConfig
from eventocc.receiver.pipeline.receiver import Receiver
from eventocc.receiver.pipeline.report import decode_events

log = logging.getLogger(__name__)

CHUNK_US = 10_000
"""Events are pushed in 10 ms chunks: the granularity of idle pose output and frame decoding."""
DEFAULTS = {
    "profile": DEFAULT_PROFILE,
    "cells": 16,
    "refresh_hz": 60.0,
    "marker_size": 0.272,
    "message_size": None,
}
"""The link's settings where neither an option nor a scene gives them."""


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = add_command(sub, "decode", help="decode the marker in an event recording", doc=__doc__)
    p.add_argument("recording", type=Path, help="event file (RAW, DAT, AEDAT4, bag, npz, h5, ...)")
    p.add_argument(
        "--calibration", type=Path, help="camera calibration file (default: the camera of --scene)"
    )
    # The link's settings come from these options, else from --scene, else the defaults.
    p.add_argument(
        "--profile", choices=PROFILE_NAMES, help=f"link profile (default: {DEFAULTS['profile']})"
    )
    p.add_argument("--cells", type=int, help=f"payload side N (default: {DEFAULTS['cells']})")
    p.add_argument(
        "--refresh-hz",
        type=float,
        help=f"display refresh rate (default: {DEFAULTS['refresh_hz']:g})",
    )
    p.add_argument(
        "--marker-size",
        type=float,
        help=f"white ring's outer side, metres (default: {DEFAULTS['marker_size']})",
    )
    p.add_argument(
        "--message-size",
        type=int,
        help="message bytes (needed by the paper profile, which has no header)",
    )
    p.add_argument(
        "--pose-smoothing-ms",
        type=float,
        default=5.0,
        help="fit where each pose puts the marker to the tracker's updates within this many "
        "ms of it (0: raw updates)",
    )
    p.add_argument(
        "--orientation-smoothing-ms",
        type=float,
        default=15.0,
        help="fit each pose's orientation to the updates within this many ms of it (at least "
        "--pose-smoothing-ms); poses come this much later",
    )
    p.add_argument(
        "--scene",
        type=Path,
        help="simulator scene.json: ground truth for the BER, and the link settings not given",
    )
    p.add_argument("--out", type=Path, required=True, help="output directory")
    p.set_defaults(func=run)


def _link_settings(args: argparse.Namespace, scene) -> None:
    """Fill the link options not given from the scene, else from ``DEFAULTS``."""
    known = DEFAULTS
    if scene is not None:
        known = {
            "profile": scene.encoder.profile.name,
            "cells": scene.encoder.geometry.cells,
            "refresh_hz": scene.display.refresh_hz,
            "marker_size": scene.marker_size_m,
            "message_size": len(scene.encoder.message),
        }
    for name, value in known.items():
        if getattr(args, name) is None:
            setattr(args, name, value)


def _camera(args: argparse.Namespace, scene):
    if args.calibration is not None:
        from eventocc.receiver.calibration import load_calibration

        return load_calibration(args.calibration)
    if scene is not None:
        return scene.camera
    raise ValueError("give --calibration (or --scene for a simulated recording)")


def run(args: argparse.Namespace) -> int:
    from eventocc.receiver.io import read_events

    scene = None
    if args.scene is not None:
        from eventocc.receiver.sim import Scene
        from eventocc.receiver.sim.truth import SceneTruth

        scene = Scene.from_dict(json.loads(args.scene.read_text()))
    _link_settings(args, scene)
    camera = _camera(args, scene)
    stream = read_events(args.recording, chunk_us=CHUNK_US)
    if stream.width is not None and (stream.width, stream.height) != (camera.width, camera.height):
        raise ValueError(
            f"the recording is {stream.width}x{stream.height} but the calibration "
            f"is {camera.width}x{camera.height}; pass the matching --calibration"
        )
    config = ReceiverConfig(
        camera,
        cells=args.cells,
        profile=args.profile,
        refresh_hz=args.refresh_hz,
        marker_size_m=args.marker_size,
        pose_smoothing_us=round(args.pose_smoothing_ms * 1000),
        orientation_smoothing_us=round(args.orientation_smoothing_ms * 1000),
    )
    receiver = Receiver(config, message_size=args.message_size)
    truth = None
    if scene is not None:
        truth = SceneTruth(scene)
    chunks = _checked(read_with_progress(stream, desc="decode", quiet=args.quiet), camera)
    decoded = decode_events(receiver, chunks, truth)
    report = decoded.write(args.out)
    _summarise(report)
    return 0 if report["messages"] else 1


def _checked(chunks: Iterator[np.ndarray], camera) -> Iterator[np.ndarray]:
    """The chunks, each checked against the calibrated sensor."""
    for chunk in chunks:
        if len(chunk) and (chunk["x"].max() >= camera.width or chunk["y"].max() >= camera.height):
            raise ValueError(
                f"events beyond the calibrated {camera.width}x{camera.height} "
                "sensor; pass the matching --calibration"
            )
        yield chunk


def _summarise(report: dict) -> None:
    if not report["locked"]:
        reasons = ", ".join(list(report["detection_failures"])[:3]) or "no events"
        print(f"marker not found: {reasons}")
        return
    print(
        f"locked after {report['time_to_lock_s']:.2f} s; frames seen {report['frames_seen']}"
        f"/{report['frames_read']}; tracking losses {report['tracking_losses']}"
    )
    if report["ber"] is not None:
        print(f"BER before FEC {report['ber']:.2e}")
    for m in report["messages"]:
        if m["check"] == "unchecked":
            check = "unchecked: the paper profile sends no checksum"
        else:
            check = "verified" if m["verified"] else "does NOT match the sender's sha256"
        if "matches_sent" in m:
            check += (
                "; matches the scene's message" if m["matches_sent"] else "; NOT the message sent"
            )
        print(
            f"message {m['name'] or '(unnamed)'}: {m['size']} bytes, sha256 {m['sha256']} ({check})"
        )
    if report["realtime_factor"] is not None:
        stages = ", ".join(f"{k} {v:.2f}" for k, v in sorted(report["cpu_s"].items()))
        print(f"real-time factor {report['realtime_factor']:.2f} (CPU s per stage: {stages})")
    if not report["messages"]:
        print("no message completed (wrong --profile/--cells, or too short a recording?)")
