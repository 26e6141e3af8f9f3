"""The lake: one root (a local directory or an ``s3://bucket/prefix`` URI), five zones.

Layout (docs/architecture-catalog.md)::

    <root>/landing/<clip_id>/...                          clip folders as delivered
    <root>/raw|clean/<table>/clip_id=<c>[/agent_id=<a>]/<name>.parquet
    <root>/raw|clean/blobs/<clip_id>/<agent_id>/<sensor>/<frame>.png
    <root>/releases/<name>/...
    <root>/quarantine/<clip_id>/report.json
    <root>/manifests/<clip_id>/<stage>.json
    <root>/catalog.duckdb                                 (local roots only)

Every write is atomic: a local file is written under a hidden temporary name in the same
directory and renamed into place; on S3 a PUT (or a completed multipart upload) is atomic by
itself. Readers and the catalog only ever glob ``*.parquet`` / final names, so a half-written
file is never visible. Partition keys are stripped from the files and restored on read.
"""

from __future__ import annotations

import collections
import contextlib
import contextvars
import copy
import errno
import hashlib
import itertools
import json
import os
import queue
import re
import shutil
import socket
import threading
import time
import uuid
from collections.abc import Iterable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.fs as pafs
import pyarrow.parquet as pq

from v2xlake.schemas.clip import ID_PATTERN
from v2xlake.schemas.tables import table_owner
from v2xlake.storage import checksum

ZONES = ("landing", "raw", "clean", "releases", "quarantine", "manifests")
PARTITION_KEYS = ("clip_id", "agent_id")
BLOBS = "blobs"  # a zone's folder of per-frame files (images), one folder per clip


def s3_filesystem() -> pafs.S3FileSystem:
    """S3 filesystem from the usual AWS_* environment (plus AWS_ENDPOINT_URL for a local server)."""
    endpoint = os.environ.get("AWS_ENDPOINT_URL") or os.environ.get("V2XLAKE_S3_ENDPOINT")
    kwargs: dict[str, Any] = {
        "access_key": os.environ.get("AWS_ACCESS_KEY_ID"),
        "secret_key": os.environ.get("AWS_SECRET_ACCESS_KEY"),
        "region": os.environ.get("AWS_REGION", "us-east-1"),
    }
    if endpoint:
        u = urlparse(endpoint)
        kwargs["endpoint_override"] = u.netloc or u.path
        kwargs["scheme"] = u.scheme or "http"
    return pafs.S3FileSystem(**kwargs)


@dataclass(frozen=True)
class ParquetOptions:
    """Encoding of the lake's tables, chosen by ``tests/bench/bench_parquet.py`` on real Ouster
    points (one row group per frame): BYTE_STREAM_SPLIT on float columns, DELTA_BINARY_PACKED
    on int32/int64 columns (times, frame indices), dictionaries only on strings.

    The default (``ParquetOptions()``, the clean zone and everything downstream) compresses
    with zstd level 1: ~1.2-1.8x faster than pyarrow's defaults (snappy + dictionary
    everywhere) at 8.2 instead of 14.6 bytes per point. The raw zone uses ``RAW_OPTIONS``
    (see ``for_zone``)."""

    compression: str = "zstd"
    compression_level: int | None = 1
    byte_stream_split: bool = True  # float columns (they never get a dictionary)
    delta_ints: bool = True  # int32 / int64 columns: DELTA_BINARY_PACKED
    # with delta_ints: int32 columns too (frame indices; constant within a LiDAR row group,
    # where PLAIN + lz4 is as small and ~3x cheaper to encode)
    delta_int32: bool = True
    dictionary_strings: bool = True  # strings / dictionary columns keep their dictionary
    # min/max of float columns (x, y, z, intensity...): costs ~15-25 % of a LiDAR row group's
    # encoding and prunes nothing (every scan spans the whole sensor range); statistics of
    # every other column (frame_idx, t_ns, ring, strings) are always written
    float_statistics: bool = True
    # min/max of dictionary columns (``sensor``): string comparisons, ~0.5 ms per LiDAR row
    # group; the lake's files are per sensor anyway
    dictionary_statistics: bool = True
    # values the writer encodes per batch (pyarrow default 1024); large LiDAR row groups
    # spend less in per-batch bookkeeping with bigger batches (pages may exceed 1 MiB by
    # up to one batch)
    write_batch_size: int | None = None

    @staticmethod
    def for_zone(zone: str) -> ParquetOptions:
        """The encoding a zone's tables get when the writer does not pass one."""
        return ZONE_OPTIONS.get(zone, ParquetOptions())

    def writer_kwargs(self, schema: pa.Schema) -> dict[str, Any]:
        dict_cols = [
            f.name for f in schema
            if pa.types.is_string(f.type) or pa.types.is_dictionary(f.type)
        ] if self.dictionary_strings else []
        enc: dict[str, str] = {}
        for f in schema:
            if self.byte_stream_split and pa.types.is_floating(f.type):
                enc[f.name] = "BYTE_STREAM_SPLIT"
            elif self.delta_ints and (pa.types.is_int64(f.type) or (
                    self.delta_int32 and pa.types.is_int32(f.type))):
                enc[f.name] = "DELTA_BINARY_PACKED"
        stats: bool | list[str] = True
        if not (self.float_statistics and self.dictionary_statistics):
            stats = [f.name for f in schema
                     if not (pa.types.is_floating(f.type) and not self.float_statistics)
                     and not (pa.types.is_dictionary(f.type) and not self.dictionary_statistics)]
        kw: dict[str, Any] = dict(
            compression=self.compression, compression_level=self.compression_level,
            use_dictionary=dict_cols or False, column_encoding=enc or None,
            write_statistics=stats)
        if self.write_batch_size is not None:
            kw["write_batch_size"] = self.write_batch_size
        return kw


# The raw zone is written once by ingest, at bag-reading speed, and read a few times by
# anonymize (which writes the clean zone with the default zstd); the delivered bags stay in
# landing/ as the archive. So raw trades size for encoding speed: lz4 over PLAIN columns (no
# byte-stream-split, no delta), no float or dictionary statistics, big write batches.
# Measured (tests/bench/bench_parquet.py, 2-core VM, real Ouster OS1-128 scans): 970 MB/s
# write and 4.0 GB/s read at 11.3 B/point, against 450 MB/s, 1.7 GB/s and 8.2 B/point for the
# clean zone's zstd-1 + BSS; lz4 + BSS + delta time (the previous raw choice) cost ingest ~2
# ms more per 230k-point frame to save ~1 MB, which the file write then saves only ~0.5 ms of.
RAW_OPTIONS = ParquetOptions(compression="lz4", compression_level=None, byte_stream_split=False,
                             delta_ints=False, float_statistics=False,
                             dictionary_statistics=False, write_batch_size=65_536)
ZONE_OPTIONS: dict[str, ParquetOptions] = {"raw": RAW_OPTIONS}


