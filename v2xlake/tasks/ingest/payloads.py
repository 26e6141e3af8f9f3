"""Message payloads read in place: views instead of fresh copies, for rosbags' ROS 2 storages.

Why: rosbags hands every message over as a fresh ``bytes``. For MCAP it reads the chunk, then
copies the record out of the chunk and the payload out of the record; for sqlite3, SQLite
copies the blob from its page cache into one buffer and apsw copies that into ``bytes``. For a
7 MB LiDAR scan that memory traffic, not the decoding, was most of what separated ingest from
its floor on a two-core machine (``tests/bench/bench_ingest.py``).

What stays rosbags': opening the bag, metadata, the MCAP summary and chunk index, the sqlite3
schema, connections and types, the per-file connection mapping, message-level compression,
and the time-ordered merge across chunks, files and bags. Only the ``messages`` method of each
opened storage is replaced, for the duration of one iteration and on that instance only:

- MCAP (``_mcap_messages``): the same chunks in the same order, each chunk's messages sorted
  by log time the same way (stable), each chunk validated by rosbags' own ``decompress`` (size
  and CRC; it also inflates lz4 / zstd chunks); payloads are ``memoryview`` slices of the
  memory-mapped file (or of the inflated chunk). Files without a chunk index keep rosbags'
  scan. The mapped bag must not be truncated while it is read (``landing/`` is immutable).
- sqlite3 (``_sqlite_messages``): rosbags' query, selecting the row id and the blob's length
  instead of the blob, ordered by time then row id (insertion order breaks ties); each blob
  is read with SQLite's incremental blob I/O straight into its own buffer, with SQLite's
  memory-mapped I/O on for the read-only connection.

Payload views are read-only and stay valid while referenced. ROS 1 bags keep rosbags' path.
"""

from __future__ import annotations

import heapq
import mmap
import struct
from collections.abc import Callable, Collection, Iterator
from contextlib import contextmanager
from functools import partial
from typing import Any, cast

import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.interfaces import Connection
from rosbags.rosbag2 import Reader as Reader2
from rosbags.rosbag2.errors import ReaderError
from rosbags.rosbag2.storage_mcap import ChunkInfo, McapReader, decompress
from rosbags.rosbag2.storage_sqlite3 import Sqlite3Reader

Payload = bytes | memoryview
Messages = Iterator[tuple[Connection, int, Payload]]
# MCAP record: opcode u8, length u64; message record body: channel u16, sequence u32,
# log time u64, publish time u64, then the payload (rosbags reads the same fields)
_RECORD = struct.Struct("<BQ")
_MESSAGE = struct.Struct("<hiqq")
_CHUNK_CRC = struct.Struct("<I")
_MESSAGE_OP = 0x05
SQLITE_MMAP_BYTES = 1 << 40  # whole files; SQLite caps it at its compile-time maximum


def messages(reader: AnyReader, connections: Collection[Connection],
             start: int | None = None, stop: int | None = None) -> Messages:
    """``reader.messages(connections, start, stop)``, with payloads read in place (see module
    doc)."""
    with _in_place(_storages(reader)):
        yield from reader.messages(connections=connections, start=start, stop=stop)


def _storages(reader: AnyReader) -> list[Any]:
    """The opened storage files behind ``reader`` (none for ROS 1 bags)."""
    out: list[Any] = []
    for r in reader.readers:
        if isinstance(r, Reader2):
            out.extend(getattr(r.storage, "storages", [r.storage]))
    return out


@contextmanager
def _in_place(storages: list[Any]) -> Iterator[None]:
    patched = []
    for s in storages:
        impl: Callable[..., Messages] | None = (
            _mcap_messages if isinstance(s, McapReader) and s.chunks
            else _sqlite_messages if isinstance(s, Sqlite3Reader) else None)
        if impl is not None:
            setattr(s, "messages", partial(impl, s))  # noqa: B010 (this instance only)
            patched.append(s)
    try:
        yield
    finally:
        for s in patched:
            s.__dict__.pop("messages", None)


