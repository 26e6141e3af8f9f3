"""The frame layout of a points table, known in one place: which file and row group hold a
frame's points.

Point tables (``lidar_points``, ``lidar_points_deskewed``) are written one row group per frame
and per LiDAR, in frame order (``Lake.write_table(row_group_by="frame_idx")``), one file per
agent and LiDAR (or per chunk of frames). A stage that reads one frame at a time (deskew by
chunks of row groups, register pair by pair) asks this index instead of opening Parquet
footers itself, so the layout can change here without touching a stage.

The index is built from the files' footers only (row-group statistics of ``frame_idx``); a
row group without usable statistics, or holding several frames (a file written without
``row_group_by``), has its ``frame_idx`` column read once.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from v2xlake.storage.lake import Lake


@dataclass(frozen=True)
class RowGroupRef:
    """One row group of one file of a points table."""

    path: str
    row_group: int
    # the one LiDAR all its rows belong to when its footer says so (frame_idx and sensor
    # statistics min == max): then ``read`` needs neither column nor a filter
    sensor: str | None = None


@dataclass
class PointFrameIndex:
    """One agent's points table: frame index -> the row groups holding its points.

    ``read(frame_idx, sensor, columns)`` returns exactly that frame's rows of that LiDAR
    (a row group shared by several frames or LiDARs is filtered). Safe to read from several
    threads (the register stage reads frames on a pool): each thread keeps its own open
    files, since one pyarrow ``ParquetFile`` is not documented as safe to read from two."""

    lake: Lake
    table: str
    files: list[str]
    groups: dict[int, list[RowGroupRef]] = field(default_factory=dict)
    _open: threading.local = field(default_factory=threading.local, repr=False,
                                   compare=False)

    @classmethod
    def build(cls, lake: Lake, zone: str, table: str, clip_id: str,
              agent_id: str) -> PointFrameIndex:
        lake.check_read(zone, table)
        files = lake.list_files(lake.table_dir(zone, table, clip_id, agent_id), ".parquet")
        idx = cls(lake, table, files)
        for path in files:
            pf = idx._file(path)
            col = pf.schema_arrow.get_field_index("frame_idx")
            scol = pf.schema_arrow.get_field_index("sensor")
            for rg in range(pf.num_row_groups):
                meta = pf.metadata.row_group(rg)
                st = meta.column(col).statistics
                sensor = None
                if st is not None and st.has_min_max and st.min == st.max:
                    frames = [int(st.min)]
                    ss = meta.column(scol).statistics if scol >= 0 else None
                    if ss is not None and ss.has_min_max and ss.min == ss.max \
                            and ss.null_count == 0:
                        v = ss.min
                        sensor = v.decode() if isinstance(v, bytes) else str(v)
                else:
                    frames = [int(f) for f in np.unique(
                        pf.read_row_group(rg, columns=["frame_idx"]).column(0).to_numpy())]
                for f in frames:
                    idx.groups.setdefault(f, []).append(RowGroupRef(path, rg, sensor))
        return idx

    def _file(self, path: str) -> pq.ParquetFile:
        files: dict[str, pq.ParquetFile] | None = getattr(self._open, "files", None)
        if files is None:
            files = self._open.files = {}
        if path not in files:
            files[path] = pq.ParquetFile(path, filesystem=self.lake.fs)
        return files[path]

    def frames(self) -> list[int]:
        return sorted(self.groups)

    def __bool__(self) -> bool:
        return bool(self.groups)

    def read(self, frame_idx: int, sensor: str | None,
             columns: Sequence[str] | None = None) -> pa.Table | None:
        """The frame's rows (of ``sensor`` when given), ``columns`` only (``frame_idx`` and
        ``sensor`` are read for the filter and dropped unless asked for); None when the
        table has no row for it."""
        want = list(columns) if columns is not None else None
        read = None if want is None else list(dict.fromkeys(
            [*want, "frame_idx", *(["sensor"] if sensor is not None else [])]))
        parts = []
        for ref in self.groups.get(int(frame_idx), []):
            if want is not None and ref.sensor is not None:
                # one frame of one LiDAR (the lake's layout): the filter below copied every
                # column to keep all rows (deskewed 61k-point frames of the register stage:
                # 4-6 ms -> 1.7 ms a frame)
                pf = self._file(ref.path)
                parts.append(pf.read_row_group(ref.row_group, columns=want)
                             if sensor is None or ref.sensor == sensor else pa.schema(
                                 [pf.schema_arrow.field(c) for c in want]).empty_table())
                continue
            t = self._file(ref.path).read_row_group(ref.row_group, columns=read)
            keep = pc.equal(t.column("frame_idx"), int(frame_idx))
            if sensor is not None:
                keep = pc.and_(keep, pc.equal(t.column("sensor").cast(pa.string()), sensor))
            t = t.filter(keep)
            parts.append(t if want is None else t.select(want))
        if not parts:
            return None
        return parts[0] if len(parts) == 1 else pa.concat_tables(parts)


def row_group_count(lake: Lake, path: str) -> int:
    """Row groups of one points file (one per frame and LiDAR as the lake writes them)."""
    return int(pq.ParquetFile(path, filesystem=lake.fs).num_row_groups)


def iter_row_groups(lake: Lake, path: str, start: int = 0, stop: int | None = None,
                    columns: Sequence[str] | None = None, *, use_threads: bool = True
                    ) -> Iterator[pa.Table]:
    """Row groups ``start`` .. ``stop - 1`` (all by default) of one points file, one table
    each: a frame at a time (deskew splits a file into such ranges, anonymize streams it).
    ``use_threads=False``: one frame's columns are too small for pyarrow's pool to pay
    (anonymize's copy: 1.5 -> 0.9 ms per 61k-point frame)."""
    pf = pq.ParquetFile(path, filesystem=lake.fs)
    end = pf.num_row_groups if stop is None else min(stop, pf.num_row_groups)
    for rg in range(start, end):
        yield pf.read_row_group(rg, columns=None if columns is None else list(columns),
                                use_threads=use_threads)


def file_schema(lake: Lake, path: str) -> pa.Schema:
    """The Arrow schema of one lake file (from its footer)."""
    return pq.ParquetFile(path, filesystem=lake.fs).schema_arrow



def partition_files(lake: Lake, zone: str, table: str,
                    clip_id: str) -> list[tuple[str, str | None, str]]:
    """(path, agent_id or None, file name stem) of every Parquet file of one clip's partition
    of ``zone.table``: the unit a stage that rewrites or splits a table works on."""
    lake.check_read(zone, table)
    root = lake.table_dir(zone, table, clip_id)
    out = []
    for path in lake.list_files(root, ".parquet"):
        rel = path[len(root):].strip("/").split("/")
        agent = next((s.split("=", 1)[1] for s in rel[:-1] if s.startswith("agent_id=")), None)
        out.append((path, agent, rel[-1][: -len(".parquet")]))
    return out