# ---------------------------------------------------------------- write errors (#16)
class LakeWriteError(OSError):
    """A write the lake cannot take (disk full, quota, size limit, read-only, permission),
    with the lake, the file and the reason in one line. What was being written is removed
    (temporary names, staging), so nothing half-written stays behind."""

    def __str__(self) -> str:
        return str(self.strerror)


WRITE_ERRNOS = {
    errno.ENOSPC: "no space left on the device (free some space, then re-run: what was "
                  "being written has been removed)",
    errno.EDQUOT: "disk quota exceeded (what was being written has been removed)",
    errno.EFBIG: "file too large for the file system or the process's file size limit",
    errno.EROFS: "the lake is on a read-only file system (query it; to process or release, "
                 "use a writable copy)",
    errno.EACCES: "permission denied (the lake or this folder is not writable for this user)",
    errno.EPERM: "operation not permitted (the lake or this folder is not writable)",
}


# ---------------------------------------------------------------- run ownership (#16)
# Every name a run leaves in the lake while it works (staging folders, temporary files,
# release builds) carries its owner, ``p<pid>.<host>``, so that the next run can tell a
# dead run's leftovers (swept) from a live run's work (kept) without locks or heartbeats.
HOST_TAG = hashlib.blake2s(socket.gethostname().encode(), digest_size=3).hexdigest()
OWNER = re.compile(r"-p(\d+)\.([0-9a-f]{6})-")
JOURNAL = "PUBLISH.json"


def run_tag() -> str:
    """This process's owner tag (read at call time: a forked worker gets its own pid)."""
    return f"p{os.getpid()}.{HOST_TAG}"


def owner_state(name: str) -> str:
    """"live", "dead", "foreign" (another host: cannot tell) or "unowned" (no tag)."""
    m = OWNER.search(name)
    if m is None:
        return "unowned"
    pid, host = int(m.group(1)), m.group(2)
    if host != HOST_TAG:
        return "foreign"
    if pid == os.getpid():
        return "live"
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return "dead"
    except PermissionError:  # another user's live process
        return "live"
    return "live"


@dataclass
class Sweep:
    """What ``Lake.sweep`` did: run folders removed (after rolling forward those whose
    publish had begun), temporary files removed, live or foreign runs kept."""

    runs: list[str] = field(default_factory=list)
    rolled_forward: list[str] = field(default_factory=list)
    files: list[str] = field(default_factory=list)
    kept: list[str] = field(default_factory=list)

    def __bool__(self) -> bool:
        return bool(self.runs or self.files)


class _ChecksumSink:
    """A write-only file object that forwards to ``stream`` and checksums the bytes as they
    pass (``v2xlake.storage.checksum``), so a written file's checksum costs no second read.

    ``threaded=True`` (background writers): hashing *and* writing run on an I/O thread, fed
    the chunks pyarrow hands to ``write`` (immutable bytes, so holding them is safe); both
    release the GIL, so the Parquet encoder never waits for the file system or an S3 upload
    and, on a two-core machine, the caller's decoding, the encoder and the I/O share both
    cores. At most ``IO_QUEUE`` chunks wait; an I/O error is raised by the next ``write`` or
    by ``close``."""

    def __init__(self, stream: Any, threaded: bool = False) -> None:
        self._stream, self._hash, self._pos, self.closed = stream, checksum.hasher(), 0, False
        self._queue: queue.Queue[Any] | None = None
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None
        if threaded:
            self._queue = queue.Queue(IO_QUEUE)
            self._thread = threading.Thread(target=self._io_loop, name="lake-io", daemon=True)
            self._thread.start()

    def _io_loop(self) -> None:
        assert self._queue is not None
        while True:
            chunk = self._queue.get()
            try:
                if chunk is None:
                    return
                if self._error is None:
                    self._hash.update(chunk)
                    self._stream.write(chunk)
            except BaseException as e:  # kept for the writer's thread to raise
                self._error = e
            finally:
                self._queue.task_done()

    def _raise(self) -> None:
        if self._error is not None:
            raise self._error

    def write(self, data: Any) -> int:
        self._raise()
        if self._queue is not None:
            self._queue.put(data)
        else:
            self._hash.update(data)
            self._stream.write(data)
        n = memoryview(data).nbytes
        self._pos += n
        return n

    def tell(self) -> int:
        return self._pos

    def flush(self) -> None:
        if self._queue is not None and self._thread is not None:
            self._queue.join()  # every queued chunk handed to the stream
        self._raise()
        self._stream.flush()

    def writable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return False

    def readable(self) -> bool:
        return False

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            try:
                self._stop()
            finally:
                self._stream.close()

    def _stop(self) -> None:
        """Drain the I/O thread (every queued chunk written) and raise its error, if any."""
        if self._thread is not None and self._queue is not None:
            self._queue.put(None)
            self._thread.join()
            self._thread = None
        self._raise()

    def hexdigest(self) -> str:
        self._stop()
        return checksum.digest(self._hash)


MAX_PENDING = 2  # row groups a background TableWriter may have queued
IO_QUEUE = 8  # output chunks (SINK_BUFFER each) waiting for a background writer's I/O thread
SINK_BUFFER = 4 << 20  # bytes buffered before a TableWriter's output reaches Python


