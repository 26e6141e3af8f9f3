"""Which Parquet encoding for LiDAR points? Write/read MB/s and bytes/point, same data each.

Data: the three real Ouster OS-1-128 scans of ``../shared/data/real`` (131,072 points each,
with per-point time, ring, intensity) repeated with a per-copy time offset to ``--frames``
frames, one row group per frame, the ``lidar_points`` schema of the lake. Candidates: pyarrow
defaults (snappy + dictionary on every column), zstd level 1 / 3 with byte-stream-split
floats and no dictionary (the lake's choice), the same without byte-stream-split, lz4 and
snappy without dictionary, the lake's own ``ParquetOptions()`` (zstd 1, BSS floats,
DELTA_BINARY_PACKED ints: the clean zone) and ``RAW_OPTIONS`` (the raw zone written by
ingest: lz4, PLAIN everything, no float/dictionary statistics, 64 Ki-value write batches).
MB/s counts in-memory Arrow bytes; best of ``--repeat``.

    python tests/bench/bench_parquet.py [--frames 100]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

from v2xlake.schemas.arrow import arrow_schema  # noqa: E402
from v2xlake.schemas.tables import LidarPointRow  # noqa: E402

OUSTER = REPO.parent / "shared" / "data" / "real" / "bags" / "ouster_os1_128_3frames_ros2"


def real_frames() -> list[pa.Table]:
    from v2xlake.storage.lake import Lake
    from v2xlake.tasks.ingest import IngestConfig, run_ingest

    with tempfile.TemporaryDirectory() as d:
        lake = Lake(d)
        run_ingest(lake, REPO / "tests" / "fixtures" / "ouster",
                   IngestConfig(copy_to_landing=False))
        t = lake.read_table("raw", "lidar_points", clip_id="ouster-os1-128-real")
    t = t.drop_columns(["clip_id", "agent_id"])
    fr = t.column("frame_idx").to_numpy()
    return [t.filter(pa.array(fr == i)) for i in range(3)]


def frames_table(base: list[pa.Table], n: int) -> list[pa.Table]:
    schema = arrow_schema(LidarPointRow).remove(0).remove(0)  # drop clip_id, agent_id
    out = []
    for i in range(n):
        b = base[i % len(base)]
        cols = {name: b.column(name) for name in b.column_names}
        cols["frame_idx"] = pa.array(np.full(b.num_rows, i, np.int32))
        cols["t_ns"] = pa.array(b.column("t_ns").to_numpy() + (i // 3) * 300_000_000)
        out.append(pa.table(cols).select(schema.names).cast(schema))
    return out


CANDIDATES: dict[str, dict[str, object]] = {
    "pyarrow default (snappy+dict)": {},
    "lake: ParquetOptions()": {},  # filled in main() from storage.lake.ParquetOptions
    "lake raw: RAW_OPTIONS": {},  # filled in main() from storage.lake.RAW_OPTIONS
    "zstd1 + BSS, no dict": dict(compression="zstd", compression_level=1,
                                 use_dictionary=["sensor"], use_byte_stream_split=True),
    "zstd3 + BSS, no dict": dict(compression="zstd", compression_level=3,
                                 use_dictionary=["sensor"], use_byte_stream_split=True),
    "zstd1, no BSS, no dict": dict(compression="zstd", compression_level=1,
                                   use_dictionary=["sensor"]),
    "lz4, no dict": dict(compression="lz4", use_dictionary=["sensor"]),
    "snappy, no dict": dict(compression="snappy", use_dictionary=["sensor"]),
}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--repeat", type=int, default=3, help="best of N (noisy machines)")
    args = ap.parse_args()
    from v2xlake.storage.lake import RAW_OPTIONS, ParquetOptions

    frames = frames_table(real_frames(), args.frames)
    CANDIDATES["lake: ParquetOptions()"] = ParquetOptions().writer_kwargs(frames[0].schema)
    CANDIDATES["lake raw: RAW_OPTIONS"] = RAW_OPTIONS.writer_kwargs(frames[0].schema)
    nbytes = sum(f.nbytes for f in frames)
    npts = sum(f.num_rows for f in frames)
    print(f"{args.frames} frames, {npts / 1e6:.1f} M points, {nbytes / 1e6:.0f} MB in Arrow "
          f"({nbytes / npts:.1f} B/point); one row group per frame; cores: {os.cpu_count()}")
    print(f"{'candidate':32s} {'write MB/s':>10s} {'read MB/s':>10s} {'B/point':>8s} "
          f"{'vs default':>10s}")
    base_w = None
    with tempfile.TemporaryDirectory() as d:
        for name, opts in CANDIDATES.items():
            path = f"{d}/x.parquet"
            best_w = best_r = float("inf")
            for _ in range(args.repeat):
                t0 = time.perf_counter()
                with pq.ParquetWriter(path, frames[0].schema, **opts) as w:
                    for f in frames:
                        w.write_table(f, row_group_size=f.num_rows)
                best_w = min(best_w, time.perf_counter() - t0)
                t0 = time.perf_counter()
                back = pq.read_table(path)
                best_r = min(best_r, time.perf_counter() - t0)
            assert back.num_rows == npts
            size = os.path.getsize(path)
            w_mbs = nbytes / 1e6 / best_w
            base_w = base_w or w_mbs
            print(f"{name:32s} {w_mbs:10.0f} {nbytes / 1e6 / best_r:10.0f} {size / npts:8.2f} "
                  f"{w_mbs / base_w:9.2f}x")


if __name__ == "__main__":
    main()
