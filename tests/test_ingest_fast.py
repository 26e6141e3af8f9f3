"""Ingest's fast path keeps its promises: the compiled decoding equals the plain column-by-
column definition, output checksums taken while writing equal the files' checksums, the raw
zone gets its own encoding, the landing copy is a hard link where possible, failures (in the
caller, the encoder or the I/O thread) leave nothing."""

from __future__ import annotations

import os
import threading
from pathlib import Path
from types import SimpleNamespace as NS

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from tests.fixtures.minibag import MiniClip, write_clip
from v2xlake.schemas.clip import LidarFields, PointTimeField, TimeReference, TimeUnit
from v2xlake.storage import checksum
from v2xlake.storage.lake import RAW_OPTIONS, Lake, ParquetOptions
from v2xlake.tasks.ingest import IngestConfig, pointcloud, run_ingest


def _msg(a: np.ndarray, fields: list[tuple[str, int, int, int]]) -> NS:
    return NS(height=1, width=a.size, point_step=a.dtype.itemsize,
              row_step=a.dtype.itemsize * a.size, is_bigendian=False,
              data=a.view(np.uint8).ravel(),
              fields=[NS(name=n, offset=o, datatype=d, count=c) for n, o, d, c in fields])


def _cloud(rng: np.random.Generator, n: int, order: str, time_fmt: str, offset: int
           ) -> tuple[np.ndarray, list[tuple[str, int, int, int]]]:
    """Records with an odd point_step and fields at unaligned offsets (``offset`` shifts them
    all), float64 x, a two-element intensity, NaN/inf points and a run of non-finite points."""
    o = offset
    dt = np.dtype({"names": ["x", "y", "z", "i", "t", "ring", "ret"],
                   "formats": [order + "f8", order + "f4", order + "f4", (order + "f4", 2),
                               order + time_fmt, order + "u2", "u1"],
                   "offsets": [o, o + 8, o + 12, o + 16, o + 24, o + 32, o + 34],
                   "itemsize": o + 37})
    a = np.zeros(n, dt)
    a["x"], a["y"], a["z"] = rng.normal(0, 10, n), rng.normal(0, 10, n), rng.normal(0, 1, n)
    a["i"] = rng.random((n, 2)) * 100
    a["t"] = (rng.integers(0, 100_000_000, n) if time_fmt.startswith("u")
              else 1_700_000_007.0 + rng.random(n) * 0.1)
    a["ring"], a["ret"] = rng.integers(0, 128, n), rng.integers(0, 3, n)
    a["x"][rng.random(n) < 0.2] = np.nan
    a["z"][rng.random(n) < 0.1] = np.inf
    a["y"][40:80] = np.nan
    code = {"u4": 6, "f8": 8}[time_fmt]
    fields = [("x", o, 8, 1), ("y", o + 8, 7, 1), ("z", o + 12, 7, 1), ("i", o + 16, 7, 2),
              ("t", o + 24, code, 1), ("ring", o + 32, 4, 1), ("ret", o + 34, 2, 1)]
    return a, fields


@pytest.mark.parametrize("order", ["<", ">"])
@pytest.mark.parametrize("time_fmt", ["u4", "f8"])
@pytest.mark.parametrize("optional", [True, False])
def test_compiled_decode_equals_columnwise_definition(order: str, time_fmt: str,
                                                      optional: bool) -> None:
    """``decode_cloud``'s single compiled pass against the plain NumPy definition: keep the
    points whose x, y, z are finite, cast each column, convert time with point_times_ns."""
    rng = np.random.default_rng(1)
    n = 2003
    a, fields = _cloud(rng, n, order, time_fmt, offset=3)
    ref = TimeReference.HEADER if time_fmt == "u4" else TimeReference.ABSOLUTE
    unit = TimeUnit.NS if time_fmt == "u4" else TimeUnit.S
    lf = LidarFields(intensity="i" if optional else None, ring="ring" if optional else None,
                     return_id="ret" if optional else None,
                     time=PointTimeField(field="t", unit=unit, reference=ref))
    stamp = 1_700_000_007_000_000_000
    msg = _msg(a, fields)
    msg.is_bigendian = order == ">"
    c = pointcloud.decode_cloud(msg, lf, stamp_ns=stamp)
    keep = np.isfinite(a["x"]) & np.isfinite(a["y"]) & np.isfinite(a["z"])
    assert c.n_points == int(keep.sum()) and c.n_nan == n - int(keep.sum())
    assert np.array_equal(c.x, a["x"][keep].astype(np.float32))
    assert np.array_equal(c.y, a["y"][keep]) and np.array_equal(c.z, a["z"][keep])
    t = pointcloud.point_times_ns(a["t"][keep], lf.time, stamp)
    assert c.t_ns.dtype == np.int64 and np.array_equal(c.t_ns, t)
    if optional:
        assert np.array_equal(c.intensity, a["i"][keep][:, 0])
        assert c.ring.dtype == np.uint16 and np.array_equal(c.ring, a["ring"][keep])
        assert c.return_id.dtype == np.uint8 and np.array_equal(c.return_id, a["ret"][keep])
    else:
        assert not c.intensity.any() and not c.ring.any() and not c.return_id.any()
    assert (c.t_start_ns, c.t_end_ns) == (int(t.min()), int(t.max()))
    for col in (c.x, c.t_ns, c.ring):
        assert col.flags.c_contiguous