class TableWriter:
    """One Parquet file being written: ``write(table)`` appends exactly one row group.

    Local lakes write to a hidden temporary name in the target directory and ``os.replace``
    it on a clean exit; S3 lakes stream a multipart upload that only becomes an object when
    completed (an aborted upload leaves nothing). On an exception the partial file is
    removed, so no reader ever sees it. The bytes are checksummed as they are written:
    after a clean exit ``checksum`` holds the file's checksum and the lake's ``written`` map
    records ``(rows, checksum)`` under the final path.
    """

    def __init__(self, lake: Lake, final: str, schema: pa.Schema, options: ParquetOptions,
                 background: bool = False) -> None:
        self.lake, self.path, self.schema, self.options = lake, final, schema, options
        self.rows = 0
        self.row_groups = 0
        self._target = lake._tmp(final) if lake.is_local else final
        self._writer: pq.ParquetWriter | None = None
        # background=True: encoding/compression of row group i (pyarrow releases the GIL)
        # overlaps with the caller producing row groups i+1 and i+2; at most two are queued
        # (slack for uneven frames; each holds one frame's columns in memory).
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="parquet") if background else None
        self._pending: collections.deque[Future[None]] = collections.deque()
        self._background = background
        self._sink: _ChecksumSink | None = None
        self.checksum: str | None = None

    def __enter__(self) -> TableWriter:
        with self.lake.writing(self.path):
            self.lake._mkdir(self.path.rpartition("/")[0])
            stream = self.lake.fs.open_output_stream(self._target)
        self._sink = _ChecksumSink(stream, threaded=self._background)
        # pyarrow writes a Parquet file in ~10 KiB pieces; buffer them into big chunks before
        # they reach Python (one call per SINK_BUFFER bytes instead of ~200 per LiDAR frame)
        self._out = pa.BufferedOutputStream(pa.PythonFile(self._sink, mode="w"), SINK_BUFFER)
        try:
            self._writer = pq.ParquetWriter(self._out, self.schema,
                                            **self.options.writer_kwargs(self.schema))
        except BaseException:
            self._out.close()
            with contextlib.suppress(Exception):
                self.lake.fs.delete_file(self._target)
            raise
        return self

    def write(self, data: pa.Table) -> None:
        assert self._writer is not None, "use TableWriter in a with block"
        drop = [c for c in data.column_names if c not in self.schema.names]
        if drop:
            data = data.drop_columns(drop)
        data = data.select(self.schema.names)
        if data.schema != self.schema:
            data = data.cast(self.schema)
        self.rows += data.num_rows
        self.row_groups += 1
        if self._pool is None:
            self._writer.write_table(data, row_group_size=max(data.num_rows, 1))
            return
        self._wait(MAX_PENDING - 1)
        self._pending.append(self._pool.submit(self._writer.write_table, data,
                                               row_group_size=max(data.num_rows, 1)))

    def _wait(self, keep: int = 0) -> None:
        """Wait until at most ``keep`` row groups are queued (raises a background error)."""
        while len(self._pending) > keep:
            self._pending.popleft().result()

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        assert self._writer is not None
        failed = exc_type is not None
        error: BaseException | None = None
        try:
            self._wait()
        except Exception as e:  # a background row group failed
            failed, error = True, e
            for f in self._pending:
                f.cancel()
            self._pending.clear()
        if self._pool is not None:
            self._pool.shutdown(wait=True)
        try:
            if not failed and self.row_groups == 0:
                self._writer.write_table(self.schema.empty_table())
            self._writer.close()
        except Exception as e:
            failed, error = True, error or e
        assert self._sink is not None
        try:
            self._out.close()  # flushes the buffer, closes the sink and its stream
        except Exception as e:
            failed, error = True, error or e
        finally:
            with contextlib.suppress(Exception):
                self._sink.close()  # idempotent; stops the hashing thread in every case
        if failed:
            with contextlib.suppress(Exception):
                self.lake.fs.delete_file(self._target)
            cause = error if error is not None else exc
            if isinstance(cause, OSError) and not isinstance(cause, LakeWriteError):
                clear = self.lake.write_error(self.path, cause)
                if clear is not None:  # disk full, read-only...: say so, name the file
                    raise clear from cause
            if error is not None and exc_type is None:
                raise error
            return
        with self.lake.writing(self.path):
            self.lake._commit(self._target, self.path)
        self.checksum = self._sink.hexdigest()
        self.lake.written[self.path] = (self.rows, self.checksum)


def _partition_columns(names: Sequence[str], clip_id: str,
                       agent_id: str | None) -> dict[str, str | None]:
    """Columns that the path carries instead of the file, with their partition values.

    ``clip_id`` always; ``agent_id`` only when the table is partitioned by agent (a clip-level
    table such as ``qa_checks`` keeps its nullable ``agent_id`` column in the file).
    """
    return {k: v for k, v in (("clip_id", clip_id), ("agent_id", agent_id))
            if k in names and (v is not None or k == "clip_id")}


#: :meth:`Lake.reading_once`'s memo: (lake, zone, tables, {(table, clip, agent, columns):
#: table}) of the calling thread's context, None outside the block
_READ_ONCE: contextvars.ContextVar[
    tuple[Lake, str, frozenset[str], dict[tuple[Any, ...], pa.Table]] | None] = \
    contextvars.ContextVar("lake_read_once", default=None)


