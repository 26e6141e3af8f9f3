"""The lake: one root (a local directory or an ``s3://bucket/prefix`` URI), five zones.

Layout (DESIGN.md "Lake and catalog")::

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

import json
import os
import uuid
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.fs as pafs
import pyarrow.parquet as pq

ZONES = ("landing", "raw", "clean", "releases", "quarantine", "manifests")
PARTITION_KEYS = ("clip_id", "agent_id")


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
    """Defaults chosen by tests/bench/bench_parquet.py (see README): zstd with byte-stream-split
    floats and no dictionary on numeric columns writes ~6x faster than pyarrow's defaults and
    is smaller."""

    compression: str = "zstd"
    compression_level: int = 1


class Lake:
    def __init__(self, uri: str | os.PathLike[str]) -> None:
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
            Path(self.base).mkdir(parents=True, exist_ok=True)
        self.uri = s if not self.is_local else self.base

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
        return f"{head}/.{name}.tmp-{uuid.uuid4().hex}"

    def _commit(self, tmp: str, final: str) -> None:
        if self.is_local:
            os.replace(tmp, final)

    def write_bytes(self, path: str, data: bytes) -> None:
        head = path.rpartition("/")[0]
        self._mkdir(head)
        target = self._tmp(path) if self.is_local else path
        with self.fs.open_output_stream(target) as f:
            f.write(data)
        self._commit(target, path)

    def read_bytes(self, path: str) -> bytes:
        with self.fs.open_input_stream(path) as f:
            return bytes(f.read())

    def exists(self, path: str) -> bool:
        return bool(self.fs.get_file_info(path).type != pafs.FileType.NotFound)

    def delete_dir(self, path: str) -> None:
        if self.exists(path):
            self.fs.delete_dir(path)

    def list_files(self, path: str, suffix: str = "") -> list[str]:
        if not self.exists(path):
            return []
        sel = pafs.FileSelector(path, recursive=True)
        out = [
            i.path for i in self.fs.get_file_info(sel)
            if i.type == pafs.FileType.File and i.path.endswith(suffix)
            and not i.base_name.startswith(".")
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
        self.write_bytes(self.path(zone, "blobs", key), data)
        return key

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
        options: ParquetOptions = ParquetOptions(),  # noqa: B008
    ) -> tuple[str, int]:
        """Write one partition file atomically; returns (path, rows).

        ``row_group_by`` names a sorted column whose runs become row groups (LiDAR points: one
        row group per frame, so a reader fetching one frame touches one row group).
        """
        for key, val in (("clip_id", clip_id), ("agent_id", agent_id)):
            if key in data.column_names:
                col = data.column(key)
                if val is not None and len(col) and not pc.all(pc.equal(col, val)).as_py():
                    raise ValueError(f"{table}: column {key} disagrees with partition {val!r}")
                data = data.drop_columns([key])
        final = f"{self.table_dir(zone, table, clip_id, agent_id)}/{name}.parquet"
        self._mkdir(final.rpartition("/")[0])
        target = self._tmp(final) if self.is_local else final
        floats = [f.name for f in data.schema if pa.types.is_floating(f.type)]
        dict_cols = [
            f.name for f in data.schema
            if pa.types.is_string(f.type) or pa.types.is_dictionary(f.type)
        ]
        writer = pq.ParquetWriter(
            target, data.schema, filesystem=self.fs, compression=options.compression,
            compression_level=options.compression_level, use_dictionary=dict_cols or False,
            use_byte_stream_split=floats or False, write_statistics=True,
        )
        try:
            if row_group_by and data.num_rows:
                keys = data.column(row_group_by).to_numpy()
                cuts = np.flatnonzero(np.diff(keys)) + 1
                bounds = [0, *cuts.tolist(), data.num_rows]
                for a, b in zip(bounds[:-1], bounds[1:], strict=True):
                    writer.write_table(data.slice(a, b - a), row_group_size=b - a)
            else:
                writer.write_table(data, row_group_size=max(data.num_rows, 1))
        finally:
            writer.close()
        self._commit(target, final)
        return final, data.num_rows

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
        """Read every partition file under the given keys, restoring the partition columns."""
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
        self.delete_dir(self.table_dir(zone, table, clip_id))
