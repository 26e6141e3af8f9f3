"""Ingest's direct PointCloud2 / image parsers agree with rosbags' deserialize, field by field,
on ROS 2 sqlite3, MCAP and ROS 1 bags (different wire formats), and refuse what they cannot
parse exactly (customised definitions, big-endian CDR, truncated messages)."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from tests.fixtures.real import requires_real_data
from v2xlake.tasks.ingest.rawmsg import LAYOUTS, parse, parser_for

REPO = Path(__file__).resolve().parents[1]
OUSTER = REPO.parent / "shared" / "data" / "real" / "bags" / "ouster_os1_128_3frames_ros2"


def same(ref: Any, mine: Any, where: str = "msg") -> None:
    """Every attribute of rosbags' message equals ours (type included for bools / arrays)."""
    if dataclasses.is_dataclass(ref):
        for f in dataclasses.fields(ref):
            if f.name.startswith("__") or f.name.isupper():  # __msgtype__, constants
                continue
            same(getattr(ref, f.name), getattr(mine, f.name), f"{where}.{f.name}")
    elif isinstance(ref, np.ndarray):
        assert isinstance(mine, np.ndarray) and mine.dtype == ref.dtype, where
        assert np.array_equal(ref, mine), where
    elif isinstance(ref, list):
        assert len(ref) == len(mine), where
        for i, (a, b) in enumerate(zip(ref, mine, strict=True)):
            same(a, b, f"{where}[{i}]")
    else:
        assert type(ref) is type(mine) and ref == mine, (where, ref, mine)


def messages(ts: Any) -> list[tuple[str, str, Any]]:
    """Odd lengths everywhere, so every CDR alignment case is hit."""
    T = ts.types
    ros1 = "seq" in {f[0] for f in ts.fielddefs["std_msgs/msg/Header"][1]}
    rng = np.random.default_rng(3)
    out: list[tuple[str, str, Any]] = []
    for i, frame in enumerate(["", "l", "li", "lid", "lidar", "lidar_top_front"]):
        stamp = T["builtin_interfaces/msg/Time"](sec=1_700_000_000 + i, nanosec=999_999_999 - i)
        hdr = {"stamp": stamp, "frame_id": frame, **({"seq": 7 + i} if ros1 else {})}
        header = T["std_msgs/msg/Header"](**hdr)
        names = ["x", "y", "z", "intensity", "t", "ring", "ambient"][: 1 + i]
        fields = [T["sensor_msgs/msg/PointField"](name=n, offset=4 * k, datatype=1 + (k % 8),
                                                  count=1 + (k == 2)) for k, n in enumerate(names)]
        n = 7 * i
        step = 4 * len(names) + 3
        out.append(("/points", "sensor_msgs/msg/PointCloud2", T["sensor_msgs/msg/PointCloud2"](
            header=header, height=1 + (i % 2), width=n, fields=fields, is_bigendian=bool(i % 2),
            point_step=step, row_step=step * n,
            data=rng.integers(0, 256, (1 + i % 2) * step * n, dtype=np.uint8),
            is_dense=bool(i % 3))))
        out.append(("/png", "sensor_msgs/msg/CompressedImage", T["sensor_msgs/msg/CompressedImage"](
            header=header, format=["png", "jpeg", "rgb8; png compressed"][i % 3],
            data=rng.integers(0, 256, 5 + 3 * i, dtype=np.uint8))))
        w, h = 3 + i, 2
        out.append(("/raw", "sensor_msgs/msg/Image", T["sensor_msgs/msg/Image"](
            header=header, height=h, width=w, encoding=["mono8", "bgr8", "16UC1"][i % 3],
            is_bigendian=i % 2, step=w * 3 + i,
            data=rng.integers(0, 256, h * (w * 3 + i), dtype=np.uint8))))
    return out


def write_bag(path: Path, storage: str) -> Path:
    ros1 = storage == "ros1"
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    msgs = messages(ts)
    conns: dict[str, Any] = {}
    if ros1:
        bag = path / "x.bag"
        with Writer1(bag) as w:
            for k, (topic, typ, msg) in enumerate(msgs):
                if topic not in conns:
                    conns[topic] = w.add_connection(topic, typ, typestore=ts)
                w.write(conns[topic], k + 1, ts.serialize_ros1(msg, typ))
        return bag
    bag = path / "x"
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer2(bag, version=8, storage_plugin=plugin) as w2:
        for k, (topic, typ, msg) in enumerate(msgs):
            if topic not in conns:
                conns[topic] = w2.add_connection(topic, typ, typestore=ts)
            w2.write(conns[topic], k + 1, ts.serialize_cdr(msg, typ))
    return bag


def check_bag(bag: Path) -> int:
    n = 0
    with AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as r:
        for conn, _t, raw in r.messages():
            fast = parser_for(r.typestore.fielddefs, conn.msgtype, bool(r.is2))
            assert fast is not None, conn.msgtype
            mine = fast(raw)
            assert mine is not None
            same(r.deserialize(raw, conn.msgtype), mine)
            n += 1
    return n


@pytest.mark.parametrize("storage", ["sqlite3", "mcap", "ros1"])
def test_fast_parsers_equal_rosbags(tmp_path: Path, storage: str) -> None:
    assert check_bag(write_bag(tmp_path, storage)) == 6 * len(LAYOUTS)


@requires_real_data("bags/ouster_os1_128_3frames_ros2")
def test_fast_parser_on_real_ouster_bag() -> None:
    with AnyReader([OUSTER], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as r:
        conns = [c for c in r.connections if c.msgtype == "sensor_msgs/msg/PointCloud2"]
        assert conns
        fast = parser_for(r.typestore.fielddefs, conns[0].msgtype, True)
        assert fast is not None
        n = 0
        for conn, _t, raw in r.messages(connections=conns):
            ref = r.deserialize(raw, conn.msgtype)
            same(ref, fast(raw))
            n += 1
        assert n == 3


def test_fast_parser_refuses_what_it_cannot_parse_exactly() -> None:
    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    msg = T["sensor_msgs/msg/CompressedImage"](
        header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=1, nanosec=2),
                                        frame_id="cam"), format="png",
        data=np.arange(9, dtype=np.uint8))
    typ = "sensor_msgs/msg/CompressedImage"
    # big-endian CDR: not ours, rosbags reads it
    assert parse(ts.serialize_cdr(msg, typ, little_endian=False), typ, ros2=True) is None
    # truncated: a clear error, never a silent short blob
    raw = ts.serialize_cdr(msg, typ)
    with pytest.raises(ValueError, match=r"truncated|past the end"):
        parse(raw[:-4], typ, ros2=True)
    # a bag with its own (non-standard) definition of the type: no fast parser
    custom = get_typestore(Stores.EMPTY)
    custom.register(get_types_from_msg("std_msgs/Header header\nstring format\nuint8[] data\n"
                                       "uint32 quality", typ))
    defs = dict(ts.fielddefs)
    defs[typ] = custom.fielddefs[typ]
    assert parser_for(defs, typ, True) is None
    assert parser_for(ts.fielddefs, typ, True) is not None
    assert parser_for(ts.fielddefs, "sensor_msgs/msg/Imu", True) is None
