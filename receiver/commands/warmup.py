"""``eventocc-receiver warmup``: compile the receiver's and the virtual camera's kernels now.

The per-event loops are numba kernels, compiled on first use and cached on disk beside their
modules (or in ``NUMBA_CACHE_DIR``). Compiling them all takes most of a minute on one core, which
a first ``receive`` or ``make demo`` would otherwise spend in silence: the install runs this
once, so every later start loads the cache. It drives each path on tiny inputs: the simulator
still and hand-held, the receiver on both (detection, tracking, triage, decoding), the
Reed-Solomon corrector and the EVT 3.0 reader and writer.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from eventocc.receiver.commands import add_command


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = add_command(
        subparsers,
        "warmup",
        help="compile the kernels once (an install does), so later starts load them at once",
        doc=__doc__,
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    started = time.perf_counter()
    if not args.quiet:
        print("compiling the receiver's kernels (once per install; about a minute on one core)")
    warm_up()
    if not args.quiet:
        print(f"compiled in {time.perf_counter() - started:.0f} s")
    return 0


def warm_up() -> None:
    from eventocc.occ.fec import ReedSolomon
    from eventocc.occ.stream import StreamEncoder
    from eventocc.receiver.camera import CameraModel
    from eventocc.receiver.io import read_events, write_events
    from eventocc.receiver.pipeline.config import ReceiverConfig
    from eventocc.receiver.pipeline.receiver import Receiver
    from eventocc.receiver.pipeline.report import decode_events
    from eventocc.receiver.sim import HandHeldMotion, Scene, StaticMotion, simulate

    camera = CameraModel.paper().binned(320, 180)
    for profile in ("robust", "fast"):  # fast keeps both polarities' bursts
        encoder = StreamEncoder(b"warm-up", profile=profile, cells=16)
        for motion in (StaticMotion(0.6), HandHeldMotion(flow_px_per_ms=0.3, seed=0)):
            scene = Scene(encoder=encoder, camera=camera, motion=motion, seed=0)
            receiver = Receiver(ReceiverConfig(camera, cells=16, profile=profile))
            chunks = list(simulate(scene, duration_s=0.15, chunk_us=10_000))
            decode_events(receiver, chunks)
    rs = ReedSolomon(255, 223)
    word = rs.encode(np.zeros((1, 223), np.uint8))
    word[0, :3] ^= 1
    rs.decode(word)
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "warm-up.raw"
        write_events(path, chunks, width=camera.width, height=camera.height)
        for _ in read_events(path):
            pass