class Lake:
    def __init__(self, uri: str | os.PathLike[str], *, create: bool = True) -> None:
        s = str(uri)
        if s.startswith("s3://"):
            u = urlparse(s)
            self.fs: pafs.FileSystem = s3_filesystem()
            self.base = f"{u.netloc}{u.path}".rstrip("/")
            self.is_local = False
        else:
            self.fs = pafs.LocalFileSystem()
            self.base = str(Path(s).expanduser().resolve())
            self.is_local = True
            if create:
                try:
                    Path(self.base).mkdir(parents=True, exist_ok=True)
                except OSError as e:
                    reason = WRITE_ERRNOS.get(e.errno or 0)
                    if reason is None:
                        raise
                    raise LakeWriteError(e.errno or 0, f"cannot create the lake {self.base}: "
                                                       f"{reason}") from e
        self.uri = s if not self.is_local else self.base
        # final path -> (rows, checksum) of every Parquet file this instance wrote (TableWriter)
        self.written: dict[str, tuple[int, str]] = {}
        # the stage this handle writes for and its tables (None: unrestricted, e.g. tests and
        # tools); see ``for_stage``
        self.writer: str | None = None
        self.owns: frozenset[tuple[str, str]] = frozenset()
        # the tables this handle may read besides ``owns`` (None: any); see ``for_stage``
        self.reads: frozenset[tuple[str, str]] | None = None
        self._stage_root: str | None = None  # staged stage output (for_stage atomic_clip)
        self._replaced: set[tuple[str, str, str]] = set()

    def for_stage(self, stage: str, owns: Iterable[tuple[str, str]], *,
                  atomic_clip: str | None = None, stage_root: str | None = None,
                  reads: Iterable[tuple[str, str]] | None = None) -> Lake:
        """A handle on the same lake that writes only the ``(zone, table)`` pairs ``owns``;
        with ``atomic_clip``, also the one publish protocol of every stage (below).

        With ``reads`` (the stage's ``Stage.reads``) it also reads only those tables and its
        own: a table read but not declared would be left out of the stage's manifest key,
        so a change to it would not re-run the stage; refused at once instead
        (``check_read``). ``None`` reads anything (tools, tests).

        The single-writer rule (each table has one owning stage, ``schemas.tables``) is
        enforced here, where every Parquet write goes through, so a stage that writes
        another stage's table fails at once instead of silently dropping that stage's
        columns on a re-run.

        Publishing (``atomic_clip``): the handle is the stage's output for that clip. Reads
        go to the lake; Parquet writes and blobs (``write_blob``) go to a private run folder
        (``_staging/<clip>/<stage>-p<pid>.<host>-<uuid>``: the owner lets a sweep tell a
        live run's folder from a dead one's); deleting a partition (``delete_partition``),
        the clip's blobs (``delete_blobs``) or the clip's whole zone (``replace_clip``)
        only marks it for replacement. ``publish_stage()`` then swaps each written or
        marked partition into place in one journaled commit, so a run killed half-way never
        shows half a stage's output; ``discard_stage()`` drops it (a failed run). The flow
        stages every stage whose ``Stage.atomic`` is set; ingest and anonymize, which
        replace a clip's whole zone, stage themselves the same way. ``stage_root`` names an
        existing run folder instead: the handle of a chunk of a stage's work that a cluster
        worker does, writing into the same output as the flow's handle.
        """
        other = copy.copy(self)
        other.written = {}
        other.writer = stage
        other.owns = frozenset(owns)
        other.reads = None if reads is None else frozenset(reads)
        other._replaced = set()
        other._stage_root = None
        if stage_root is not None:
            other._stage_root = stage_root
        elif atomic_clip is not None:
            self.sweep(atomic_clip)  # a killed earlier run of this clip: finish or drop it
            other._stage_root = self._run_dir(atomic_clip, stage)
            other._make_run_dir()
        return other

    @property
    def stage_root(self) -> str | None:
        return self._stage_root

    def _make_run_dir(self) -> None:
        """Create the run folder now (locally), so that a sweep of another run can tell it
        is taken. Another process tidies an empty ``_staging`` (or clip folder) away with
        rmdir: that can land between two levels of makedirs, so try again."""
        if not self.is_local or self._stage_root is None:
            return
        for attempt in range(5):
            try:
                os.makedirs(self._stage_root, exist_ok=True)
                return
            except FileNotFoundError:
                if attempt == 4:
                    raise

    def _write_dir(self, zone: str, table: str, clip_id: str, agent_id: str | None) -> str:
        if self._stage_root is None:
            return self.table_dir(zone, table, clip_id, agent_id)
        self._replaced.add((zone, table, clip_id))
        parts = [self._stage_root, zone, table, f"clip_id={clip_id}"]
        if agent_id is not None:
            parts.append(f"agent_id={agent_id}")
        return "/".join(parts)

    def _staged_dir(self, zone: str, table: str, clip_id: str) -> str:
        """Where a clip's partition (``table``) or its blobs (``"blobs"``) are staged."""
        assert self._stage_root is not None
        part = clip_id if table == BLOBS else f"clip_id={clip_id}"
        return "/".join([self._stage_root, zone, table, part])

    def _final_dir(self, zone: str, table: str, clip_id: str) -> str:
        return self.path(zone, BLOBS, clip_id) if table == BLOBS \
            else self.table_dir(zone, table, clip_id)

    def publish_stage(self) -> dict[str, str]:
        """Move a staged stage's partitions and blobs into place (see ``for_stage``); returns
        {staged path prefix: final path prefix} for the caller to rewrite recorded paths.

        The swap is journaled (``_commit_moves``): a run killed half-way through it is
        rolled forward by the next sweep, so the stage's tables are never left half old,
        half new."""
        if self._stage_root is None:
            return {}
        for f in self.list_files(self._stage_root, ".parquet"):  # chunks' writes, too
            zone, table, part = f[len(self._stage_root) + 1:].split("/")[:3]
            if table != BLOBS:
                self._replaced.add((zone, table, part.removeprefix("clip_id=")))
        for z in self._children(self._stage_root):  # chunks' blobs, too
            for clip in self._children(f"{z.path}/{BLOBS}"):
                self._replaced.add((z.base_name, BLOBS, clip.base_name))
        moves: list[tuple[str, str]] = []
        deletes: list[str] = []
        for zone, table, clip_id in sorted(self._replaced):
            src = self._staged_dir(zone, table, clip_id)
            dst = self._final_dir(zone, table, clip_id)
            if self.exists(src):
                moves.append((src, dst))
            else:
                deletes.append(dst)
        self._commit_moves(self._stage_root, moves, deletes)
        self.discard_stage()
        return dict(moves)

    def discard_stage(self) -> None:
        """Drop a staged stage's unpublished output (a failed run)."""
        if self._stage_root is not None:
            self.delete_dir(self._stage_root)
            self._replaced = set()
            if self.is_local:
                with contextlib.suppress(OSError):  # the clip's and the shared folder
                    os.rmdir(os.path.dirname(self._stage_root))
                    os.rmdir(os.path.dirname(os.path.dirname(self._stage_root)))

    def replace_clip(self, zone: str, clip_id: str) -> None:
        """Mark the clip's whole ``zone`` for replacement by this staged run: at
        ``publish_stage`` every partition of the clip in ``zone`` that the run did not
        write, any table's, and the clip's blobs there are removed in the same commit. For
        a stage that rebuilds a clip's zone from its inputs (ingest: raw from the bags),
        after which what another stage derived from the old zone (QA's raw checks of the
        old bags) is stale, as after ``delete_clip``."""
        if self._stage_root is None:
            raise RuntimeError("replace_clip needs a staged handle (for_stage(atomic_clip=))")
        for table in self.tables(zone):
            self._replaced.add((zone, table, clip_id))
        self._replaced.add((zone, BLOBS, clip_id))

    def _check_owner(self, zone: str, table: str) -> None:
        if self.writer is None or (zone, table) in self.owns:
            return
        owner = table_owner(zone, table)
        raise PermissionError(
            f"stage {self.writer!r} may not write {zone}.{table}: "
            + (f"it belongs to stage {owner!r}" if owner else "no stage declares it"))

    def check_read(self, zone: str, table: str) -> None:
        """Refuse reading a table the stage this handle serves did not declare (``reads``
        of ``for_stage``); every table read of the storage layer comes through here."""
        if self.reads is None or (zone, table) in self.reads or (zone, table) in self.owns:
            return
        raise PermissionError(
            f"stage {self.writer!r} reads {zone}.{table} but does not declare it in its "
            "Stage.reads (its manifest would not notice a change to it)")

    def clip_lock(self, clip_id: str, wait_s: float | None = None
                  ) -> contextlib.AbstractContextManager[None]:
        """This clip's write lock (``clip_lock``): one run at a time per clip."""
        return clip_lock(self, clip_id, wait_s)

    def looks_like_lake(self) -> bool:
        """True when the root holds at least one zone a pipeline writes (a mistyped path, or
        an empty folder, is not a lake: reading it must be an error, not empty answers)."""
        return any(self.exists(self.path(z)) for z in ("landing", "raw", "clean", "manifests",
                                                       "quarantine", "releases"))

    # ---------------------------------------------------------------- paths
    def path(self, *parts: str) -> str:
        return "/".join([self.base, *[p.strip("/") for p in parts if p]])

    def table_dir(self, zone: str, table: str, clip_id: str | None = None,
                  agent_id: str | None = None) -> str:
        parts = [zone, table]
        if clip_id is not None:
            parts.append(f"clip_id={clip_id}")
            if agent_id is not None:
                parts.append(f"agent_id={agent_id}")
        return self.path(*parts)

    def table_glob(self, zone: str, table: str) -> str:
        """A glob for DuckDB: every parquet file of one table, any partition depth."""
        root = self.table_dir(zone, table)
        prefix = root if self.is_local else f"s3://{root}"
        return f"{prefix}/**/*.parquet"

    @property
    def catalog_path(self) -> str:
        return self.path("catalog.duckdb")

    # ---------------------------------------------------------------- atomic primitives
    def _mkdir(self, path: str) -> None:
        if self.is_local:
            Path(path).mkdir(parents=True, exist_ok=True)

    def _tmp(self, final: str) -> str:
        head, _, name = final.rpartition("/")
        return f"{head}/.{name}.tmp-{run_tag()}-{uuid.uuid4().hex}"

    def _commit(self, tmp: str, final: str) -> None:
        if self.is_local:
            os.replace(tmp, final)

    def write_bytes(self, path: str, data: bytes) -> None:
        head = path.rpartition("/")[0]
        target = self._tmp(path) if self.is_local else path
        with self.writing(path):
            self._mkdir(head)
            try:
                with self.fs.open_output_stream(target) as f:
                    f.write(data)
                self._commit(target, path)
            except BaseException:
                if self.is_local:  # a disk-full write leaves no temporary file behind
                    with contextlib.suppress(OSError):
                        os.remove(target)
                raise

    # ---------------------------------------------------------------- write errors
    def write_error(self, path: str, error: OSError) -> LakeWriteError | None:
        """The clear form of an OS error that no retry of this write can fix (disk full,
        quota, file size limit, read-only file system, permission), or None."""
        reason = WRITE_ERRNOS.get(error.errno or 0)
        if reason is None:
            return None
        root = self.base.split("/_staging/")[0]  # a staging lake names its lake
        rel = path[len(root) + 1:] if path.startswith(root + "/") else path
        if rel.startswith("_staging/"):
            rel = "/".join(rel.split("/")[3:]) + " (staged)"
        where = root if self.is_local else f"s3://{root}"
        return LakeWriteError(error.errno or 0,
                              f"cannot write {rel} in the lake {where}: {reason}")

    @contextlib.contextmanager
    def writing(self, path: str) -> Iterator[None]:
        """Turn an OS error of a write to ``path`` into a ``LakeWriteError`` naming the lake,
        the file and the reason (``write_error``); other errors pass unchanged."""
        try:
            yield
        except LakeWriteError:
            raise
        except OSError as e:
            clear = self.write_error(path, e)
            if clear is None:
                raise
            raise clear from e

    def read_bytes(self, path: str) -> bytes:
        with self.fs.open_input_stream(path) as f:
            return bytes(f.read())

    def exists(self, path: str) -> bool:
        return bool(self.fs.get_file_info(path).type != pafs.FileType.NotFound)

    def count_rows(self, path: str) -> int:
        """Rows of one Parquet file, from its footer."""
        with self.fs.open_input_file(path) as f:
            return int(pq.ParquetFile(f).metadata.num_rows)

    def delete_dir(self, path: str) -> None:
        if self.exists(path):
            with self.writing(path):
                self.fs.delete_dir(path)

    def list_files(self, path: str, suffix: str = "", *, hidden: bool = False) -> list[str]:
        """Files under ``path`` (recursive), sorted. Hidden names (temporary files in
        flight) are left out unless ``hidden``: a release check must see every file."""
        sel = pafs.FileSelector(path, recursive=True, allow_not_found=True)
        out = [
            i.path for i in self.fs.get_file_info(sel)
            if i.type == pafs.FileType.File and i.path.endswith(suffix)
            and (hidden or not any(part.startswith(".")
                                   for part in i.path[len(path):].split("/")))
        ]
        return sorted(out)

    # ---------------------------------------------------------------- json / blobs
    def write_json(self, path: str, obj: Any) -> None:
        self.write_bytes(path, json.dumps(obj, indent=2, sort_keys=True, default=str).encode())

    def read_json(self, path: str) -> Any:
        return json.loads(self.read_bytes(path))

    def blob_key(self, clip_id: str, agent_id: str, sensor: str, frame_idx: int,
                 ext: str = "png") -> str:
        return f"{clip_id}/{agent_id}/{sensor}/{frame_idx:06d}.{ext}"

    def write_blob(self, zone: str, key: str, data: bytes) -> str:
        """Write one blob (``key`` starts with its clip id, ``blob_key``); on a staged
        handle into the run folder, published with the run's tables (``for_stage``)."""
        if self._stage_root is None:
            self.write_bytes(self.path(zone, BLOBS, key), data)
            return key
        clip_id = key.split("/", 1)[0]
        self._replaced.add((zone, BLOBS, clip_id))
        self.write_bytes(f"{self._stage_root}/{zone}/{BLOBS}/{key}", data)
        return key

    def delete_blobs(self, zone: str, clip_id: str) -> None:
        """Remove the clip's blobs in ``zone``; on a staged handle only marked, and replaced
        at ``publish_stage`` by what the run wrote (nothing: removed)."""
        if self._stage_root is not None:
            self._replaced.add((zone, BLOBS, clip_id))
            return
        self.delete_dir(self.path(zone, BLOBS, clip_id))

    def read_blob(self, zone: str, key: str) -> bytes:
        return self.read_bytes(self.path(zone, "blobs", key))

    def blob_path(self, zone: str, key: str) -> str:
        return self.path(zone, "blobs", key)

    # ---------------------------------------------------------------- parquet tables
    def write_table(
        self,
        zone: str,
        table: str,
        data: pa.Table,
        *,
        clip_id: str,
        agent_id: str | None = None,
        name: str = "part",
        row_group_by: str | None = None,
        options: ParquetOptions | None = None,
    ) -> tuple[str, int]:
        """Write one partition file atomically; returns (path, rows). ``options`` defaults to
        the zone's encoding (``ParquetOptions.for_zone``: lz4 in raw, zstd elsewhere).

        ``row_group_by`` names a sorted column whose runs become row groups (LiDAR points: one
        row group per frame, so a reader fetching one frame touches one row group).
        """
        keys = _partition_columns(data.column_names, clip_id, agent_id)
        for key, val in keys.items():
            col = data.column(key)
            if val is not None and len(col) and not pc.all(pc.equal(col, val)).as_py():
                raise ValueError(f"{table}: column {key} disagrees with partition {val!r}")
        data = data.drop_columns(list(keys))
        with self.open_writer(zone, table, data.schema, clip_id=clip_id, agent_id=agent_id,
                              name=name, options=options) as w:
            if row_group_by and data.num_rows:
                keys = data.column(row_group_by).to_numpy()
                cuts = np.flatnonzero(np.diff(keys)) + 1
                bounds = [0, *cuts.tolist(), data.num_rows]
                for a, b in itertools.pairwise(bounds):
                    w.write(data.slice(a, b - a))
            else:
                w.write(data)
        return w.path, data.num_rows

    def open_writer(
        self,
        zone: str,
        table: str,
        schema: pa.Schema,
        *,
        clip_id: str,
        agent_id: str | None = None,
        name: str = "part",
        options: ParquetOptions | None = None,
        background: bool = False,
    ) -> TableWriter:
        """A streaming, atomic Parquet writer: each ``write(t)`` becomes exactly one row group
        (LiDAR: one per frame, written as frames are decoded, so a clip never has to fit in
        memory); the file appears under its final name only when the ``with`` block exits
        without an exception, otherwise the temporary file is removed. ``options`` defaults
        to the zone's encoding (``ParquetOptions.for_zone``)."""
        self._check_owner(zone, table)
        for key in _partition_columns(schema.names, clip_id, agent_id):
            schema = schema.remove(schema.get_field_index(key))
        final = f"{self._write_dir(zone, table, clip_id, agent_id)}/{name}.parquet"
        return TableWriter(self, final, schema, options or ParquetOptions.for_zone(zone),
                           background=background)

    @contextlib.contextmanager
    def reading_once(self, zone: str, tables: Iterable[str]) -> Iterator[None]:
        """Within the block, in the calling thread only, ``read_table`` of one of ``tables``
        of ``zone`` with the same keys and columns (no ``filters``) returns the table it read
        the first time. For a stage whose helpers each read the clip's small tables again
        (the register stage: ``agents`` 8 times, ``calibrated_sensors`` 6, ``ego_poses`` 9
        per 3-agent clip), on tables it does not write: the block does not see a change made
        to them meanwhile."""
        if isinstance(tables, str):  # a set of its characters would cache nothing
            raise TypeError("reading_once takes an iterable of table names, not one name")
        token = _READ_ONCE.set((self, zone, frozenset(tables), {}))
        try:
            yield
        finally:
            _READ_ONCE.reset(token)

    def read_table(
        self,
        zone: str,
        table: str,
        *,
        clip_id: str | None = None,
        agent_id: str | None = None,
        columns: Sequence[str] | None = None,
        filters: Any = None,
    ) -> pa.Table:
        """Read every partition file under the given keys, restoring the partition columns
        (the table read first, inside :meth:`reading_once` for it)."""
        once = _READ_ONCE.get()
        if once is None or once[0] is not self or once[1] != zone or table not in once[2] \
                or filters is not None:
            return self._read_table(zone, table, clip_id, agent_id, columns, filters)
        key = (table, clip_id, agent_id, None if columns is None else tuple(columns))
        hit = once[3].get(key)
        if hit is None:
            hit = once[3][key] = self._read_table(zone, table, clip_id, agent_id, columns, None)
        return hit

    def _read_table(self, zone: str, table: str, clip_id: str | None, agent_id: str | None,
                    columns: Sequence[str] | None, filters: Any) -> pa.Table:
        self.check_read(zone, table)
        root = self.table_dir(zone, table, clip_id, agent_id)
        files = self.list_files(root, ".parquet")
        parts = []
        for path in files:
            cols = [c for c in columns if c not in PARTITION_KEYS] if columns else None
            t = pq.read_table(path, filesystem=self.fs, columns=cols, filters=filters)
            keys = dict(
                seg.split("=", 1) for seg in path[len(self.table_dir(zone, table)):].split("/")
                if "=" in seg
            )
            for k in reversed(PARTITION_KEYS):
                if k in keys and (columns is None or k in columns):
                    t = t.add_column(0, k, pa.array([keys[k]] * t.num_rows, pa.string()))
            parts.append(t)
        if not parts:
            return pa.table({})
        return pa.concat_tables(parts, promote_options="default")

    def delete_partition(self, zone: str, table: str, clip_id: str) -> None:
        self._check_owner(zone, table)
        if self._stage_root is not None:  # replaced at publish_stage, never half-way
            self._replaced.add((zone, table, clip_id))
            return
        self.delete_dir(self.table_dir(zone, table, clip_id))

    # ---------------------------------------------------------------- clip-level operations
    def tables(self, zone: str) -> list[str]:
        """Table names that have a folder in ``zone`` (blobs excluded)."""
        root = self.path(zone)
        if not self.exists(root):
            return []
        infos = self.fs.get_file_info(pafs.FileSelector(root, recursive=False))
        return sorted(
            i.base_name for i in infos
            if i.type == pafs.FileType.Directory and i.base_name != "blobs"
            and not i.base_name.startswith((".", "_"))
        )

    def delete_clip(self, zone: str, clip_id: str) -> None:
        """Remove every partition and blob of one clip from one zone."""
        for table in self.tables(zone):  # clip-level: every owner's partition goes
            self.delete_dir(self.table_dir(zone, table, clip_id))
        self.delete_dir(self.path(zone, "blobs", clip_id))

    # ---------------------------------------------------------------- staging and sweeping
    def _run_dir(self, clip_id: str, who: str) -> str:
        """``_staging/<clip>/<who>-p<pid>.<host>-<uuid>``: one run's private output."""
        return self.path("_staging", clip_id, f"{who}-{run_tag()}-{uuid.uuid4().hex[:12]}")

    def discard_staging(self, clip_id: str) -> int:
        """Finish or drop what killed runs of ``clip_id`` left in ``_staging`` (``sweep``);
        returns how many run folders that was. A live run's folder is kept."""
        return len(self.sweep(clip_id).runs)

    def _commit_moves(self, run_dir: str, moves: Sequence[tuple[str, str]],
                      deletes: Sequence[str]) -> None:
        """Swap staged folders into place as one commit: the journal ``PUBLISH.json`` (moves
        and deletions, lake-relative) is written first, atomically, then the old folders
        are moved aside into the run folder and the new ones renamed in. A run killed after
        the journal is rolled forward by ``sweep`` (``_roll_forward``: what is still staged
        is moved in, the deletions repeated), so a clip never keeps half a stage's output."""
        rel = len(self.base) + 1
        self.write_json(f"{run_dir}/{JOURNAL}", {
            "moves": [[a[rel:], b[rel:]] for a, b in moves], "deletes": [d[rel:] for d in deletes]})
        with self.writing(moves[0][1] if moves else run_dir):
            self._roll_forward(run_dir)

    def _roll_forward(self, run_dir: str) -> None:
        """Carry out a run folder's journal (idempotent: a move whose source is gone is done)."""
        journal = self.read_json(f"{run_dir}/{JOURNAL}")
        trash = f"{run_dir}/_replaced"
        for i, dst in enumerate(journal["deletes"]):
            self._aside(self.path(dst), f"{trash}/d{i}")
        for i, (src, dst) in enumerate(journal["moves"]):
            if self.exists(self.path(src)):
                self._aside(self.path(dst), f"{trash}/m{i}")
                self._move_tree(self, self.path(src), self.path(dst))

    def _move_tree(self, staging: Lake, src: str, dst: str) -> None:
        if self.is_local and staging.is_local:
            self._mkdir(dst.rpartition("/")[0])
            os.replace(src, dst)
            return
        for f in staging.list_files(src):
            self.write_bytes(dst + f[len(src):], staging.read_bytes(f))
        staging.delete_dir(src)

    def _aside(self, path: str, trash: str) -> None:
        """Move a folder out of the zones (locally one rename; it goes with the run folder)."""
        if not self.exists(path):
            return
        if self.is_local:
            self.delete_dir(trash)
            self._mkdir(trash.rpartition("/")[0])
            os.replace(path, trash)
        else:
            self.delete_dir(path)

    def sweep(self, clip_id: str | None = None, *,
              foreign_older_than_s: float | None = None) -> Sweep:
        """Clean up after runs that died (SIGKILL, power loss): every name a run leaves
        behind carries its owner (``run_tag``: process id and host), so what a live run
        owns is kept. Dead runs' staging folders are rolled forward when their publish had
        begun (journal present) and removed otherwise; with ``clip_id=None`` also their
        release builds in progress (``releases/.NAME.building-...``), hidden temporary files
        (``.NAME.tmp-...``) and catalog temporaries. Runs of another host are kept unless
        ``foreign_older_than_s`` is given and their folder is older than that.
        """
        out = Sweep()
        root = self.path("_staging")
        clips = [clip_id] if clip_id is not None else [
            i.base_name for i in self._children(root) if i.type == pafs.FileType.Directory]
        for cid in clips:
            folder = self.path("_staging", cid)
            for info in self._children(folder):
                if not self._dead(info, foreign_older_than_s):
                    out.kept.append(info.path)
                    continue
                if self.exists(f"{info.path}/{JOURNAL}"):
                    self._roll_forward(info.path)
                    out.rolled_forward.append(info.path)
                self.delete_dir(info.path)
                out.runs.append(info.path)
            if self.is_local:
                with contextlib.suppress(OSError):
                    os.rmdir(folder)
        if clip_id is None:
            for info in self._children(self.path("releases")):
                if ".building-" in info.base_name and self._dead(info, foreign_older_than_s):
                    self.delete_dir(info.path)
                    out.runs.append(info.path)
            if self.is_local:
                out.files.extend(self._sweep_files(foreign_older_than_s))
        if self.is_local:
            with contextlib.suppress(OSError):
                os.rmdir(root)
        return out

    def _children(self, path: str) -> list[pafs.FileInfo]:
        if not self.exists(path):
            return []
        return list(self.fs.get_file_info(pafs.FileSelector(path, recursive=False)))

    @staticmethod
    def _dead(info: pafs.FileInfo, foreign_older_than_s: float | None) -> bool:
        state = owner_state(info.base_name)
        if state == "foreign" and foreign_older_than_s is not None and info.mtime is not None:
            return bool(time.time() - info.mtime.timestamp() > foreign_older_than_s)
        return state == "dead"

    def _sweep_files(self, foreign_older_than_s: float | None) -> list[str]:
        """Hidden temporary files of dead runs (a writer killed between write and rename)
        anywhere in a local lake (``_staging`` is swept by folder, blob folders only ever
        arrive by rename, so neither is walked)."""
        gone = []
        for top, dirs, files in os.walk(self.base):
            dirs[:] = [d for d in dirs if d not in ("_staging", "blobs")]
            for name in files:
                if name.startswith(".") and (".tmp-" in name or name.startswith(".catalog-")):
                    path = os.path.join(top, name)
                    info = self.fs.get_file_info(path)
                    if self._dead(info, foreign_older_than_s):
                        with contextlib.suppress(FileNotFoundError):
                            os.remove(path)
                        gone.append(path)
        return gone

    def copy_in(self, src: str | os.PathLike[str], dest: str, *, link: bool = False) -> int:
        """Copy a local file into the lake at ``dest`` (a lake path); returns bytes copied.
        Used for the landing zone (bags as delivered).

        ``link=True`` (ingest's landing copy): on a local lake, hard-link the file when it is
        on the same filesystem (no data written: bags as delivered are immutable, and a link
        keeps them even if the delivery folder is deleted); otherwise, or where links are not
        allowed, a real copy (``shutil.copyfile``: in-kernel ``sendfile`` on Linux).

        ``src`` is resolved first, so the lake gets the file a symlink points at, never the
        symlink: Linux ``link()`` would hard-link the symlink itself, and a symlink in the
        lake is a way out of it for anything that reads the lake's folders (user SQL).
        Whether the target may be read at all is the caller's decision (ingest's
        ``plain_files``)."""
        src = os.path.realpath(src)
        head = dest.rpartition("/")[0]
        size = os.path.getsize(src)
        with self.writing(dest):
            self._mkdir(head)
            if not self.is_local:
                pafs.copy_files(str(src), dest, source_filesystem=pafs.LocalFileSystem(),
                                destination_filesystem=self.fs)
                return size
            tmp = self._tmp(dest)
            linked = False
            if link:
                try:
                    os.link(src, tmp)
                    linked = True
                except OSError:  # other filesystem (EXDEV), no permission, no link support
                    pass
            try:
                if not linked:
                    shutil.copyfile(src, tmp)
                os.replace(tmp, dest)
            except BaseException:  # disk full half-way: no temporary copy stays behind
                with contextlib.suppress(OSError):
                    os.remove(tmp)
                raise
        return size


