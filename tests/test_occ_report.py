"""The receiver -> server report schema: round trips through JSON and refuses bad reports."""

from __future__ import annotations

import hashlib

import pydantic
import pytest

from eventocc.occ.report import (
    FrameStats,
    HealthReport,
    Hello,
    MessageReport,
    PoseReport,
    ProgressReport,
    SurfaceReport,
    TrackingState,
    parse_report,
)
from eventocc.occ.stream import ReceivedMessage, StreamDecoder, StreamEncoder

REPORTS = [
    PoseReport(
        t_us=1_700_000_000_123_456,
        position=(0.1, -0.2, 1.5),
        quaternion_xyzw=(0.0, 0.0, 0.0, 1.0),
        state=TrackingState.TRACKING,
    ),
    FrameStats(t_us=5, frame_index=3, bits_read=256, confidence_mean=0.9, events_per_s=1e6),
    ProgressReport(stream_id=7, symbols_held=3, symbols_needed=10),
    HealthReport(cpu_load=0.4, events_per_s=2e6, state=TrackingState.SCANNING),
    SurfaceReport(t_us=9, width=2, height=1, pixels_b64="AP8="),
]


@pytest.mark.parametrize("report", REPORTS, ids=lambda r: r.type)
def test_reports_round_trip_through_json(report) -> None:
    assert parse_report(report.model_dump_json()) == report


def test_a_decoded_message_travels_as_a_report() -> None:
    enc = StreamEncoder(b"\x00\xffpayload", name="a.txt")
    dec = StreamDecoder()
    got, k = [], 0
    while not got:
        if enc.is_data_frame(k):
            got = dec.push(enc.payload_bits(k))
        k += 1
    report = parse_report(MessageReport.of(got[0]).model_dump_json())
    assert isinstance(report, MessageReport)
    assert (report.name, report.data, report.stream_id) == (
        "a.txt",
        b"\x00\xffpayload",
        enc.stream_id,
    )


def _decode(encoder: StreamEncoder, decoder: StreamDecoder) -> ReceivedMessage:
    for k in range(4 * encoder.cycle):
        if encoder.is_data_frame(k) and (got := decoder.push(encoder.payload_bits(k))):
            return got[0]
    raise AssertionError("the message did not decode")


def test_framed_messages_are_verified_against_the_sha256_their_sender_sent() -> None:
    sent = b"\x00\xffpayload"
    got = _decode(StreamEncoder(sent, profile="robust"), StreamDecoder(profile="robust"))
    assert got.sender_sha256 == hashlib.sha256(sent).hexdigest() and got.verified
    report = parse_report(MessageReport.of(got).model_dump_json())
    assert report.verified and report.sender_sha256 == got.sender_sha256


def test_paper_messages_are_unchecked_even_when_right() -> None:
    # paper sends no checksum: a plausible wrong message decodes just as a right one does.
    sent, other = b"the message sent", b"another message!"
    decoder = StreamDecoder(profile="paper", message_size=len(sent))
    got = _decode(StreamEncoder(other, profile="paper"), decoder)
    assert got.data == other and got.sender_sha256 is None and not got.verified
    report = parse_report(MessageReport.of(got).model_dump_json())
    assert not report.verified


def test_a_report_from_before_sender_sha256_still_parses_as_unchecked() -> None:
    text = (
        '{"type": "message", "stream_id": 1, "name": "", "size": 1, "sha256": "'
        + hashlib.sha256(b"a").hexdigest()
        + '", "data_b64": "YQ==", "profile": "robust"}'
    )
    report = parse_report(text)
    assert isinstance(report, MessageReport) and not report.verified


def test_progress_report_takes_the_decoder_progress() -> None:
    progress = {"stream_id": 1, "symbols_held": 2, "symbols_needed": 9, "name": None, "size": None}
    assert ProgressReport(**progress).symbols_needed == 9


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ('{"type": "teleport"}', "does not match any of the expected tags"),
        (
            '{"type": "frame", "t_us": 1, "frame_index": -1, "bits_read": 1, '
            '"confidence_mean": 0.5, "events_per_s": 1}',
            "greater than or equal to 0",
        ),
        (
            '{"type": "message", "stream_id": 1, "name": "", "size": 2, "sha256": "'
            + "0" * 64
            + '", "data_b64": "AAA=", "profile": "robust"}',
            "does not match sha256",
        ),
        (
            '{"type": "message", "stream_id": 1, "name": "", "size": 1, "sha256": "'
            + "0" * 64
            + '", "data_b64": "!!", "profile": "robust"}',
            "not valid base64",
        ),
        (
            '{"type": "message", "stream_id": 1, "name": "", "size": 1, "sha256": "'
            + hashlib.sha256(b"a").hexdigest()
            + '", "data_b64": "YQ==", "profile": "robust", "sender_sha256": "'
            + "0" * 64
            + '"}',
            "does not match the sender's sha256",
        ),
        ('{"type": "health", "cpu_load": 1, "events_per_s": 1, "state": "asleep"}', "state"),
        (
            '{"type": "surface", "t_us": 1, "width": 2, "height": 2, "pixels_b64": "AP8="}',
            "holds 2 bytes, not 2x2",
        ),
    ],
)
def test_bad_reports_are_refused_with_a_reason(text: str, match: str) -> None:
    with pytest.raises(pydantic.ValidationError, match=match):
        parse_report(text)


def test_hello_defaults_to_this_protocol_version() -> None:
    hello = Hello.model_validate_json('{"receiver_id": "cam-1"}')
    assert (hello.version, hello.token) == (1, None)
    with pytest.raises(pydantic.ValidationError):
        Hello(receiver_id="")
