"""Event files our writers do not make, made by the formats' own libraries (rosbags, faery) or,
for EVT 2.1, word by word: what the reader tests read."""

from __future__ import annotations

from pathlib import Path

import numpy as np

EVENT_MSG = "uint16 x\nuint16 y\ntime ts\nbool polarity\n"
ARRAY_MSG = "std_msgs/Header header\nuint32 height\nuint32 width\n{pkg}/Event[] events\n"
BAG_STORAGES = ("ros1", "sqlite3", "mcap")


def write_bag(
    path: Path, storage: str, pkg: str, chunks, width: int = 64, height: int = 48
) -> None:
    """A bag of ``pkg``/EventArray messages, one per chunk: ``storage`` is ``ros1`` (a .bag
    file), or ``sqlite3`` or ``mcap`` (a ROS 2 bag folder)."""
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ros2 = storage != "ros1"
    store = get_typestore(Stores.ROS2_HUMBLE if ros2 else Stores.ROS1_NOETIC)
    store.register(
        {
            **get_types_from_msg(EVENT_MSG, f"{pkg}/msg/Event"),
            **get_types_from_msg(ARRAY_MSG.format(pkg=pkg), f"{pkg}/msg/EventArray"),
        }
    )
    T = store.types
    Time, Header = T["builtin_interfaces/msg/Time"], T["std_msgs/msg/Header"]
    Event, Array = T[f"{pkg}/msg/Event"], T[f"{pkg}/msg/EventArray"]
    msgtype = f"{pkg}/msg/EventArray"
    if ros2:
        plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        writer = Writer2(path, version=9, storage_plugin=plugin)
    else:
        writer = Writer1(path)
    with writer:
        conn = writer.add_connection("/dvs/events", msgtype, typestore=store)
        for i, chunk in enumerate(chunks):
            events = [
                Event(
                    x=int(e["x"]),
                    y=int(e["y"]),
                    ts=Time(sec=int(e["t"]) // 10**6, nanosec=int(e["t"]) % 10**6 * 1000),
                    polarity=bool(e["p"] > 0),
                )
                for e in chunk
            ]
            header = {"stamp": Time(sec=i, nanosec=0), "frame_id": "camera"}
            if not ros2:
                header["seq"] = i
            msg = Array(header=Header(**header), height=height, width=width, events=events)
            data = store.serialize_cdr(msg, msgtype) if ros2 else store.serialize_ros1(msg, msgtype)
            writer.write(conn, i + 1, data)


def write_aedat4(path: Path, events: np.ndarray, width: int, height: int) -> None:
    import faery

    array = np.zeros(len(events), dtype=faery.EVENTS_DTYPE)
    array["t"], array["x"], array["y"], array["on"] = (
        events["t"],
        events["x"],
        events["y"],
        events["p"] > 0,
    )
    faery.events_stream_from_array(array, dimensions=(width, height)).to_file(path, zero_t0=False)


def write_evt21(path: Path, events: np.ndarray, width: int, height: int) -> None:
    """EVT 2.1 (faery cannot write it): a TIME_HIGH word whenever t >> 6 changes, then one
    event word per event, its mask's bit 0 set."""
    words, high = [], -1
    for e in events:
        t = int(e["t"])
        if t >> 6 != high:
            high = t >> 6
            words.append(0x8 << 60 | high << 32)
        x, y = int(e["x"]), int(e["y"])
        words.append(int(e["p"] > 0) << 60 | (t & 0x3F) << 54 | x << 43 | y << 32 | 1)
    header = f"% evt 2.1\n% format EVT21;height={height};width={width}\n% end\n"
    path.write_bytes(header.encode() + np.array(words, "<u8").tobytes())
