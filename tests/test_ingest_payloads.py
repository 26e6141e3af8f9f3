"""Payloads read in place (tasks/ingest/payloads.py) are rosbags' messages, byte for byte and
in rosbags' order, for every ROS 2 storage and compression; damaged chunks fail as in rosbags."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path
from typing import Any

import pytest
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode
from rosbags.rosbag2.storage_mcap import McapReader
from rosbags.typesys import Stores, get_typestore

from tests.fixtures.minibag import MiniClip, write_clip
from tests.fixtures.real import requires_real_data
from v2xlake.tasks.ingest.payloads import messages

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "bags"
STORE = get_typestore(Stores.ROS2_HUMBLE)


def read(bag: Path, in_place: bool, window: tuple[int | None, int | None] = (None, None)
         ) -> list[tuple[str, int, Any]]:
    """Every message (in ``[start, stop)``) as (topic, log time, payload); the reader is closed
    before returning, so in-place payloads must outlive it."""
    start, stop = window
    with AnyReader([bag], default_typestore=STORE) as r:
        it = (messages(r, r.connections, start, stop) if in_place
              else r.messages(connections=r.connections, start=start, stop=stop))
        return [(c.topic, t, raw) for c, t, raw in it]


def assert_same(bag: Path, window: tuple[int | None, int | None] = (None, None)
                ) -> list[tuple[str, int, Any]]:
    ref, mine = read(bag, False, window), read(bag, True, window)
    assert [(t, s) for t, s, _ in mine] == [(t, s) for t, s, _ in ref]
    assert all(bytes(a) == b for (_, _, a), (_, _, b) in zip(mine, ref, strict=True))
    return mine


def rewrite(src: Path, dst: Path, storage: str, mode: CompressionMode | None) -> Path:
    """``src`` copied message by message into a new bag (optionally compressed)."""
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    w = Writer(dst, version=8, storage_plugin=plugin)
    if mode is not None:
        w.set_compression(mode, CompressionFormat.ZSTD)
    with AnyReader([src], default_typestore=STORE) as r, w:
        conns = {c.id: w.add_connection(c.topic, c.msgtype, typestore=r.typestore)
                 for c in r.connections}
        for c, t, raw in r.messages():
            w.write(conns[c.id], t, raw)
    return dst


@pytest.mark.parametrize(("storage", "mode"), [
    ("sqlite3", None), ("mcap", None),
    ("sqlite3", CompressionMode.MESSAGE), ("mcap", CompressionMode.STORAGE),
])
def test_payloads_equal_rosbags(tmp_path: Path, storage: str, mode: CompressionMode | None
                                ) -> None:
    clip = write_clip(tmp_path / "clip", MiniClip(storage=storage, seconds=0.3, points=500))
    bag = clip / "red" if mode is None else rewrite(clip / "red", tmp_path / "z", storage, mode)
    got = assert_same(bag)
    assert {t for t, _, _ in got} >= {"/red/lidar/points", "/red/ins"}
    times = sorted({s for _, s, _ in got})
    part = assert_same(bag, (times[len(times) // 3], times[2 * len(times) // 3]))
    assert 0 < len(part) < len(got)
    if mode is None:  # nothing to inflate: views of the bag itself, not copies
        assert all(isinstance(p, memoryview) and p.readonly for _, _, p in got)


@requires_real_data("bags/ouster_os1_128_3frames_ros2")
def test_payloads_equal_rosbags_on_real_ouster_bag() -> None:
    got = assert_same(REAL / "ouster_os1_128_3frames_ros2")
    assert sum(t == "/ouster/points" for t, _, _ in got) == 3


def _mcap_with_crcs(tmp_path: Path) -> tuple[Path, list[Any]]:
    """A rosbags MCAP bag (rosbags writes CRC 0, i.e. unchecked) with every chunk's CRC filled
    in, as the MCAP C++ writer of ``ros2 bag record`` does."""
    clip = write_clip(tmp_path / "clip", MiniClip(storage="mcap", seconds=0.3, points=500,
                                                  agents=("red",)))
    path = next((clip / "red").glob("*.mcap"))
    r = McapReader(path)
    r.open()
    chunks = list(r.chunks)
    r.close()
    data = bytearray(path.read_bytes())
    for c in chunks:
        begin = c.chunk_start_offset + 9 + 40 + len(c.compression)
        crc = zlib.crc32(data[begin:begin + c.uncompressed_size])
        struct.pack_into("<I", data, c.chunk_start_offset + 9 + 24, crc)
    path.write_bytes(bytes(data))
    return clip / "red", chunks


def test_chunk_crc_checked_like_rosbags(tmp_path: Path) -> None:
    bag, chunks = _mcap_with_crcs(tmp_path)
    assert_same(bag)  # correct CRCs pass
    path = next(bag.glob("*.mcap"))
    data = bytearray(path.read_bytes())
    c = chunks[len(chunks) // 2]
    data[c.chunk_start_offset + 9 + 40 + len(c.compression) + c.uncompressed_size // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    for in_place in (False, True):
        with pytest.raises(Exception, match="checksum mismatch"):
            read(bag, in_place)


def test_record_running_past_its_chunk_is_an_error(tmp_path: Path) -> None:
    clip = write_clip(tmp_path / "clip", MiniClip(storage="mcap", seconds=0.3, points=500,
                                                  agents=("red",)))
    path = next((clip / "red").glob("*.mcap"))
    r = McapReader(path)
    r.open()
    c = r.chunks[0]
    r.close()
    data = bytearray(path.read_bytes())
    first = c.chunk_start_offset + 9 + 40 + len(c.compression)  # first record of the chunk
    struct.pack_into("<Q", data, first + 1, c.uncompressed_size)  # its length: the whole chunk
    path.write_bytes(bytes(data))
    with pytest.raises(Exception, match="Truncated record in chunk"):
        read(clip / "red", True)