def test_decode_of_a_scan_without_finite_points_keeps_its_time_span() -> None:
    a, fields = _cloud(np.random.default_rng(2), 50, "<", "u4", offset=0)
    a["x"] = np.nan
    lf = LidarFields(intensity="i", time=PointTimeField(field="t", unit=TimeUnit.NS,
                                                        reference=TimeReference.HEADER))
    c = pointcloud.decode_cloud(_msg(a, fields), lf, stamp_ns=10)
    assert c.n_points == 0 and c.n_nan == 50
    assert (c.t_start_ns, c.t_end_ns) == (int(a["t"].min()) + 10, int(a["t"].max()) + 10)


def test_outputs_checksummed_while_writing_and_raw_encoding(tmp_path: Path) -> None:
    clip = write_clip(tmp_path / "clip", MiniClip(seconds=0.2, points=300, clip_id="fast"))
    lake = Lake(tmp_path / "lake")
    rep = run_ingest(lake, clip)
    assert rep.outputs and all(o.checksum for o in rep.outputs)
    for o in rep.outputs:
        path = lake.path(o.path)
        assert checksum.of_file(path) == o.checksum, o.path
        assert o.checksum is not None and o.checksum.startswith("xxh3_128:")
        assert pq.ParquetFile(path).metadata.num_rows == o.rows
    pts = next(lake.path(o.path) for o in rep.outputs if "/lidar_points/" in o.path)
    md = pq.ParquetFile(pts).metadata
    names = [md.schema.column(i).name for i in range(md.num_columns)]
    col = {n: md.row_group(0).column(i) for i, n in enumerate(names)}
    assert col["x"].compression == "LZ4" and "BYTE_STREAM_SPLIT" not in col["x"].encodings
    assert not col["x"].is_stats_set  # no float statistics in the raw zone
    assert col["frame_idx"].is_stats_set and col["t_ns"].is_stats_set
    # the clean zone keeps zstd (anything but raw)
    assert ParquetOptions.for_zone("clean") == ParquetOptions()
    assert ParquetOptions.for_zone("raw") == RAW_OPTIONS


def test_landing_is_a_hard_link_on_the_same_filesystem(tmp_path: Path) -> None:
    clip = write_clip(tmp_path / "clip", MiniClip(seconds=0.2, points=10, clip_id="lnk"))
    lake = Lake(tmp_path / "lake")
    run_ingest(lake, clip, IngestConfig(copy_to_landing=True))
    src = next(p for p in (clip / "red").iterdir() if p.suffix == ".db3")
    dst = Path(lake.path("landing", "lnk", "red", src.name))
    assert dst.read_bytes() == src.read_bytes()
    assert os.stat(dst).st_ino == os.stat(src).st_ino
    # link=False (the default of copy_in) is a real copy
    lake.copy_in(src, lake.path("landing", "copy.db3"))
    assert os.stat(lake.path("landing", "copy.db3")).st_ino != os.stat(src).st_ino


def test_failed_background_writer_leaves_nothing(tmp_path: Path) -> None:
    lake = Lake(tmp_path)
    schema = pa.schema([pa.field("frame_idx", pa.int32(), nullable=False)])
    with pytest.raises(RuntimeError, match="boom"):
        with lake.open_writer("raw", "t", schema, clip_id="c", background=True) as w:
            w.write(pa.table({"frame_idx": pa.array([1, 2], pa.int32())}, schema=schema))
            raise RuntimeError("boom")
    assert lake.list_files(lake.path("raw")) == [] and not lake.written
    leftovers = [p for p in Path(tmp_path).rglob("*") if p.is_file()]
    assert leftovers == []
    # the I/O and encoding threads stopped
    assert not [t for t in threading.enumerate() if t.name == "lake-io"
                or t.name.startswith("parquet")]
    with lake.open_writer("raw", "t", schema, clip_id="c", background=True) as w:
        w.write(pa.table({"frame_idx": pa.array([1, 2], pa.int32())}, schema=schema))
    (path, (rows, sha)), = lake.written.items()
    assert rows == 2 and sha == checksum.of_file(path) == w.checksum


class _FailingStream:
    """A file stream whose disk fills up after ``ok`` writes."""

    def __init__(self, ok: int) -> None:
        self.ok, self.chunks, self.closed = ok, [], False

    def write(self, data: bytes) -> None:
        if len(self.chunks) >= self.ok:
            raise OSError(28, "No space left on device")
        self.chunks.append(bytes(data))

    def flush(self) -> None:
        pass

    def close(self) -> None:
        self.closed = True


def test_io_thread_error_reaches_the_writer() -> None:
    from v2xlake.storage.lake import _ChecksumSink

    good = _ChecksumSink(_FailingStream(ok=10**6), threaded=True)
    for i in range(50):
        good.write(bytes([i]) * 1000)
    assert good.hexdigest() == checksum.of_bytes(b"".join(bytes([i]) * 1000 for i in range(50)))
    good.close()
    stream = _FailingStream(ok=2)
    sink = _ChecksumSink(stream, threaded=True)
    with pytest.raises(OSError, match="No space left"):
        for _ in range(100):  # the error surfaces in a later write (or at the latest in close)
            sink.write(b"x" * 1000)
        sink.close()
    with pytest.raises(OSError):  # closing after the failure releases the stream, still fails
        sink.close()
    assert stream.closed and len(stream.chunks) == 2
    assert not [t for t in threading.enumerate() if t.name == "lake-io"]
