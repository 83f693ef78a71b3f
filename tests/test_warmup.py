"""The install's warm-up compiles every kernel a first run needs: nothing is compiled after it."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

FIRST_RUN = """
from eventocc.occ.stream import StreamEncoder
from eventocc.receiver.live.virtual_camera import default_camera, virtual_sensor
from eventocc.receiver.pipeline.config import ReceiverConfig
from eventocc.receiver.pipeline.receiver import Receiver
from eventocc.receiver.sim import HandHeldMotion, Scene, simulate

camera = default_camera()
for profile, cells in (("robust", 12), ("paper", 16), ("fast", 20)):
    scene = Scene(
        encoder=StreamEncoder(b"a first run", profile=profile, cells=cells),
        camera=camera,
        sensor=virtual_sensor(),
        motion=HandHeldMotion(flow_px_per_ms=0.05, seed=3),
        seed=3,
    )
    receiver = Receiver(ReceiverConfig(camera, cells=cells, profile=profile))
    for chunk in simulate(scene, duration_s=0.3, chunk_us=10_000):
        receiver.push(chunk)
    receiver.finish()
"""


def cached(folder: Path) -> set[str]:
    return {p.relative_to(folder).as_posix() for p in folder.rglob("*.nb[ic]")}


@pytest.mark.slow
def test_after_the_warmup_a_first_run_compiles_nothing(tmp_path):
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path), "NUMBA_NUM_THREADS": "1"}
    warmup = [sys.executable, "-m", "eventocc.receiver.cli", "warmup"]
    subprocess.run(warmup, env=env, check=True, capture_output=True)
    before = cached(tmp_path)
    assert before, "the warm-up cached nothing"
    subprocess.run([sys.executable, "-c", FIRST_RUN], env=env, check=True)
    assert cached(tmp_path) == before