CLIP_ID = re.compile(ID_PATTERN)

#: Longest name ``safe_name`` keeps as it is (bytes); a file name stops at 255.
MAX_NAME_BYTES = 160


def safe_name(name: str) -> str:
    """``name`` as one lake folder or file name: unchanged when it is short and holds no
    ``/`` or NUL (every clip id is), else a prefix of its safe characters and a hash of the
    whole. Quarantine reports and locks are named after ids that may come from a broken
    delivery (an ``_unreadable-<folder>`` name, an overlong id): an OSError there would
    hide the real problem."""
    if len(name.encode()) <= MAX_NAME_BYTES and name and "/" not in name and "\0" not in name \
            and name not in (".", ".."):
        return name
    digest = hashlib.blake2s(name.encode("utf-8", "surrogatepass"), digest_size=8).hexdigest()
    head = re.sub(r"[^A-Za-z0-9_\-]+", "_", name)[:96]
    return f"{head}-{digest}"


# ---------------------------------------------------------------- one writer per clip (#25)
class ClipBusy(RuntimeError):
    """Another process holds the clip's lock longer than this one may wait."""


#: How long a second writer of a clip waits for the first (seconds) before it is refused;
#: ``V2XLAKE_CLIP_LOCK_WAIT_S`` overrides it.
CLIP_LOCK_WAIT_S = 600.0
#: S3 lock lease (seconds): renewed every third of it while held; a holder that stopped
#: renewing for longer (a killed process, a lost host) is taken over.
S3_LOCK_LEASE_S = 60.0


