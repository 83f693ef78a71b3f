"""The simulator's public contract: construction, ground truth, description, CLI, bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest

from eventocc.occ.stream import StreamEncoder
from eventocc.receiver.camera import CameraModel
from eventocc.receiver.cli import main
from eventocc.receiver.sim import HandHeldMotion, Scene, SensorModel, StaticMotion, simulate

SMALL = CameraModel.paper().resized(160, 120)


def scene(**kw) -> Scene:
    base = {
        "encoder": StreamEncoder(b"contract", profile="robust", cells=16),
        "camera": SMALL,
        "motion": StaticMotion(distance_m=4.0),
        "sensor": SensorModel.preset("gen4-indoor"),
    }
    return Scene(**(base | kw))


def test_description_round_trips():
    s = scene(motion=HandHeldMotion(distance_m=4.0, flow_px_per_ms=0.5, seed=2), seed=7)
    d = json.loads(json.dumps(s.describe()))
    assert Scene.from_dict(d).describe() == d


def test_ground_truth_poses_and_refresh_times():
    rec = simulate(scene(start_refresh=5), 0.05)
    T = rec.pose_at(np.array([0, 10_000, 20_000]))
    assert T.shape == (3, 4, 4)
    assert T[0, 2, 3] == pytest.approx(-4.0)  # 4 m in front of the screen (z into it)
    times = rec.refresh_times_us(5, 8)
    assert times[0] == 0.0 and np.allclose(np.diff(times), 1e6 / 60)


def test_a_hand_held_path_started_later_carries_on_from_there():
    motion = HandHeldMotion(distance_m=4.0, flow_px_per_ms=0.5, seed=2)
    later = HandHeldMotion(distance_m=4.0, flow_px_per_ms=0.5, seed=2, start_s=0.25)
    t = np.array([0, 10_000, 20_000])
    rig = scene().rig
    assert np.allclose(
        later.trajectory(rig).pose_at(t), motion.trajectory(rig).pose_at(t + 250_000)
    )
    s = scene(motion=later)
    assert Scene.from_dict(json.loads(json.dumps(s.describe()))).motion == later


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda: simulate(scene(), 0.0), "duration must be positive"),
        (lambda: SensorModel.preset("gen9"), "unknown sensor preset"),
        (lambda: scene(marker_size_m=-1.0), "marker_size_m must be positive"),
        (lambda: scene(start_refresh=-1), "start_refresh must be >= 0"),
        (lambda: simulate(scene(motion=HandHeldMotion(distance_m=0.5)), 0.1), "does not fit"),
    ],
)
def test_bad_input_is_refused_with_a_clear_message(make, message):
    with pytest.raises(ValueError, match=message):
        make()


def test_cli_writes_events_poses_frames_and_scene(tmp_path):
    msg = tmp_path / "msg.txt"
    msg.write_bytes(b"hello from the cli")
    out = tmp_path / "rec"
    assert (
        main(
            [
                "simulate",
                "--message",
                str(msg),
                "--profile",
                "paper",
                "--duration",
                "0.05",
                "--distance",
                "8",
                "--out",
                str(out),
                "--events",
                "events.npz",
            ]
        )
        == 0
    )
    assert {p.name for p in out.iterdir()} >= {
        "events.npz",
        "poses.tum",
        "frames.npz",
        "scene.json",
    }
    frames = np.load(out / "frames.npz")
    assert frames["is_data"][0] and frames["payload_bits"].shape[1:] == (16, 16)


def test_cli_sizes_the_marker_for_the_pixels_per_cell_asked(tmp_path):
    msg = tmp_path / "msg.txt"
    msg.write_bytes(b"pixels per cell")
    out = tmp_path / "rec"
    args = ["simulate", "--message", str(msg), "--cells", "16", "--duration", "0.02"]
    assert main([*args, "--px-per-cell", "9", "--distance", "3", "--out", str(out)]) == 0
    described = json.loads((out / "scene.json").read_text())
    assert described["cell_px"] == pytest.approx(9.0, rel=1e-6)
    assert described["sensor"]["name"] == "gen4-indoor"


def test_cli_refuses_pixels_per_cell_that_do_not_make_a_marker(tmp_path, capsys):
    msg = tmp_path / "msg.txt"
    msg.write_bytes(b"x")
    args = ["simulate", "--message", str(msg), "--out", str(tmp_path / "rec")]
    assert main([*args, "--px-per-cell", "0"]) == 2
    assert "--px-per-cell must be positive" in capsys.readouterr().err
