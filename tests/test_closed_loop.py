"""The closed loop end to end on the virtual camera: a camera carried from near to far in the
middle of a message. The controller steps down, and the message completes across the changes,
its symbols of every density counting (``bench.loop_sim``: simulator, receiver rebuilt at each
change, controller fed by the receiver's frame reports)."""

from __future__ import annotations

from dataclasses import replace

from bench.closed_loop import FixedPoint, per_scene, runs_at, scene_key
from bench.loop_sim import LoopScene, random_message, run_link
from eventocc.occ.link_policy import LinkChoice, LinkPolicy, PolicyConfig, px_at
from eventocc.receiver.camera import CameraModel

MOVE_S = 0.8
IDEAL_PX = {"robust": 4.0, "fast": 5.0}
"""What the clean (``ideal``) sensor needs: it reads smaller cells than the EVK4."""


def test_a_camera_carried_away_mid_message_steps_down_and_the_message_completes() -> None:
    loop = LoopScene(
        0.35,
        screen_m=0.2,
        camera=CameraModel.paper().binned(640, 360),
        preset="ideal",
        distance_after=(MOVE_S, 0.9),
    )
    message = random_message(3000)
    policy = LinkPolicy(config=PolicyConfig(min_px=IDEAL_PX))
    run = run_link(loop, message, 6.0, policy=policy, stop_when_done=True)

    # Near, it had stepped up (a probe decided on the near camera's reports may go on screen
    # as it moves: it fails there and goes back or down).
    before = [s for s in run.segments if s.t_s <= MOVE_S]
    after = [s for s in run.segments if s.t_s > MOVE_S]
    climbed = max((s.choice for s in before if not s.reason.startswith("probe")), key=cells)
    assert climbed.cells > 16, run.segments
    assert after and after[0].reason.startswith(("down from", "probe of")), run.segments
    # Far away the densest marker it had climbed to no longer fits the camera's pixels.
    far_px = loop.px_per_cell(16, MOVE_S)
    assert px_at(far_px, 16, climbed.cells) < IDEAL_PX[climbed.profile]
    assert after[-1].choice.cells < climbed.cells

    assert run.message_ok, "the message must come out once, byte-exact and verified"
    assert run.message_done_s is not None and run.message_done_s > after[0].t_s
    # The symbols collected near count: far away alone, N = 16 robust (its 30 data frames a
    # second) would need over twice as long as it took.
    far_alone_s = 8 * len(message) / LinkChoice("robust", 16).payload_bps(loop.display_hz)
    assert run.message_done_s - after[0].t_s < 0.5 * far_alone_s


def cells(choice: LinkChoice) -> int:
    return choice.cells


def test_the_report_names_the_commit_each_scene_ran_at() -> None:
    point = FixedPoint(0.6, "still", "robust", 16, 25.8, 3000.0, 1.0)
    far = replace(point, distance_m=2.5)
    # An older results file names one commit for the whole sweep and one for the auto runs.
    revisions = per_scene({"sweep": ", commit aaa", "auto": ", commit bbb"}, [point, far], [])
    assert revisions == {"sweep 0.6 m still": ", commit aaa", "sweep 2.5 m still": ", commit aaa"}
    revisions[scene_key("sweep", 2.5, "still")] = ", commit ccc"
    assert runs_at(revisions, "sweep") == "commit aaa (0.6 m still); commit ccc (2.5 m still)"