class _Held:
    """This process's hold on one lock: a thread lock (threads of one process exclude each
    other and one thread may re-enter) and the storage lock, taken once."""

    def __init__(self) -> None:
        self.rlock = threading.RLock()
        self.depth = 0
        self.release: Any = None


_HELD: dict[str, _Held] = {}
_HELD_GUARD = threading.Lock()


def _lock_wait_s(wait_s: float | None) -> float:
    if wait_s is not None:
        return wait_s
    try:
        return float(os.environ.get("V2XLAKE_CLIP_LOCK_WAIT_S", CLIP_LOCK_WAIT_S))
    except ValueError:
        return CLIP_LOCK_WAIT_S


def _flock(path: str, wait_s: float, what: str) -> Any:
    """An exclusive ``flock`` on a local lock file (released by the kernel when the process
    dies, whatever killed it); returns the function releasing it."""
    import fcntl

    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    deadline = time.monotonic() + wait_s
    delay = 0.05
    while True:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            break
        except BlockingIOError:
            if time.monotonic() >= deadline:
                holder = ""
                with contextlib.suppress(OSError):
                    holder = os.pread(fd, 200, 0).decode(errors="replace").strip()
                os.close(fd)
                raise ClipBusy(f"{what} is being written by another run ({holder or 'unknown'}); "
                               f"waited {wait_s:g} s: try again when it has finished") from None
            time.sleep(delay)
            delay = min(delay * 2, 1.0)
        except BaseException:
            os.close(fd)
            raise
    tag = f"{run_tag()} since {time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime())}"
    with contextlib.suppress(OSError):
        os.ftruncate(fd, 0)
        os.pwrite(fd, tag.encode(), 0)

    def release() -> None:
        try:
            fcntl.flock(fd, fcntl.LOCK_UN)
        finally:
            os.close(fd)
    return release


