"""Format detection, the container formats (bags, AEDAT4, text, HDF5) and the public API."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from eventocc.receiver.events import concat, make_events
from eventocc.receiver.io import EventFileError, detect_format, read_events, write_events
from eventocc.receiver.io.stream import EventChecker
from tests.event_files import write_aedat4, write_bag

EVENTS = make_events(
    np.arange(1000, 41000, 100), np.arange(400) % 64, np.arange(400) % 48, np.arange(400) % 3 == 0
)


def test_detection_by_content_beats_extension(tmp_path, caplog):
    write_events(tmp_path / "real.dat", EVENTS, width=64, height=48)
    (tmp_path / "real.dat").rename(tmp_path / "mislabelled.raw")
    with caplog.at_level(logging.WARNING):
        stream = read_events(tmp_path / "mislabelled.raw")
    assert stream.format == "dat" and "content is dat" in caplog.text
    np.testing.assert_array_equal(concat(stream), EVENTS)


@pytest.mark.parametrize(
    ("fmt", "name", "expected"),
    [
        ("evt3", "a.bin", "raw"),
        ("dat", "a.bin", "dat"),
        ("npz", "a.bin", "npz"),
        ("hdf5", "a.bin", "hdf5"),
        ("text", "a.txt", "text"),
    ],
)
def test_detect_format(tmp_path, fmt, name, expected):
    write_events(tmp_path / name, EVENTS, format=fmt, width=64, height=48)
    assert detect_format(tmp_path / name) == expected


def test_unknown_content_and_extension_is_a_clear_error(tmp_path):
    (tmp_path / "x.bin").write_bytes(b"\x01\x02\x03")
    with pytest.raises(EventFileError, match="pass one of"):
        read_events(tmp_path / "x.bin")
    with pytest.raises(FileNotFoundError):
        read_events(tmp_path / "missing.raw")
    with pytest.raises(ValueError, match="unknown event format"):
        read_events(tmp_path / "x.bin", format="mp4")
    with pytest.raises(ValueError, match="cannot tell the format to write"):
        write_events(tmp_path / "x.bin", EVENTS, width=64, height=48)


def test_chunking_options(tmp_path):
    write_events(tmp_path / "a.raw", EVENTS, width=64, height=48)
    by_count = list(read_events(tmp_path / "a.raw", chunk_events=64))
    assert [len(c) for c in by_count] == [64] * 6 + [16]
    by_time = list(read_events(tmp_path / "a.raw", chunk_us=10_000))
    assert all(np.ptp(c["t"]) < 10_000 for c in by_time) and len(by_time) == 5
    with pytest.raises(ValueError, match="not both"):
        read_events(tmp_path / "a.raw", chunk_events=1, chunk_us=1)


def test_stream_metadata_before_iterating(tmp_path):
    write_events(tmp_path / "a.h5", EVENTS, width=64, height=48)
    with read_events(tmp_path / "a.h5") as stream:
        assert (stream.format, stream.width, stream.height, stream.position) == ("hdf5", 64, 48, 0)
        list(stream)
        assert stream.position == stream.size


@pytest.mark.parametrize(
    ("body", "seconds"),
    [
        ("0.001000 3 4 1\n0.001500 5 6 0\n", True),
        ("1000 3 4 1\n1500 5 6 -1\n", False),
    ],
)
def test_text_seconds_or_microseconds(tmp_path, body, seconds):
    (tmp_path / "e.txt").write_text("# t x y p\n" + body)
    events = concat(read_events(tmp_path / "e.txt"))
    assert events["t"].tolist() == [1000, 1500] and events["p"].tolist() == [1, -1]
    assert read_events(tmp_path / "e.txt").width is None


def test_text_garbage_line_names_the_line(tmp_path):
    (tmp_path / "e.txt").write_text("1000 3 4 1\n1500 five 6 0\n")
    with pytest.raises(EventFileError, match="not 't x y p' text"):
        concat(read_events(tmp_path / "e.txt"))
    (tmp_path / "p.txt").write_text("1000 3 4 1\n1500 5 6 7\n")
    with pytest.raises(EventFileError, match="line 2"):
        concat(read_events(tmp_path / "p.txt"))


def test_dsec_style_hdf5_with_offset_and_blosc(tmp_path):
    h5py = pytest.importorskip("h5py")
    hdf5plugin = pytest.importorskip("hdf5plugin")
    with h5py.File(tmp_path / "dsec.h5", "w") as f:
        comp = hdf5plugin.Blosc(cname="zstd")
        f.create_dataset("events/t", data=np.array([5, 9], np.uint32), **comp)
        f.create_dataset("events/x", data=np.array([1, 2], np.uint16), **comp)
        f.create_dataset("events/y", data=np.array([3, 4], np.uint16), **comp)
        f.create_dataset("events/p", data=np.array([1, 0], np.uint8), **comp)
        f["t_offset"] = np.int64(1_000_000)
    events = concat(read_events(tmp_path / "dsec.h5"))
    assert events["t"].tolist() == [1_000_005, 1_000_009] and events["p"].tolist() == [1, -1]


def test_hdf5_ms_to_idx_follows_dsec(tmp_path):
    h5py = pytest.importorskip("h5py")
    write_events(tmp_path / "a.h5", [EVENTS[:150], EVENTS[150:]], width=64, height=48)
    with h5py.File(tmp_path / "a.h5") as f:
        t, index = f["events/t"][:], f["ms_to_idx"][:]
    for ms, i in enumerate(index):
        assert t[i] >= ms * 1000 and (i == 0 or t[i - 1] < ms * 1000)


# --------------------------------------------------------------------------------- ROS bags


@pytest.mark.parametrize(
    ("storage", "pkg"),
    [
        ("ros1", "dvs_msgs"),
        ("ros1", "prophesee_event_msgs"),
        ("sqlite3", "dvs_msgs"),
        ("mcap", "dvs_msgs"),
    ],
)
def test_rosbag_event_arrays(tmp_path, storage, pkg):
    pytest.importorskip("rosbags")
    events = EVENTS[:50].copy()
    events["t"] += 1_700_000_000_000_000  # epoch microseconds, as drivers stamp them
    path = tmp_path / ("e.bag" if storage == "ros1" else "bag2")
    write_bag(path, storage, pkg, [events[:1], events[1:20], events[20:20], events[20:]])
    stream = read_events(path)
    assert (stream.format, stream.width, stream.height) == ("rosbag", 64, 48)
    np.testing.assert_array_equal(concat(stream), events)


def test_bag_without_event_topic_is_a_clear_error(tmp_path):
    pytest.importorskip("rosbags")
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    with Writer(tmp_path / "s.bag") as w:
        conn = w.add_connection("/chatter", "std_msgs/msg/String", typestore=store)
        w.write(
            conn,
            1,
            store.serialize_ros1(
                store.types["std_msgs/msg/String"](data="hi"), "std_msgs/msg/String"
            ),
        )
    with pytest.raises(EventFileError, match="no event array topic"):
        read_events(tmp_path / "s.bag")


# ----------------------------------------------------------------------------------- AEDAT4


def test_aedat4_written_by_faery(tmp_path):
    pytest.importorskip("faery")
    pytest.importorskip("aedat")
    write_aedat4(tmp_path / "e.aedat4", EVENTS, 64, 48)
    stream = read_events(tmp_path / "e.aedat4")
    assert (stream.format, stream.width, stream.height) == ("aedat4", 64, 48)
    np.testing.assert_array_equal(concat(stream), EVENTS)


T = 2_000_005


@pytest.mark.parametrize(
    ("t", "x", "y", "index", "message"),
    [
        ([T, T, T], [1, 10, 2], [1, 1, 1], 1, "event at x=10, y=1 is outside the 10x8 sensor"),
        ([T, T, T], [1, 2, 3], [1, 1, 8], 2, "event at x=3, y=8 is outside the 10x8 sensor"),
        ([T, -1, T], [1, 2, 3], [1, 1, 1], 1, "negative timestamp -1 us"),
        # Reordered by up to a second, as sensors do: fine; more, against the earlier chunk too.
        ([1_500_000, 1_000_000, 999_999], [1, 2, 3], [1, 1, 1], 2, "time goes back from "),
    ],
)
def test_the_checker_names_the_first_implausible_event(t, x, y, index, message):
    checker = EventChecker(10, 8)
    assert checker.first_problem(make_events([1_000, 2_000_000], [0, 9], [0, 7], [1, 0])) is None
    found, what = checker.first_problem(make_events(t, x, y, np.ones(3, bool)))
    assert found == index and what.startswith(message)
    if "goes back" in message:
        assert what == (
            "time goes back from 2000000 to 999999 us, more than 1000000 us: "
            "not a real sensor's reordering"
        )
