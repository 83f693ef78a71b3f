"""ROS1 and ROS2 bags (``.bag``, ``.mcap``, ``.db3`` or a rosbag2 folder) of event arrays.

Message types: ``dvs_msgs/EventArray`` (rpg_dvs_ros, ESIM) and ``prophesee_event_msgs/EventArray``
(prophesee_ros_wrapper, the authors' bags): header, height, width, then events of
``uint16 x, uint16 y, time ts, bool polarity``. The bag container is read by ``rosbags``
(extra ``bags``); the event arrays are parsed straight from the serialized bytes with numpy,
because deserializing them as Python objects costs a Python object per event.
"""

from __future__ import annotations

import itertools
import logging
import struct
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from eventocc.receiver.events import EVENT_DTYPE
from eventocc.receiver.io.errors import EventFileError, MissingExtraError, foreign_errors
from eventocc.receiver.io.stream import EventChecker, EventStream, Progressed, sensor_size

log = logging.getLogger(__name__)

EVENT_ARRAY_TYPES = ("dvs_msgs/msg/EventArray", "prophesee_event_msgs/msg/EventArray")
# ROS1 packs fields; ROS2's CDR aligns each field to its size, so elements after the first
# start 2 bytes off a 4-byte boundary and carry 2 bytes of padding before ``ts``.
ROS1_EVENT = np.dtype(
    {
        "names": ["x", "y", "sec", "nsec", "p"],
        "formats": ["<u2", "<u2", "<u4", "<u4", "u1"],
        "offsets": [0, 2, 4, 8, 12],
        "itemsize": 13,
    }
)
CDR_FIRST_EVENT = np.dtype(
    {
        "names": ["x", "y", "sec", "nsec", "p"],
        "formats": ["<u2", "<u2", "<i4", "<u4", "u1"],
        "offsets": [0, 2, 4, 8, 12],
        "itemsize": 14,
    }
)
CDR_EVENT = np.dtype(
    {
        "names": ["x", "y", "sec", "nsec", "p"],
        "formats": ["<u2", "<u2", "<i4", "<u4", "u1"],
        "offsets": [0, 2, 6, 10, 14],
        "itemsize": 16,
    }
)


def _anyreader():
    try:
        from rosbags.highlevel import AnyReader
    except ImportError:
        raise MissingExtraError("ROS bags", "rosbags", "bags") from None
    return AnyReader


def is_bag_dir(path: Path) -> bool:
    return path.is_dir() and (path / "metadata.yaml").exists()


def _bag_size(path: Path) -> int:
    return sum(p.stat().st_size for p in path.iterdir()) if path.is_dir() else path.stat().st_size


def open_rosbag(path: Path) -> EventStream:
    with _open_reader(path) as reader:
        connections = _event_connections(path, reader)
        with foreign_errors(path, "damaged ROS bag", where="in message 0"):
            first = next(reader.messages(connections=connections), None)
        width = height = None
        if first is not None:
            _, width, height = _parse(path, first[2], reader.is2, 0)
            width, height = sensor_size(
                path, *((width, height) if width and height else (None, None)), where="in message 0"
            )
        n_messages = sum(c.msgcount for c in connections)
    return EventStream(
        _messages(path, width, height, n_messages),
        path=path,
        format="rosbag",
        width=width,
        height=height,
        size=_bag_size(path),
    )


@contextmanager
def _open_reader(path: Path) -> Iterator:
    AnyReader = _anyreader()
    with foreign_errors(path, "not a readable ROS bag", offset=0):
        reader = AnyReader([path])
        reader.open()
    try:
        yield reader
    finally:
        reader.close()


def _event_connections(path: Path, reader) -> list:
    connections = [c for c in reader.connections if c.msgtype in EVENT_ARRAY_TYPES]
    if not connections:
        found = sorted({f"{c.topic} ({c.msgtype})" for c in reader.connections})
        raise EventFileError(
            path,
            f"no event array topic ({', '.join(EVENT_ARRAY_TYPES)}); topics: {found}",
            where="in the bag",
        )
    topics = sorted({c.topic for c in connections})
    if len(topics) > 1:
        log.warning("%s: several event topics %s; reading %s", path, topics, topics[0])
    return [c for c in connections if c.topic == topics[0]]


def _messages(path: Path, width, height, n_messages: int) -> Iterator[Progressed]:
    checker = EventChecker(width, height)
    size = _bag_size(path)
    with _open_reader(path) as reader:
        connections = _event_connections(path, reader)
        messages = reader.messages(connections=connections)
        for i in itertools.count():
            with foreign_errors(path, "damaged ROS bag", where=f"in message {i}"):
                message = next(messages, None)
            if message is None:
                return
            events, _, _ = _parse(path, message[2], reader.is2, i)
            problem = checker.first_problem(events)
            if problem is not None:
                j, what = problem
                if j:
                    yield events[:j], size * i // n_messages
                raise EventFileError(path, what, where=f"in message {i}, event {j}")
            yield events, size * (i + 1) // n_messages


def _parse(path: Path, raw: bytes, ros2: bool, index: int) -> tuple[np.ndarray, int, int]:
    """Events, width and height of one serialized EventArray message."""
    try:
        if ros2:
            if raw[:2] != b"\x00\x01":
                raise ValueError("only little-endian CDR is supported")
            body = memoryview(raw)[4:]
            (frame_len,) = struct.unpack_from("<I", body, 8)
            pos = 12 + frame_len
            pos += -pos % 4
            height, width, n = struct.unpack_from("<III", body, pos)
            pos += 12
            data = bytes(body[pos:]) + b"\0"  # the last element has no trailing padding
            first = np.frombuffer(data, CDR_FIRST_EVENT, count=min(n, 1))
            rest = (
                np.frombuffer(data, CDR_EVENT, count=n - 1, offset=CDR_FIRST_EVENT.itemsize)
                if n > 1
                else first[:0]
            )
            fields = np.concatenate([first.astype(CDR_EVENT), rest.astype(CDR_EVENT)])
        else:
            (frame_len,) = struct.unpack_from("<I", raw, 12)
            pos = 16 + frame_len
            height, width, n = struct.unpack_from("<III", raw, pos)
            fields = np.frombuffer(raw, ROS1_EVENT, count=n, offset=pos + 12)
    except (struct.error, ValueError) as e:
        raise EventFileError(
            path, f"malformed EventArray message ({e})", where=f"in message {index}"
        ) from None
    events = np.empty(len(fields), EVENT_DTYPE)
    events["t"] = fields["sec"].astype(np.int64) * 1_000_000 + fields["nsec"] // 1000
    events["x"] = fields["x"]
    events["y"] = fields["y"]
    events["p"] = np.where(fields["p"] > 0, 1, -1)
    return events, width, height