def _s3_client() -> Any:
    import boto3

    endpoint = os.environ.get("AWS_ENDPOINT_URL") or os.environ.get("V2XLAKE_S3_ENDPOINT")
    return boto3.client("s3", endpoint_url=endpoint or None,
                        region_name=os.environ.get("AWS_REGION", "us-east-1"),
                        aws_access_key_id=os.environ.get("AWS_ACCESS_KEY_ID"),
                        aws_secret_access_key=os.environ.get("AWS_SECRET_ACCESS_KEY"))


def _s3_lock(path: str, wait_s: float, what: str, lease_s: float) -> Any:
    """A lease object created with a conditional PUT (``If-None-Match: *``: exactly one
    writer creates it), renewed by a thread with ``If-Match`` on its ETag while held, taken
    over (conditional DELETE on the stale ETag, then the conditional PUT again) when its
    lease ran out; returns the function releasing it."""
    from botocore.exceptions import ClientError

    bucket, _, key = path.partition("/")
    client = _s3_client()
    owner = f"{run_tag()}-{uuid.uuid4().hex[:12]}"

    def body() -> bytes:
        return json.dumps({"owner": owner, "expires": time.time() + lease_s}).encode()

    def code(e: ClientError) -> str:
        return str(e.response.get("Error", {}).get("Code", ""))

    deadline = time.monotonic() + wait_s
    delay = 0.05
    holder = "unknown"
    while True:
        try:
            etag = client.put_object(Bucket=bucket, Key=key, Body=body(),
                                     IfNoneMatch="*")["ETag"]
            break
        except ClientError as e:
            if code(e) not in ("PreconditionFailed", "ConditionalRequestConflict", "412"):
                raise
        try:
            got = client.get_object(Bucket=bucket, Key=key)
            info = json.loads(got["Body"].read() or b"{}")
            holder = str(info.get("owner", "unknown"))[:100]
            if float(info.get("expires", 0)) < time.time():  # its holder stopped renewing
                with contextlib.suppress(ClientError):
                    client.delete_object(Bucket=bucket, Key=key, IfMatch=got["ETag"])
                continue
        except ClientError as e:
            if code(e) not in ("NoSuchKey", "404"):
                raise
            continue  # released meanwhile: try again at once
        except ValueError:  # not our JSON: treat as held until the deadline
            pass
        if time.monotonic() >= deadline:
            raise ClipBusy(f"{what} is being written by another run ({holder}); waited "
                           f"{wait_s:g} s: try again when it has finished")
        time.sleep(delay)
        delay = min(delay * 2, 1.0)

    stop = threading.Event()
    state = {"etag": etag}

    def renew() -> None:
        while not stop.wait(lease_s / 3):
            with contextlib.suppress(Exception):
                state["etag"] = client.put_object(Bucket=bucket, Key=key, Body=body(),
                                                  IfMatch=state["etag"])["ETag"]

    thread = threading.Thread(target=renew, name="lake-lock", daemon=True)
    thread.start()

    def release() -> None:
        stop.set()
        thread.join()
        with contextlib.suppress(ClientError):
            client.delete_object(Bucket=bucket, Key=key, IfMatch=state["etag"])
    return release


