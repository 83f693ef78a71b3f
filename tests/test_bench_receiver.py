"""``bench.receiver``'s accounting: messages are judged against the bytes sent, and goodput is
a share of the ceiling that cannot exceed it."""

from __future__ import annotations

import numpy as np
import pytest

from bench.receiver import SMALL, Case, _passed_refreshes, _row, goodput_bps, run_case
from eventocc.occ.frame_codec import FrameCodec
from eventocc.occ.stream import StreamDecoder, StreamEncoder
from eventocc.receiver.pipeline.config import ReceiverConfig
from eventocc.receiver.pipeline.decoder import FrameRead
from eventocc.receiver.pipeline.receiver import FrameOutput, MessageOutput, Receiver
from eventocc.receiver.pipeline.report import DecodeLog, FrameTruth

SENT = b"the message that was sent"
PLAUSIBLE = b"the message that was SENT"
"""As long as ``SENT`` and different: what a wrong Reed-Solomon correction could deliver."""


def _columns(row: str) -> list[str]:
    return [c.strip() for c in row.strip().strip("|").split("|")]


def _paper_report(delivered: bytes) -> dict:
    """The report of a receiver that was sent ``SENT`` with the paper profile and delivered
    ``delivered`` (as decoded from its frames), with the fields the bench's row adds."""
    decoder = StreamDecoder(profile="paper", message_size=len(delivered))
    encoder = StreamEncoder(delivered, profile="paper")
    got = next(m for k in range(0, 40, 2) for m in decoder.push(encoder.payload_bits(k)))
    rx = Receiver(ReceiverConfig(SMALL, cells=16, profile="paper"), message_size=len(SENT))
    rx.stats.first_event_us, rx.stats.last_event_us, rx.stats.events = 0, 400_000, 1000
    log = DecodeLog(rx, FrameTruth(StreamEncoder(SENT, profile="paper"), 60.0))
    log.add([MessageOutput(200_000, got)])
    report = log.report()
    report.update(cpu_total_s=0.1, tracking_s=0.0, tracking_cpu_s=0.0, passed_share=None)
    report["message_bits"] = 8 * len(SENT)
    return report


def test_a_plausible_wrong_paper_message_is_neither_verified_nor_counted():
    report = _paper_report(PLAUSIBLE)
    (message,) = report["messages"]
    assert not message["verified"] and message["check"] == "unchecked"
    assert message["matches_sent"] is False
    case = Case("paper", 16, 60.0, SMALL, 0.6, 0.4)
    columns = _columns(_row(case, report))
    assert columns[5] == "none"  # no goodput from a wrong message
    assert columns[7] == "1"  # one wrong message
    assert columns[9] == "none"  # no right message


def test_the_right_paper_message_counts_but_stays_unchecked():
    report = _paper_report(SENT)
    (message,) = report["messages"]
    assert message["matches_sent"] and not message["verified"]
    case = Case("paper", 16, 60.0, SMALL, 0.6, 0.4)
    assert goodput_bps(case, report) == pytest.approx(8 * len(SENT) / 0.2)
    assert _columns(_row(case, report))[7] == "0"


@pytest.mark.parametrize("duration_s", [0.22, 0.45])
def test_goodput_never_exceeds_the_ceiling(duration_s):
    # A clean still camera: nearly every frame passes, so counting frames by their start over a
    # span holding one start more than whole periods would put goodput above the ceiling.
    case = Case("robust", 16, 60.0, SMALL, 0.6, duration_s)
    columns = _columns(_row(case, run_case(case, replays=1)))
    ceiling, goodput = float(columns[3]), float(columns[5])
    assert 0.5 * ceiling < goodput <= ceiling


def test_goodput_share_counts_the_frames_that_failed():
    # Every third data frame arrives garbled: a third of the shown frames did not pass.
    encoder = StreamEncoder(bytes(range(200)) * 4, profile="robust", cells=16)
    truth = FrameTruth(encoder, 60.0)
    codec = FrameCodec(encoder.profile, 16)
    shown = truth.data_refreshes(0, 1_000_000)
    assert shown == [k for k in range(60) if encoder.is_data_frame(k)]
    outputs = []
    for i, k in enumerate(shown):
        bits = encoder.payload_bits(k)
        if i % 3 == 2:
            bits = bits ^ np.eye(16, dtype=np.uint8) ^ 1  # all but a diagonal flipped
        read = FrameRead(i, round(k * 1e6 / 60) + 2_000, bits, np.ones((16, 16)), 0.8, 100)
        outputs.append(FrameOutput(read, True))
    passed = _passed_refreshes(truth, codec, outputs)
    assert passed == {k for i, k in enumerate(shown) if i % 3 != 2}
