"""Prophesee RAW and DAT: the published test vectors, the real recordings, corrupt input."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from eventocc.receiver.events import concat, make_events
from eventocc.receiver.io import EventFileError, read_events, write_events

REPO = Path(__file__).resolve().parent.parent
REAL_DATA = Path(os.environ.get("EVENTOCC_REAL_DATA", REPO / ".." / "shared" / "data" / "real"))


def raw_file(tmp_path: Path, header: str, payload: bytes, name: str = "v.raw") -> Path:
    path = tmp_path / name
    path.write_bytes(header.encode() + payload)
    return path


def words(dtype: str, *values: int) -> bytes:
    return np.array(values, dtype=dtype).tobytes()


def read_all(path: Path, **kw) -> np.ndarray:
    return concat(read_events(path, **kw))


def as_tuples(events: np.ndarray) -> list[tuple[int, int, int, int]]:
    return [tuple(int(v) for v in e) for e in events[["t", "x", "y", "p"]]]


EVT3 = "% evt 3.0\n% format EVT3;height=720;width=1280\n% end\n"
EVT2 = "% evt 2.0\n% format EVT2;height=720;width=1280\n% end\n"


def test_evt2_vector(tmp_path):
    path = raw_file(tmp_path, EVT2, bytes.fromhex("0f000080c820031a"))
    assert as_tuples(read_all(path)) == [(1000, 100, 200, 1)]


@pytest.mark.parametrize(
    ("endianness", "payload"),
    [
        (";endianness=legacy", "0a00021203080000"),  # IMX636: type/time/x/y half first
        ("", "030800000a000212"),  # GenX320: one little-endian u64
    ],
)
def test_evt21_vector_both_byte_orders(tmp_path, endianness, payload):
    header = f"% evt 2.1\n% format EVT21;height=720;width=1280{endianness}\n% end\n"
    time_high = (5000 >> 6) << 32 | 0x8 << 60
    time_high_bytes = words("<u4", time_high >> 32, 0) if endianness else words("<u8", time_high)
    path = raw_file(tmp_path, header, time_high_bytes + bytes.fromhex(payload))
    stream = read_events(path)
    assert stream.format == ("evt21-legacy" if endianness else "evt21")
    assert as_tuples(concat(stream)) == [(5000, 64, 10, 1), (5000, 65, 10, 1), (5000, 75, 10, 1)]


def test_evt3_single_event_vector(tmp_path):
    path = raw_file(tmp_path, EVT3, bytes.fromhex("0080e863c8006428"))
    assert as_tuples(read_all(path)) == [(1000, 100, 200, 1)]


def test_evt3_vector_words_including_lone_vect8(tmp_path):
    payload = words("<u2", 0x8001, 0x6388, 0x000A, 0x3040, 0x4803, 0x4010, 0x5080)
    events = read_all(raw_file(tmp_path, EVT3, payload))
    assert events["x"].tolist() == [64, 65, 75, 80, 95]
    assert set(events["t"].tolist()) == {5000}
    assert set(events["y"].tolist()) == {10} and set(events["p"].tolist()) == {-1}
    # A lone VECT_8 right after its base (OpenEB's decoder would drop it).
    lone = words("<u2", 0x8000, 0x6001, 0x0003, 0x3800, 0x5081)
    assert as_tuples(read_all(raw_file(tmp_path, EVT3, lone, "lone.raw"))) == [
        (1, 0, 3, 1),
        (1, 7, 3, 1),
    ]


def test_evt3_time_low_step_back_is_not_a_wrap_but_time_high_drop_is(tmp_path):
    payload = words(
        "<u2",
        0x8002,
        0x0005,
        0x632B,
        0x2001,
        0x6320,
        0x2002,  # TL 811 then 800
        0x8FFF,
        0x2003,
        0x8000,
        0x6001,
        0x2004,
    )  # TH 4095 -> 0 wraps 24 bits
    t = read_all(raw_file(tmp_path, EVT3, payload))["t"].tolist()
    assert t == [2 * 4096 + 811, 2 * 4096 + 800, 4095 * 4096, (1 << 24) + 1]


def test_dat_vector_and_type_00(tmp_path):
    for kind in (0x0C, 0x00):
        path = tmp_path / f"v{kind}.dat"
        path.write_bytes(
            b"% Data file containing CD events\n% Version 2\n% Width 640\n"
            b"% Height 480\n" + bytes([kind, 8]) + bytes.fromhex("e803000064003210")
        )
        stream = read_events(path)
        assert (stream.format, stream.width, stream.height) == ("dat", 640, 480)
        assert as_tuples(concat(stream)) == [(1000, 100, 200, 1)]


def test_dat_counts_the_u32_clock_wraps_and_refuses_reserved_bits(tmp_path):
    def dat(*records: tuple[int, int]) -> Path:
        path = tmp_path / "wrap.dat"
        body = np.array(list(records), dtype=[("t", "<u4"), ("w", "<u4")]).tobytes()
        path.write_bytes(b"% Width 640\n% Height 480\n" + bytes([0x0C, 8]) + body)
        return path

    w = 5 | (7 << 14) | (1 << 28)  # x 5, y 7, ON
    near_end = (1 << 32) - 10
    t = read_all(dat((near_end, w), (3, w), (near_end, w), (2, w)))["t"].tolist()
    assert t == [near_end, (1 << 32) + 3, (1 << 32) + near_end, (2 << 32) + 2]
    # A small step back is a sensor's reordering, not a wrap.
    assert read_all(dat((1000, w), (990, w)))["t"].tolist() == [1000, 990]
    stream = read_events(dat((1, w), (2, w | (1 << 30)), (3, w)))
    with pytest.raises(EventFileError, match="reserved bits 29-31 are set"):
        list(stream)


def test_writers_emit_the_vectors(tmp_path):
    ev = make_events([1000], [100], [200], [1])
    write_events(tmp_path / "a.dat", ev, width=640, height=480)
    assert (tmp_path / "a.dat").read_bytes().endswith(bytes.fromhex("0c08e803000064003210"))
    write_events(tmp_path / "a.raw", ev, width=1280, height=720, format="evt2")
    assert (
        (tmp_path / "a.raw").read_bytes().endswith(b"% end\n" + bytes.fromhex("0f000080c820031a"))
    )
    write_events(tmp_path / "b.raw", ev, width=1280, height=720)
    data = (tmp_path / "b.raw").read_bytes()
    assert b"% format EVT3;height=720;width=1280\n" in data
    assert data.endswith(bytes.fromhex("0080e863c8006428"))


# ------------------------------------------------------------------------- real recordings


@pytest.fixture(scope="module")
def real_data() -> Path:
    if not REAL_DATA.is_dir():
        if os.environ.get("CI") == "true":
            pytest.fail(f"real recordings not found at {REAL_DATA} (set EVENTOCC_REAL_DATA)")
        pytest.skip(f"real recordings not found at {REAL_DATA}")
    return REAL_DATA


def faery_events(path: Path) -> np.ndarray:
    faery = pytest.importorskip("faery")
    ref = faery.events_stream_from_file(path).to_array()
    return make_events(ref["t"].astype(np.int64), ref["x"], ref["y"], ref["on"])


def test_real_evt2_matches_faery(real_data):
    path = real_data / "evt2_sample.raw"
    stream = read_events(path)
    # The header names only the Gen3 plugin: 640x480 (faery falls back to 1280x720).
    assert (stream.format, stream.width, stream.height) == ("evt2", 640, 480)
    ours = concat(stream)
    assert len(ours) == 539_481
    np.testing.assert_array_equal(ours, faery_events(path))


def test_real_evt3_matches_faery(real_data):
    path = real_data / "evt3_sample.raw"
    stream = read_events(path, monotonic=True)
    assert (stream.format, stream.width, stream.height) == ("evt3", 1280, 720)
    ours = concat(stream)
    assert len(ours) == 219_596
    np.testing.assert_array_equal(ours, faery_events(path))


def test_real_evt3_literal_clock_steps_back_where_faery_holds_it(real_data):
    # After a TIME_LOW step back (811 -> 800 us with no event in between) faery keeps the later
    # time; by default we decode TIME_LOW literally, as OpenEB does: same events, some earlier.
    path = real_data / "evt3_sample.raw"
    ours, ref = read_all(path), faery_events(path)
    for field in ("x", "y", "p"):
        np.testing.assert_array_equal(ours[field], ref[field])
    late = ref["t"] - ours["t"]
    assert late.min() == 0 and 0 < late.max() <= 16
    assert 0 < np.count_nonzero(late) < 0.01 * len(ours)


def test_monotonic_option_holds_the_clock_for_every_format(tmp_path):
    path = tmp_path / "ev.txt"
    path.write_text("10 1 0 1\n30 2 0 0\n20 3 0 1\n40 4 0 0\n")  # t in us, one step back
    assert concat(read_events(path, monotonic=True))["t"].tolist() == [10, 30, 30, 40]
    assert concat(read_events(path))["t"].tolist() == [10, 30, 20, 40]


def test_real_evt3_reversals_are_small(real_data):
    t = read_all(real_data / "evt3_sample.raw")["t"]
    assert np.min(t - np.maximum.accumulate(t)) > -20


def test_small_blocks_and_chunks_decode_the_same_events(real_data, monkeypatch):
    path = real_data / "evt3_sample.raw"
    whole = read_all(path)
    monkeypatch.setattr("eventocc.receiver.io.prophesee_raw.CHUNK_EVENTS", 5000)
    monkeypatch.setattr("eventocc.receiver.io.prophesee_raw.BLOCK_BYTES", 4098)  # odd word boundary
    chunks = list(read_events(path))
    assert len(chunks) > 40 and max(len(c) for c in chunks) <= 5000
    np.testing.assert_array_equal(concat(chunks), whole)


# ------------------------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    ("payload", "problem", "offset"),
    [
        (words("<u2", 0x0005, 0x2001), "before any TIME_HIGH", 2),
        (words("<u2", 0x8000, 0x2001), "before any ADDR_Y", 2),
        (words("<u2", 0x8000, 0x0005, 0x4001), "before any VECT_BASE_X", 4),
        (words("<u2", 0x8000, 0x0005, 0x27FF), "outside the sensor", 4),
        (words("<u2", 0x8000, 0x02D0, 0x2001), "outside the sensor", 4),  # y = 720
        (words("<u2", 0x8000, 0x0001, 0x1234), "does not define", 4),
        (words("<u2", 0x8200, 0x0001, 0x2001, 0x8000, 0x2001), "goes back", 6),
    ],
)
def test_corrupt_evt3_raises_with_offset(tmp_path, payload, problem, offset):
    path = raw_file(tmp_path, EVT3, payload)
    with pytest.raises(EventFileError, match=problem) as info:
        read_all(path)
    assert info.value.offset == len(EVT3) + offset
    assert str(path) in str(info.value) and f"byte {len(EVT3) + offset}" in str(info.value)


def test_truncated_file_raises_or_stops_cleanly(tmp_path):
    ev = make_events(
        np.arange(0, 5000, 10), np.arange(500) % 100, np.arange(500) % 50, np.arange(500) % 2
    )
    for fmt, ext in (("evt3", "raw"), ("evt2", "raw"), ("dat", "dat")):
        path = tmp_path / f"t.{ext}"
        write_events(path, ev, width=128, height=64, format=fmt)
        path.write_bytes(path.read_bytes()[:-1])
        with pytest.raises(EventFileError, match="truncated"):
            read_all(path)
        with pytest.warns(UserWarning, match="truncated"):
            partial = read_all(path, on_error="stop")
        assert 0 < len(partial) < len(ev)
        np.testing.assert_array_equal(partial, ev[: len(partial)])


def test_raw_without_encoding_header_needs_format(tmp_path):
    path = raw_file(tmp_path, "% date today\n", bytes.fromhex("0080e863c8006428"))
    with pytest.raises(EventFileError, match="pass format="):
        read_all(path)
    assert len(read_all(path, format="evt3")) == 1


def test_dat_rejects_other_event_types(tmp_path):
    path = tmp_path / "trig.dat"
    path.write_bytes(b"% Data file containing triggers\n% Version 2\n" + bytes([0x0E, 8]))
    with pytest.raises(EventFileError, match="not CD events"):
        read_all(path)


def test_writers_reject_out_of_range_times(tmp_path):
    for fmt, t in (("evt2", 1 << 34), ("evt3", 1 << 34), ("dat", 1 << 32), ("evt3", -1)):
        with pytest.raises(ValueError, match=r"timestamps|negative"):
            write_events(
                tmp_path / "x.raw", make_events([t], [0], [0], [1]), format=fmt, width=10, height=10
            )
    with pytest.raises(ValueError, match="outside the 10x10 sensor"):
        write_events(tmp_path / "x.raw", make_events([0], [10], [0], [1]), width=10, height=10)


def test_monotonic_option_holds_the_clock_for_evt2_too(tmp_path):
    path = tmp_path / "ev.raw"
    ev = make_events([100, 300, 200, 400], [1, 2, 3, 4], [0, 0, 0, 0], [1, 0, 1, 0])
    write_events(path, [ev[:2], ev[2:]], format="evt2", width=8, height=8)  # one step back
    assert concat(read_events(path))["t"].tolist() == [100, 300, 200, 400]
    assert concat(read_events(path, monotonic=True))["t"].tolist() == [100, 300, 300, 400]