@contextlib.contextmanager
def clip_lock(lake: Lake, clip_id: str, wait_s: float | None = None) -> Iterator[None]:
    """Hold ``clip_id``'s write lock: one process at a time runs a stage on (or quarantines)
    a clip; a second waits up to ``wait_s`` (``CLIP_LOCK_WAIT_S``) and is then refused with
    ``ClipBusy``. Local lakes take an ``flock`` on ``_locks/<clip>.lock`` (the kernel drops
    it with its process); S3 lakes a lease object created by a conditional PUT. Re-entrant
    within a thread; threads of one process exclude each other.

    Why: two runs of one clip each decide from the manifests what to run, then read, write
    and record; interleaved, one run's stage read what the other's ingest was replacing and
    recorded a key for inputs it never saw (a table lost, the manifest saying current)."""
    name = safe_name(clip_id)
    path = lake.path("_locks", f"{name}.lock")
    what = f"clip {clip_id}"
    with _HELD_GUARD:
        held = _HELD.setdefault(f"{lake.uri}\0{name}", _Held())
    wait = _lock_wait_s(wait_s)
    if not held.rlock.acquire(blocking=wait > 0, timeout=wait if wait > 0 else -1):
        raise ClipBusy(f"{what} is being written by another thread of this process; "
                       f"waited {wait:g} s")
    try:
        if held.depth == 0:
            with lake.writing(path):  # a read-only lake: one clear line
                lake._mkdir(path.rpartition("/")[0])
                held.release = (_flock(path, wait, what) if lake.is_local
                                else _s3_lock(path, wait, what, S3_LOCK_LEASE_S))
        held.depth += 1
        try:
            yield
        finally:
            held.depth -= 1
            if held.depth == 0:
                release, held.release = held.release, None
                release()
    finally:
        held.rlock.release()


def checked_clip_id(lake: Lake, clip_id: str) -> str:
    """A clip id that is safe to build lake paths from: it matches the id pattern of the
    input contract, and its partition folders resolve inside the lake root (after
    symlinks). Ids come back from user-written SQL, so they are checked, never trusted."""
    if not isinstance(clip_id, str) or not CLIP_ID.fullmatch(clip_id):
        raise ValueError(f"not a clip id: {clip_id!r}")
    if lake.is_local:
        root = os.path.realpath(lake.base)
        for zone in ("raw", "clean"):
            p = os.path.realpath(os.path.join(root, zone, "blobs", clip_id))
            if os.path.commonpath([root, p]) != root:
                raise ValueError(f"clip id {clip_id!r} resolves outside the lake")
    return clip_id
