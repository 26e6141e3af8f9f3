"""Parquet files outside the lake: an export's side tables, the simulator's truth, a
benchmark's inputs. The lake's own tables go through :class:`~v2xlake.storage.lake.Lake`;
these helpers keep the one rule that matters for a plain folder too: a file is written
under a temporary name and renamed, so a reader never sees half of it.
"""

from __future__ import annotations

import os
from pathlib import Path

import pyarrow as pa
import pyarrow.fs as pafs
import pyarrow.parquet as pq


def write_parquet(path: str | os.PathLike[str], table: pa.Table, *,
                  compression: str = "zstd") -> int:
    """Write ``table`` to ``path`` atomically (parents created); returns its rows."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(f".{p.name}.{os.getpid()}.tmp")
    try:
        pq.write_table(table, tmp, compression=compression)
        os.replace(tmp, p)
    finally:
        tmp.unlink(missing_ok=True)
    return int(table.num_rows)


def read_parquet(path: str | os.PathLike[str], columns: list[str] | None = None,
                 filesystem: pafs.FileSystem | None = None) -> pa.Table:
    """A whole Parquet file (``columns`` only), local or on ``filesystem``."""
    return pq.read_table(str(path) if filesystem is not None else Path(path), columns=columns,
                         filesystem=filesystem)


def read_parquet_head(path: str, row_groups: int,
                      filesystem: pafs.FileSystem | None = None) -> pa.Table:
    """The first ``row_groups`` row groups of a Parquet file (a points table's first frames):
    what a scan of a release needs to judge a table's columns without reading all of it."""
    pf = pq.ParquetFile(path, filesystem=filesystem)
    return pf.read_row_groups(list(range(min(pf.num_row_groups, row_groups))))
