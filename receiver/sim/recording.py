"""Write a simulated recording to a directory: events, ground truth and the scene.

- ``events.<ext>``: the event stream (any format ``eventocc.receiver.io.write_events`` knows;
  EVT 3.0 ``.raw`` by default), written chunk by chunk;
- ``poses.tum``: ground-truth T_world_cam (marker frame) at ``pose_hz``, on the events' clock;
- ``frames.npz``: every display refresh in the recording: ``refresh`` index, ``time_us`` (start
  of its scan-out at the top screen row, on the events' clock), ``is_data`` (False for a
  lead-in's refreshes) and, for data refreshes, ``data_refresh`` and ``payload_bits``
  (n, N, N);
- ``scene.json``: ``Scene.describe()``, enough to rerun the simulation.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from eventocc.receiver.io import write_events
from eventocc.receiver.poses import write_tum
from eventocc.receiver.sim.engine import Recording


def write_recording(
    rec: Recording,
    out_dir: str | Path,
    *,
    events_name: str = "events.raw",
    pose_hz: float = 1000.0,
    progress: bool = True,
) -> dict:
    """Run ``rec`` and write it under ``out_dir``; returns a summary (paths, event count)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "scene.json").write_text(json.dumps(rec.scene.describe(), indent=2))
    t_pose = np.arange(0, rec.duration_us + 1, 1e6 / pose_hz).round().astype(np.int64)
    t_pose += rec.scene.time_base_us
    write_tum(out / "poses.tum", t_pose, rec.pose_at(t_pose))
    _write_frames(rec, out / "frames.npz")
    chunks: Iterable[np.ndarray] = rec
    if progress:
        chunks = _with_progress(rec)
    count = write_events(out / events_name, chunks, width=rec.width, height=rec.height)
    return {"dir": str(out), "events": count, "duration_s": rec.duration_us / 1e6}


def _write_frames(rec: Recording, path: Path) -> None:
    scene = rec.scene
    enc = scene.encoder
    period = scene.display.period_us
    k0 = scene.first_refresh
    k1 = k0 + int(np.ceil(rec.duration_us / period))
    refresh = np.arange(k0, k1)
    is_data = np.array(
        [k >= scene.start_refresh and enc.is_data_frame(int(k)) for k in refresh], dtype=bool
    )
    data = refresh[is_data]
    n = enc.geometry.cells
    bits = (
        np.stack([enc.payload_bits(int(k)) for k in data])
        if len(data)
        else np.zeros((0, n, n), np.uint8)
    )
    np.savez_compressed(
        path,
        refresh=refresh,
        time_us=rec.refresh_times_us(k0, k1),
        is_data=is_data,
        data_refresh=data,
        payload_bits=bits,
    )


def _with_progress(rec: Recording) -> Iterable[np.ndarray]:
    from tqdm import tqdm

    with tqdm(
        total=rec.duration_us / 1e6,
        unit="sim s",
        desc="simulate",
        bar_format="{l_bar}{bar}| {n:.2f}/{total:.2f} sim s [{elapsed}<{remaining}]",
    ) as bar:
        for chunk in rec:
            bar.update(rec.chunk_us / 1e6)
            yield chunk