# --------------------------------------------------------------------------- sqlite3
def _sqlite_messages(storage: Sqlite3Reader, connections: Collection[Connection],
                     start: int | None = None, stop: int | None = None) -> Messages:
    db = storage.dbconn
    assert db is not None
    db.execute(f"PRAGMA mmap_size={SQLITE_MMAP_BYTES}")
    ids = tuple({c.id for c in connections})
    where = [f"topics.id IN ({','.join('?' for _ in ids)})"]
    args: list[int] = list(ids)
    if start is not None:
        where.append("messages.timestamp >= ?")
        args.append(start)
    if stop is not None:
        where.append("messages.timestamp < ?")
        args.append(stop)
    query = ("SELECT messages.rowid, topics.id, messages.timestamp, length(messages.data) "
             "FROM messages JOIN topics ON messages.topic_id=topics.id "
             f"WHERE {' AND '.join(where)} ORDER BY messages.timestamp, messages.rowid")
    connmap = {c.id: c for c in storage.connections}
    blob = None
    try:
        for rowid, cid, timestamp, size in db.execute(query, args):
            if blob is None:
                blob = db.blob_open("main", "messages", "data", rowid, False)
            else:
                blob.reopen(rowid)
            buf = np.empty(size, np.uint8)
            blob.read_into(buf.data)
            buf.flags.writeable = False
            yield connmap[cid], timestamp, buf.data
    finally:
        if blob is not None:
            blob.close()


# --------------------------------------------------------------------------- MCAP
def _mcap_messages(storage: McapReader, connections: Collection[Connection],
                   start: int | None = None, stop: int | None = None) -> Messages:
    channel_map = {c.id: c for c in connections}
    with storage.path.open("rb") as f:
        mm = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
    mm.madvise(mmap.MADV_SEQUENTIAL)
    view = memoryview(mm)
    sources = [
        _chunk_messages(view, c, channel_map,
                        c.message_start_time if start is None else start,
                        c.message_end_time + 1 if stop is None else stop)
        for c in storage.chunks
        if (start is None or start < c.message_end_time + 1)
        and (stop is None or c.message_start_time < stop)
        and any(c.channel_count.get(cid, 0) for cid in channel_map)
    ]
    for timestamp, offset, conn, data in heapq.merge(*sources):
        if offset:
            assert conn is not None and data is not None
            yield conn, timestamp, data


def _chunk_messages(view: memoryview, chunk: ChunkInfo, channel_map: dict[int, Connection],
                    start: int, stop: int
                    ) -> Iterator[tuple[int, int, Connection | None, memoryview | None]]:
    """One chunk's messages in log-time order; first a marker at the chunk's start time so
    the merge opens a chunk only when its turn comes, as rosbags does."""
    yield chunk.message_start_time, 0, None, None
    at = chunk.chunk_start_offset
    # chunk record: opcode u8, length u64, then start u64, end u64, uncompressed size u64,
    # crc u32, compression string, compressed size u64, records
    (crc,) = _CHUNK_CRC.unpack_from(view, at + 9 + 24)
    begin = at + 9 + 40 + len(chunk.compression)
    raw = view[begin:begin + chunk.compressed_size]
    if len(raw) != chunk.compressed_size:
        raise ReaderError(f"Truncated record at offset {begin}: expected "
                          f"{chunk.compressed_size} bytes, got {len(raw)}.")
    records = memoryview(decompress(cast(bytes, raw), chunk.compression,
                                    chunk.uncompressed_size, crc))
    found: list[tuple[int, int, Connection | None, memoryview | None]] = []
    pos, end = 0, len(records)
    while pos < end:
        if pos + _RECORD.size > end:
            raise ReaderError(f"Truncated record in chunk at offset {at}.")
        op, size = _RECORD.unpack_from(records, pos)
        body = pos + _RECORD.size
        if body + size > end:
            raise ReaderError(f"Truncated record in chunk at offset {at}: expected {size} "
                              f"bytes, got {end - body}.")
        if op == _MESSAGE_OP:
            channel_id, _seq, log_time, _pub = _MESSAGE.unpack_from(records, body)
            if start <= log_time < stop and channel_id in channel_map:
                found.append((log_time, at, channel_map[channel_id],
                              records[body + _MESSAGE.size:body + size]))
        pos = body + size
    found.sort(key=lambda m: m[0])
    yield from found
