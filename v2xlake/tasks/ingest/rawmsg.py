"""Direct parsers for the bulky sensor messages: ``PointCloud2``, ``CompressedImage``, ``Image``.

Why not rosbags' ``deserialize``: it is correct and general, but ingest only needs the header
fields and a zero-copy view of the ``data`` blob, and these three layouts are fixed by ROS.
Parsing them here (a handful of ``struct.unpack_from`` calls, ``np.frombuffer`` on the blob)
removes the generic per-message work from the single-threaded read loop, which is what ingest
throughput is measured against (``tests/bench/bench_ingest.py``: rosbags reading and
deserializing every message is the floor).

Exactness: the result has the same attributes and values as rosbags' message (checked field by
field in ``tests/test_ingest_rawmsg.py`` on sqlite3, MCAP and ROS 1 bags). Two wire formats:

- ROS 2 (sqlite3 / MCAP): CDR (XCDR1) after a 4-byte encapsulation header, primitives aligned
  to their size relative to the end of that header, strings with a terminating NUL counted in
  their length. Only little-endian CDR is parsed here; anything else returns ``None`` and the
  caller falls back to rosbags.
- ROS 1: little-endian, packed (no alignment), ``Header`` starts with ``seq``, strings without
  NUL.

``parser_for`` only offers a parser when the bag's definitions of the message and of every
nested type (Header, Time, PointField) have exactly the standard field lists, so a bag with a
customised definition is always read by rosbags.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from rosbags.typesys import Stores, get_typestore

U32 = struct.Struct("<I")
I32U32 = struct.Struct("<iI")
U32U32 = struct.Struct("<II")


@dataclass(frozen=True)
class Time:
    sec: int
    nanosec: int


@dataclass(frozen=True)
class Header:
    stamp: Time
    frame_id: str
    seq: int | None = None  # ROS 1 only


@dataclass(frozen=True)
class PointField:
    name: str
    offset: int
    datatype: int
    count: int


@dataclass
class RawMessage:
    """A parsed message: ``header`` plus the type's fields as attributes (``data`` is a uint8
    view into the raw buffer, never a copy)."""

    msgtype: str
    header: Header
    values: dict[str, Any]

    def __getattr__(self, name: str) -> Any:
        try:
            return self.__dict__["values"][name]
        except KeyError:
            raise AttributeError(name) from None


# field kinds: u32, u8 (int), bool, string, bytes (uint8 sequence), fields (PointField sequence)
LAYOUTS: dict[str, tuple[tuple[str, str], ...]] = {
    "sensor_msgs/msg/PointCloud2": (
        ("height", "u32"), ("width", "u32"), ("fields", "fields"), ("is_bigendian", "bool"),
        ("point_step", "u32"), ("row_step", "u32"), ("data", "bytes"), ("is_dense", "bool")),
    "sensor_msgs/msg/CompressedImage": (("format", "string"), ("data", "bytes")),
    "sensor_msgs/msg/Image": (
        ("height", "u32"), ("width", "u32"), ("encoding", "string"), ("is_bigendian", "u8"),
        ("step", "u32"), ("data", "bytes")),
}
NESTED = ("std_msgs/msg/Header", "builtin_interfaces/msg/Time", "sensor_msgs/msg/PointField")


class _Cursor:
    """Reads primitives from ``buf``; ``cdr`` aligns them relative to ``origin``."""

    __slots__ = ("buf", "cdr", "origin", "pos")

    def __init__(self, buf: memoryview, pos: int, cdr: bool) -> None:
        self.buf, self.pos, self.cdr, self.origin = buf, pos, cdr, pos

    def align4(self) -> None:
        if self.cdr:
            self.pos += -(self.pos - self.origin) % 4

    def u32(self) -> int:
        self.align4()
        (v,) = U32.unpack_from(self.buf, self.pos)
        self.pos += 4
        return int(v)

    def u8(self) -> int:
        v = self.buf[self.pos]
        self.pos += 1
        return int(v)

    def string(self) -> str:
        n = self.u32()
        end = self.pos + n
        if end > len(self.buf):
            raise ValueError("string runs past the end of the message")
        raw = bytes(self.buf[self.pos:end - 1 if self.cdr and n else end])
        self.pos = end
        return raw.decode()

    def blob(self) -> np.ndarray:
        n = self.u32()
        if self.pos + n > len(self.buf):
            raise ValueError(f"data of {n} bytes runs past the end of the message")
        out = np.frombuffer(self.buf, dtype=np.uint8, count=n, offset=self.pos)
        self.pos += n
        return out


def _header(c: _Cursor) -> Header:
    seq = None if c.cdr else c.u32()
    c.align4()
    sec, nanosec = I32U32.unpack_from(c.buf, c.pos)
    c.pos += 8
    return Header(stamp=Time(int(sec), int(nanosec)), frame_id=c.string(), seq=seq)


def parse(raw: bytes | memoryview, msgtype: str, *, ros2: bool) -> RawMessage | None:
    """Parse one serialized message of a type in ``LAYOUTS``; ``None`` when its CDR is not
    little-endian (the caller then uses rosbags)."""
    buf = memoryview(raw).cast("B") if isinstance(raw, memoryview) else memoryview(raw)
    if ros2:
        if len(buf) < 4 or buf[1] != 1:  # encapsulation CDR_LE = 00 01
            return None
        c = _Cursor(buf, 4, cdr=True)
    else:
        c = _Cursor(buf, 0, cdr=False)
    try:
        header = _header(c)
        values: dict[str, Any] = {}
        for name, kind in LAYOUTS[msgtype]:
            if kind == "u32":
                values[name] = c.u32()
            elif kind == "u8":
                values[name] = c.u8()
            elif kind == "bool":
                values[name] = bool(c.u8())
            elif kind == "string":
                values[name] = c.string()
            elif kind == "bytes":
                values[name] = c.blob()
            else:  # PointField sequence
                fields = []
                for _ in range(c.u32()):
                    fname = c.string()
                    offset = c.u32()
                    datatype = c.u8()
                    fields.append(PointField(fname, offset, datatype, c.u32()))
                values[name] = fields
    except (struct.error, IndexError) as e:
        raise ValueError(f"{msgtype} message is truncated ({len(buf)} bytes): {e}") from e
    return RawMessage(msgtype, header, values)


_STANDARD: dict[bool, dict[str, Any]] = {}


def _standard_defs(ros2: bool) -> dict[str, Any]:
    if ros2 not in _STANDARD:
        store = get_typestore(Stores.ROS2_HUMBLE if ros2 else Stores.ROS1_NOETIC)
        _STANDARD[ros2] = {t: store.fielddefs[t][1] for t in (*LAYOUTS, *NESTED)
                           if t in store.fielddefs}
    return _STANDARD[ros2]


def parser_for(fielddefs: dict[str, Any], msgtype: str, ros2: bool
               ) -> Callable[[bytes | memoryview], RawMessage | None] | None:
    """A fast parser for ``msgtype`` when the bag defines it (and its nested types) exactly as
    standard ROS does, else ``None``. ``fielddefs`` is the reader's ``typestore.fielddefs``."""
    if msgtype not in LAYOUTS:
        return None
    std = _standard_defs(ros2)
    needed = [msgtype, "std_msgs/msg/Header", "builtin_interfaces/msg/Time"]
    if msgtype.endswith("PointCloud2"):
        needed.append("sensor_msgs/msg/PointField")
    for t in needed:
        if t not in fielddefs or t not in std or fielddefs[t][1] != std[t]:
            return None
    return lambda raw: parse(raw, msgtype, ros2=ros2)
