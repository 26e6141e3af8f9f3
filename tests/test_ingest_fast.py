"""Ingest's fast path keeps its promises: chunked decoding equals the plain column-by-column
definition, output checksums taken while writing equal the files' sha256, the raw zone gets
its own encoding, the landing copy is a hard link where possible, failures leave nothing."""

from __future__ import annotations

import hashlib
import os
import threading
from pathlib import Path
from types import SimpleNamespace as NS

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from schemas.clip import LidarFields, PointTimeField, TimeReference, TimeUnit
from storage.lake import RAW_OPTIONS, Lake, ParquetOptions
from tasks.ingest import IngestConfig, pointcloud, run_ingest
from tests.fixtures.minibag import MiniClip, write_clip


def _msg(a: np.ndarray, fields: list[tuple[str, int, int, int]]) -> NS:
    return NS(height=1, width=a.size, point_step=a.dtype.itemsize,
              row_step=a.dtype.itemsize * a.size, is_bigendian=False,
              data=a.view(np.uint8).ravel(),
              fields=[NS(name=n, offset=o, datatype=d, count=c) for n, o, d, c in fields])


@pytest.mark.parametrize("chunk", [5, 64, 1 << 20])
def test_chunked_decode_equals_columnwise_definition(monkeypatch: pytest.MonkeyPatch,
                                                     chunk: int) -> None:
    monkeypatch.setattr(pointcloud, "CHUNK", chunk)
    rng = np.random.default_rng(1)
    n = 203
    dt = np.dtype({"names": ["x", "y", "z", "i", "t", "ring", "ret"],
                   "formats": ["<f8", "<f4", "<f4", ("<f4", 2), "<u4", "<u2", "u1"],
                   "offsets": [0, 8, 12, 16, 24, 28, 30], "itemsize": 32})
    a = np.zeros(n, dt)
    a["x"], a["y"], a["z"] = rng.normal(0, 10, n), rng.normal(0, 10, n), rng.normal(0, 1, n)
    a["i"] = rng.random((n, 2)) * 100
    a["t"] = rng.integers(0, 100_000_000, n)
    a["ring"], a["ret"] = rng.integers(0, 128, n), rng.integers(0, 3, n)
    a["x"][rng.random(n) < 0.2] = np.nan
    a["z"][rng.random(n) < 0.1] = np.inf
    a["y"][40:80] = np.nan  # whole chunks without a finite point
    fields = [("x", 0, 8, 1), ("y", 8, 7, 1), ("z", 12, 7, 1), ("i", 16, 7, 2), ("t", 24, 6, 1),
              ("ring", 28, 4, 1), ("ret", 30, 2, 1)]
    lf = LidarFields(intensity="i", ring="ring", return_id="ret", time=PointTimeField(
        field="t", unit=TimeUnit.NS, reference=TimeReference.HEADER))
    c = pointcloud.decode_cloud(_msg(a, fields), lf, stamp_ns=7_000_000_000)
    keep = np.isfinite(a["x"]) & np.isfinite(a["y"]) & np.isfinite(a["z"])
    assert c.n_points == int(keep.sum()) and c.n_nan == n - int(keep.sum())
    assert np.array_equal(c.x, a["x"][keep].astype(np.float32))
    assert np.array_equal(c.y, a["y"][keep]) and np.array_equal(c.z, a["z"][keep])
    assert np.array_equal(c.intensity, a["i"][keep][:, 0])
    assert np.array_equal(c.t_ns, a["t"][keep].astype(np.int64) + 7_000_000_000)
    assert c.ring.dtype == np.uint16 and np.array_equal(c.ring, a["ring"][keep])
    assert c.return_id.dtype == np.uint8 and np.array_equal(c.return_id, a["ret"][keep])
    assert (c.t_start_ns, c.t_end_ns) == (int(c.t_ns.min()), int(c.t_ns.max()))
    for col in (c.x, c.t_ns, c.ring):
        assert col.flags.c_contiguous


def test_outputs_checksummed_while_writing_and_raw_encoding(tmp_path: Path) -> None:
    clip = write_clip(tmp_path / "clip", MiniClip(seconds=0.2, points=300, clip_id="fast"))
    lake = Lake(tmp_path / "lake")
    rep = run_ingest(lake, clip)
    assert rep.outputs and all(o.sha256 for o in rep.outputs)
    for o in rep.outputs:
        path = lake.path(o.path)
        assert hashlib.sha256(Path(path).read_bytes()).hexdigest() == o.sha256, o.path
        assert pq.ParquetFile(path).metadata.num_rows == o.rows
    pts = next(lake.path(o.path) for o in rep.outputs if "/lidar_points/" in o.path)
    md = pq.ParquetFile(pts).metadata
    names = [md.schema.column(i).name for i in range(md.num_columns)]
    col = {n: md.row_group(0).column(i) for i, n in enumerate(names)}
    assert col["x"].compression == "LZ4" and "BYTE_STREAM_SPLIT" in col["x"].encodings
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
    # the hashing and encoding threads stopped
    assert not [t for t in threading.enumerate() if t.name == "sha256"
                or t.name.startswith("parquet")]
    with lake.open_writer("raw", "t", schema, clip_id="c", background=True) as w:
        w.write(pa.table({"frame_idx": pa.array([1, 2], pa.int32())}, schema=schema))
    (path, (rows, sha)), = lake.written.items()
    assert rows == 2 and sha == hashlib.sha256(Path(path).read_bytes()).hexdigest() == w.sha256
