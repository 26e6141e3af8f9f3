"""The DuckDB catalog: every lake table as SQL, straight over the Parquet files.

Why views over hive-partitioned Parquet and not DuckLake (full reasoning in
``docs/architecture-catalog.md``): each clip's stage writes its own files with an atomic rename
(or a single S3 PUT), so there is no shared commit that concurrent writers could lose, and
publishing a clip needs no catalog write at all. A ``catalog.duckdb`` file holding the same
views as globs is (re)written by ``refresh()`` for external tools (the ``duckdb`` CLI, BI
tools); it is replaced atomically, so two processes refreshing at once cannot corrupt it.

At scale (``tests/bench/bench_scale.py``, ``docs/scale.md``): a ``Catalog`` creates a view
only when a query first names it (binding a view over a table reads its files' footers;
binding all ~70 on a 1,000-clip lake took 12-17 s and 1.4 GiB before the first answer), over
the explicit list of the table's files from one listing, without ``union_by_name`` when the
first and the newest file share a schema (``union_by_name`` reads every footer at bind time);
a query that meets a file of another schema is re-run with ``union_by_name``. What remains
is one open per file (~50-100 us here, a GET on S3): ``refresh()`` (the flows run it after
processing) writes per-table snapshots under ``_catalog/`` that hold the rows of thousands
of small per-clip files in one, checked against the listing on every read (a cache: stale
costs time, never a wrong answer; ``write_snapshots``).

Names:

- ``raw.<table>`` / ``clean.<table>``: every table found in that zone (plus the known tables of
  ``v2xlake.schemas.tables``, as empty views with the right columns when no file exists yet).
- ``main.<table>`` (unqualified, the DESIGN names: clips, agents, sensors, calibrated_sensors,
  ego_poses, lidar_frames, lidar_points, camera_frames, annotations, instances,
  registrations, alignments): the clean zone's table when it has any file, otherwise the raw
  zone's (a clip that is only ingested still answers ``SELECT * FROM clips``). Which zone
  backs each name is in ``catalog_tables`` and ``Catalog.zones``. ``qa_checks`` is raw (QA
  runs before anonymization), ``manifests`` reads ``manifests/*/*.json``, ``quarantine`` the
  quarantine reports. Raw-only tables (``ins``) are only reachable as ``raw.<table>``.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import uuid
import weakref
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any
from urllib.parse import urlparse

import duckdb
import pyarrow as pa
import pyarrow.fs as pafs

from v2xlake.schemas.arrow import arrow_schema
from v2xlake.schemas.tables import LAKE_TABLES, LidarPointRow
from v2xlake.storage.lake import Lake, run_tag

MAIN_NAMES = ("clips", "agents", "sensors", "calibrated_sensors", "ego_poses", "imu", "gnss",
              "lidar_frames", "lidar_points", "lidar_points_deskewed", "camera_frames",
              "radar_frames", "radar_points",
              "annotations", "instances", "registrations", "calibration_refined", "alignments",
              "anonymization_audit", "qa_checks", "deskew_frames")
# Each table has one writer. What a later stage adds about another stage's rows lives in its
# own table and the main view joins it in: deskew's per-frame figures (``deskew_frames``)
# into ``lidar_frames``; annotate's point count per box (``annotations_world``) into
# ``annotations``. (joined table, keys, columns it replaces; None: it adds its columns)
JOINED: dict[str, tuple[str, tuple[str, ...], tuple[str, ...] | None]] = {
    "lidar_frames": ("deskew_frames", ("clip_id", "agent_id", "sensor", "frame_idx"), None),
    "annotations": ("annotations_world", ("clip_id", "agent_id", "frame_idx", "instance_id"),
                    ("num_lidar_pts",)),
}
EXTRA_SCHEMAS = {"lidar_points_deskewed": LidarPointRow}
# Per-table snapshots (``Catalog.write_snapshots``): one Parquet file per table under
# ``_catalog/<zone>/`` with the lake-relative source path of each row and, in its metadata,
# (size, mtime_ns) of every file it holds. Tables above the size limit (points) get none.
SNAPSHOT_DIR = "_catalog"

#: The lake folders a locked-down catalog (user SQL) may read: what its views read (the
#: table zones, their snapshots, the manifests and quarantine reports), nothing else. Not
#: the lake root: ``landing/`` holds deliveries as delivered (files a clip folder brought,
#: checked by ingest but never meant to be queried), and DuckDB's ``allowed_directories``
#: compares path text, so anything under an allowed folder that is a symlink would be
#: followed out of it. Releases are read by their own tools, not by ``v2xlake query``.
QUERY_READABLE = ("raw", "clean", SNAPSHOT_DIR, "manifests", "quarantine")
SNAPSHOT_KEY = b"v2xlake_sources"
SNAPSHOT_MAX_BYTES = 256 * 2**20
SNAPSHOT_MIN_FILES = 64
SOURCE = "_source"
MANIFEST_COLUMNS = {
    "clip_id": "VARCHAR", "stage": "VARCHAR", "status": "VARCHAR", "code_version": "VARCHAR",
    "params_hash": "VARCHAR", "inputs_hash": "VARCHAR", "outputs": "JSON", "error": "VARCHAR",
    "recorded_at": "VARCHAR",
}
QUARANTINE_COLUMNS = {"clip_id": "VARCHAR", "stage": "VARCHAR", "reason": "VARCHAR",
                      "quarantined_at": "VARCHAR"}


class QueryRefused(ValueError):
    """User SQL that is not allowed (not one SELECT, not one expression, not the lake's)."""


class QueryTimeout(QueryRefused):
    """User SQL that ran past its statement timeout (stopped)."""


#: Bounds of user SQL (``v2xlake query``, ``release build --where``, the API's user
#: queries), each overridable by its environment variable: a statement timeout (seconds,
#: ``V2XLAKE_QUERY_TIMEOUT_S``), DuckDB's memory limit (``V2XLAKE_QUERY_MEMORY``) and spill
#: limit, and the most rows fetched: the CLI streams its answer, keeps the first
#: ``--max-rows`` (50 for a table, ``QUERY_MAX_ROWS`` for csv/json) and only counts the
#: rest; ``user_query`` (the API) fetches whole answers unless ``V2XLAKE_QUERY_MAX_ROWS``
#: caps them.
QUERY_TIMEOUT_S = 300.0
QUERY_MEMORY = "4GB"
QUERY_SPILL = "16GB"
QUERY_MAX_ROWS = 1_000_000
#: A ``--where`` predicate is evaluated in a child process that is killed at the timeout:
#: one DuckDB function call (``repeat('a', 2000000000)``) is not interruptible.
WHERE_GRACE_S = 3.0
#: Rows per batch a user query's answer streams in (the rows past the first are only
#: counted; a small batch would cost most of the time in per-batch overhead).
STREAM_BATCH_ROWS = 100_000


def query_bounds() -> tuple[float, str, int | None]:
    """(timeout s, memory limit, row cap of ``user_query`` or None) in force (environment,
    else the defaults)."""
    env = os.environ
    try:
        timeout = float(env.get("V2XLAKE_QUERY_TIMEOUT_S", QUERY_TIMEOUT_S))
    except ValueError:
        timeout = QUERY_TIMEOUT_S
    try:
        rows: int | None = int(env["V2XLAKE_QUERY_MAX_ROWS"])
    except (KeyError, ValueError):
        rows = None
    memory = env.get("V2XLAKE_QUERY_MEMORY", QUERY_MEMORY)
    if not re.fullmatch(r"\d+(\.\d+)?\s*[KMGT]i?B", memory):
        memory = QUERY_MEMORY
    return timeout, memory, rows


@dataclass
class QueryHead:
    """The first rows of a user query's answer and how many rows it has in all."""

    table: pa.Table
    total_rows: int

    @property
    def truncated(self) -> bool:
        return self.total_rows > self.table.num_rows


# the newlines: a trailing "-- comment" in the predicate cannot swallow the closing ")"
PREDICATE_WRAPPER = "SELECT clip_id FROM clips WHERE (\n{}\n)"
# expression classes a --where predicate may not contain (DuckDB's syntax tree names)
FORBIDDEN_CLASSES = {"SUBQUERY": "a subquery", "WINDOW": "a window function",
                     "STAR": "a star or COLUMNS(...)", "PARAMETER": "a parameter"}
# scalar functions whose value is not a function of the row (state, settings, variables)
FORBIDDEN_FUNCTIONS = frozenset({"getvariable", "current_setting", "getenv", "nextval",
                                 "currval", "setseed", "current_query", "query",
                                 "query_table", "current_database", "current_schema",
                                 "current_schemas"})


def _errno_of(e: BaseException) -> int:
    """The errno behind a DuckDB I/O error (DuckDB only gives the OS's text)."""
    text = str(e)
    for code, words in ((errno.EROFS, "Read-only file system"),
                        (errno.ENOSPC, "No space left"), (errno.EACCES, "Permission denied"),
                        (errno.EDQUOT, "quota exceeded")):
        if words in text:
            return code
    return errno.EIO


def _first_line(e: BaseException) -> str:
    return (str(e).splitlines() or [type(e).__name__])[0]


def _strip_locations(tree: Any) -> Any:
    """A syntax tree without source positions (two texts with the same structure compare
    equal)."""
    if isinstance(tree, dict):
        return {k: _strip_locations(v) for k, v in tree.items() if k != "query_location"}
    if isinstance(tree, list):
        return [_strip_locations(v) for v in tree]
    return tree


def _predicate_problem(tree: Any) -> str | None:
    """Why a WHERE clause's syntax tree is not a plain expression over one row of clips."""
    if isinstance(tree, list):
        return next((p for p in map(_predicate_problem, tree) if p), None)
    if not isinstance(tree, dict):
        return None
    cls = tree.get("class")
    if cls in FORBIDDEN_CLASSES:
        return f"{FORBIDDEN_CLASSES[cls]} is not allowed"
    if "node" in tree or "from_table" in tree or "subquery" in tree:
        return "a query inside the predicate is not allowed"
    if cls == "FUNCTION" and str(tree.get("function_name", "")).lower() in FORBIDDEN_FUNCTIONS:
        return f"function {tree['function_name']}() is not allowed"
    if cls == "FUNCTION" and (tree.get("schema") or tree.get("catalog")):
        return "qualified function names are not allowed"
    if cls == "COLUMN_REF":
        names = list(tree.get("column_names", []))
        if len(names) > 2 or (len(names) == 2 and names[0] != "clips"):
            return f"column {'.'.join(names)} is not a column of clips"
    return next((p for p in map(_predicate_problem, tree.values()) if p), None)


def duck_type(t: pa.DataType) -> str:
    """DuckDB type name of an Arrow type (for typed empty views)."""
    if pa.types.is_dictionary(t):
        return duck_type(t.value_type)
    if pa.types.is_list(t):
        return duck_type(t.value_type) + "[]"
    simple = {
        pa.string(): "VARCHAR", pa.large_string(): "VARCHAR", pa.bool_(): "BOOLEAN",
        pa.int8(): "TINYINT", pa.int16(): "SMALLINT", pa.int32(): "INTEGER",
        pa.int64(): "BIGINT", pa.uint8(): "UTINYINT", pa.uint16(): "USMALLINT",
        pa.uint32(): "UINTEGER", pa.uint64(): "UBIGINT", pa.float32(): "FLOAT",
        pa.float64(): "DOUBLE",
    }
    if t in simple:
        return simple[t]
    raise TypeError(f"no DuckDB type for {t}")


def _q(s: str) -> str:
    return "'" + s.replace("'", "''") + "'"


def _struct(cols: dict[str, str]) -> str:
    return "{" + ", ".join(f"{_q(k)}: {_q(v)}" for k, v in cols.items()) + "}"


@dataclass(frozen=True)
class ViewInfo:
    schema: str
    name: str
    zone: str  # raw | clean | manifests | quarantine | empty
    files: int
    sql: str
    deps: tuple[str, ...] = ()  # qualified views this one selects from (created first)
    # the files its SQL reads (explicit lists: the only files user SQL may open, #25)
    reads: tuple[str, ...] = ()

    @property
    def qualified(self) -> str:
        return f"{self.schema}.{self.name}"


def _real(path: str) -> bool:
    """Whether ``path`` (absolute, under the resolved lake root) is reached without a
    symlink: its real path is itself."""
    return os.path.realpath(path) == os.path.normpath(path)


def _scan(root: str, suffix: str = ".parquet", depth: int | None = None
          ) -> list[pafs.FileInfo]:
    """Visible ``*<suffix>`` files under a local folder, with size and mtime (what the
    lake's ``list_files`` shows: hidden names are writers' temporaries). Symlinks are never
    followed nor listed, and a root reached through one lists nothing: user SQL may read
    exactly these files (``Catalog._lock``), and a link inside a zone would lead out of the
    lake (``ln -s /etc <lake>/raw/evil``). ``depth``: only files that many folders down."""
    out: list[pafs.FileInfo] = []
    if not _real(root):
        return out
    todo = [(root, 0)]
    while todo:
        folder, level = todo.pop()
        try:
            entries = list(os.scandir(folder))
        except (FileNotFoundError, NotADirectoryError):
            continue
        for e in entries:
            if e.name.startswith(".") or e.is_symlink():
                continue
            if e.is_dir(follow_symlinks=False):
                if depth is None or level < depth:
                    todo.append((e.path, level + 1))
            elif (e.name.endswith(suffix) and e.is_file(follow_symlinks=False)
                  and (depth is None or level == depth)):
                st = e.stat(follow_symlinks=False)
                out.append(pafs.FileInfo(e.path, pafs.FileType.File, size=st.st_size,
                                         mtime_ns=st.st_mtime_ns))
    return out


def _base_tables(tree: Any, out: set[tuple[str, str]]) -> set[tuple[str, str]]:
    """(schema, table) of every table reference in a serialized syntax tree."""
    if isinstance(tree, dict):
        if tree.get("type") == "BASE_TABLE" and tree.get("table_name"):
            out.add((str(tree.get("schema_name") or "main").lower(),
                     str(tree["table_name"]).lower()))
        for v in tree.values():
            _base_tables(v, out)
    elif isinstance(tree, list):
        for v in tree:
            _base_tables(v, out)
    return out


class Catalog:
    """DuckDB over one lake. ``Catalog(lake).query("SELECT ...")`` -> ``pyarrow.Table``.

    The live connection is in memory (any number of processes can hold one). A view is
    created when a query first names it (``query``, ``user_query``: the names come from
    DuckDB's parser), over the files its table has at that moment; ``refresh()`` lists the
    lake again (new clips become visible to this instance) and, for local lakes unless
    ``read_only``, rewrites ``<root>/catalog.duckdb``, whose glob views see new files at once.
    """

    def __init__(self, lake: Lake, read_only: bool = False) -> None:
        self.lake = lake
        self.read_only = read_only
        self.con = duckdb.connect()
        if not lake.is_local:
            self._setup_s3(self.con)
        self._locked = False
        self._tmpdir: str | None = None  # the read-only copy of a locked-down catalog
        self._cleanup: weakref.finalize | None = None  # removes _tmpdir
        self._lockfile: str | None = None
        self._union = False  # a file of another schema was met: every table view unions
        self._bound: dict[str, ViewInfo] = {}  # views created on self.con, in creation order
        self._reset()
        if not self.read_only:
            self.write_snapshots()
            if self.lake.is_local:
                self._persist()

    def _reset(self) -> None:
        """Forget every listing and plan (the next view lists its table again)."""
        self._tables: dict[str, set[str]] = {}
        self._files: dict[tuple[str, str], list[pafs.FileInfo]] = {}
        self._planned: dict[tuple[str, bool], ViewInfo | None] = {}
        self._views: list[ViewInfo] | None = None
        self._snaps: dict[str, set[str]] = {}

    # ------------------------------------------------------------------ setup
    @staticmethod
    def _s3_settings() -> list[str]:
        endpoint = os.environ.get("AWS_ENDPOINT_URL") or os.environ.get("V2XLAKE_S3_ENDPOINT")
        out = [f"SET s3_region={_q(os.environ.get('AWS_REGION', 'us-east-1'))}"]
        if key := os.environ.get("AWS_ACCESS_KEY_ID"):
            out.append(f"SET s3_access_key_id={_q(key)}")
        if secret := os.environ.get("AWS_SECRET_ACCESS_KEY"):
            out.append(f"SET s3_secret_access_key={_q(secret)}")
        if endpoint:
            u = urlparse(endpoint)
            out += [f"SET s3_endpoint={_q(u.netloc or u.path)}", "SET s3_url_style='path'",
                    f"SET s3_use_ssl={'true' if u.scheme == 'https' else 'false'}"]
        return out

    def _setup_s3(self, con: duckdb.DuckDBPyConnection) -> None:
        import duckdb_ext  # ships httpfs for this exact duckdb version, offline

        duckdb_ext.init(con)
        con.execute("LOAD httpfs")
        for stmt in self._s3_settings():
            con.execute(stmt)

    # ------------------------------------------------------------------ views
    def _uri(self, path: str) -> str:
        return path if self.lake.is_local else f"s3://{path}"

    def _zone_tables(self, zone: str) -> set[str]:
        """Table folders that exist in a zone (one listing of the zone, remembered)."""
        if zone not in self._tables:
            self._tables[zone] = set(self.lake.tables(zone))
        return self._tables[zone]

    def _listing(self, zone: str, table: str) -> list[pafs.FileInfo]:
        """The table's visible Parquet files, by path (one recursive listing, remembered)."""
        key = (zone, table)
        if key not in self._files:
            infos: list[pafs.FileInfo] = []
            if table not in self._zone_tables(zone):
                pass
            elif self.lake.is_local:  # os.scandir: 3-4x faster than pyarrow's listing here
                infos = _scan(self.lake.table_dir(zone, table))
            else:
                sel = pafs.FileSelector(self.lake.table_dir(zone, table), recursive=True,
                                        allow_not_found=True)
                infos = [i for i in self.lake.fs.get_file_info(sel)
                         if i.type == pafs.FileType.File and i.path.endswith(".parquet")
                         and not i.base_name.startswith(".")]
            self._files[key] = sorted(infos, key=lambda i: i.path)
        return self._files[key]

    def _one_schema(self, infos: list[pafs.FileInfo]) -> bool:
        """Whether the first file (whose schema DuckDB takes without ``union_by_name``) has
        the newest file's schema: two footers instead of all of them. Files in between with
        fewer columns make the query fail, and it is re-run with ``union_by_name``
        (``_guarded``); columns only older files have are not the contract's any more."""
        import pyarrow.parquet as pq

        newest = max(infos, key=lambda i: (i.mtime_ns or 0, i.path))
        if newest.path == infos[0].path:
            return True
        a, b = (pq.read_schema(i.path, filesystem=self.lake.fs) for i in (infos[0], newest))
        return bool(a.equals(b))

    def _files_sql(self, infos: list[pafs.FileInfo]) -> str:
        """A SELECT over exactly these files (hive partition columns from their paths)."""
        src = "[" + ", ".join(_q(self._uri(i.path)) for i in infos) + "]"
        union = self._union or not self._one_schema(infos)
        return (f"SELECT * FROM read_parquet({src}, hive_partitioning=true, "
                f"hive_types_autocast=false{', union_by_name=true' if union else ''})")

    def _table_view(self, zone: str, table: str, glob: bool) -> ViewInfo:
        """``glob``: over ``<table>/**/*.parquet`` with ``union_by_name`` (catalog.duckdb,
        which must see files published later); else the table's snapshot (its rows from
        files unchanged since) and the files listed now that it does not hold."""
        infos = self._listing(zone, table)
        if infos:
            if glob:
                sql = (f"SELECT * FROM read_parquet({_q(self.lake.table_glob(zone, table))}, "
                       "hive_partitioning=true, hive_types_autocast=false, union_by_name=true)")
                return ViewInfo(zone, table, zone, len(infos), sql)
            parts, fresh, reads = [], infos, []
            snap = self._snapshot_use(zone, table, infos)
            if snap is not None:
                stale, fresh = snap
                where = (f" WHERE {SOURCE} NOT IN ({', '.join(map(_q, stale))})"
                         if stale else "")
                uri = self._uri(self._snapshot_path(zone, table))
                reads.append(uri)
                parts.append(f"SELECT * EXCLUDE ({SOURCE}) FROM read_parquet({_q(uri)}){where}")
            if fresh:
                parts.append(self._files_sql(fresh))
                reads.extend(self._uri(i.path) for i in fresh)
            return ViewInfo(zone, table, zone, len(infos), " UNION ALL BY NAME ".join(parts),
                            reads=tuple(reads))
        model = LAKE_TABLES.get(table) or EXTRA_SCHEMAS.get(table)
        if model is None:
            sql = "SELECT NULL AS clip_id WHERE false"
        else:
            cols = ", ".join(f"CAST(NULL AS {duck_type(f.type)}) AS {f.name}"
                             for f in arrow_schema(model))
            sql = f"SELECT {cols} WHERE false"
        return ViewInfo(zone, table, "empty", 0, sql)

    # ------------------------------------------------------------------ snapshots
    def _snapshot_path(self, zone: str, table: str) -> str:
        return self.lake.path(SNAPSHOT_DIR, zone, f"{table}.parquet")

    def _snapshot_tables(self, zone: str) -> set[str]:
        """Tables of a zone that have a snapshot (one listing, remembered)."""
        if zone not in self._snaps:
            folder = self.lake.path(SNAPSHOT_DIR, zone)
            self._snaps[zone] = {f.rpartition("/")[2].removesuffix(".parquet")
                                 for f in self.lake.list_files(folder, ".parquet")
                                 if f.count("/") == folder.count("/") + 1}
        return self._snaps[zone]

    def _snapshot_use(self, zone: str, table: str, infos: list[pafs.FileInfo]
                      ) -> tuple[list[str], list[pafs.FileInfo]] | None:
        """(sources to leave out of the snapshot, files to read directly) when the table has
        a usable snapshot: its rows are kept for each source file still there with the
        same size and modification time; a file changed or gone is left out (its rows
        filtered by ``_source``), a file the snapshot does not hold is read directly. None:
        no snapshot (or an unreadable one), read every file."""
        if table not in self._snapshot_tables(zone):
            return None
        if self.lake.is_local and not _real(self._snapshot_path(zone, table)):
            return None  # a symlink where the snapshot should be: read the files
        import pyarrow.parquet as pq

        try:
            meta = pq.read_metadata(self._snapshot_path(zone, table),
                                    filesystem=self.lake.fs).metadata or {}
            sources: dict[str, list[int]] = json.loads(meta[SNAPSHOT_KEY])
        except (OSError, KeyError, ValueError, pa.ArrowException):
            return None
        now = {self._rel(i.path): [i.size, i.mtime_ns] for i in infos}
        stale = sorted(p for p, sig in sources.items() if now.get(p) != sig)
        if len(stale) == len(sources):
            return None
        fresh = [i for i in infos if sources.get(self._rel(i.path)) != now[self._rel(i.path)]]
        return stale, fresh

    def _rel(self, path: str) -> str:
        return path[len(self.lake.base) + 1:]

    def write_snapshots(self, max_bytes: int = SNAPSHOT_MAX_BYTES,
                        min_files: int = SNAPSHOT_MIN_FILES) -> list[str]:
        """Write each table's snapshot anew where its files changed since the last one:
        one Parquet file ``_catalog/<zone>/<table>.parquet`` with every row of the table
        (partition columns included; rows in no particular order: ask with ORDER BY), the
        lake-relative path of the file each row came from (``_source``), and in its
        metadata the size and
        modification time of every file it holds. Tables larger than ``max_bytes`` (the
        point tables) or with fewer than ``min_files`` files (cheap to open one by one)
        get none. Returns the tables written.

        Why: a query's cost on a lake of many clips is the number of files it opens
        (~50-100 us each here, a GET each on S3), not rows; a snapshot turns thousands of
        small per-clip files into one. It is a cache, never the truth: readers check it
        against the listing they make anyway (``_snapshot_use``), so a snapshot that is
        stale, half-old or missing costs time, never a wrong answer, and writers publish
        clips exactly as before (no shared commit). Written atomically (``write_bytes``),
        so concurrent refreshes cannot corrupt it; the last one wins."""
        written = []
        tmpdir = tempfile.mkdtemp(prefix="v2xlake-snapshot-")
        con = duckdb.connect()
        try:
            con.execute("SET enable_progress_bar = false")
            if not self.lake.is_local:
                self._setup_s3(con)
            for zone in ("raw", "clean"):
                for table in sorted(self._zone_tables(zone)):
                    infos = self._listing(zone, table)
                    if (len(infos) < max(min_files, 1)
                            or sum(i.size or 0 for i in infos) > max_bytes):
                        continue
                    use = self._snapshot_use(zone, table, infos)
                    if use is not None and not use[0] and not use[1]:
                        continue  # current
                    if self._write_snapshot(con, zone, table, infos, use, tmpdir):
                        written.append(f"{zone}.{table}")
        finally:
            con.close()
            shutil.rmtree(tmpdir, ignore_errors=True)
        self._snaps = {}
        return written

    def _write_snapshot(self, con: duckdb.DuckDBPyConnection, zone: str, table: str,
                        infos: list[pafs.FileInfo],
                        use: tuple[list[str], list[pafs.FileInfo]] | None, tmpdir: str) -> bool:
        """One table's new snapshot: the last one's rows of files still unchanged (``use``)
        plus the rows of the files it lacks, so a refresh reads only what is new."""
        fresh = infos if use is None else use[1]
        sig = {self._rel(i.path): [i.size, i.mtime_ns] for i in infos}
        keep = set(sig) - {self._rel(i.path) for i in fresh}
        parts = []
        if use is not None and keep:
            stale = use[0]
            where = f" WHERE {SOURCE} NOT IN ({', '.join(map(_q, stale))})" if stale else ""
            uri = _q(self._uri(self._snapshot_path(zone, table)))
            parts.append(f"SELECT * FROM read_parquet({uri}){where}")
        if fresh:
            src = "[" + ", ".join(_q(self._uri(i.path)) for i in fresh) + "]"
            cut = len(self._uri(self.lake.base)) + 2  # 1-based start of the relative path
            parts.append(f"SELECT * EXCLUDE (filename), substr(filename, {cut}) AS {SOURCE} "
                         f"FROM read_parquet({src}, hive_partitioning=true, "
                         "hive_types_autocast=false, union_by_name=true, filename=true)")
        sources = json.dumps({p: sig[p] for p in sorted(keep | {self._rel(i.path)
                                                                 for i in fresh})},
                             separators=(",", ":"))
        tmp = os.path.join(tmpdir, f"{zone}-{table}.parquet")
        try:
            con.execute(f"COPY ({' UNION ALL BY NAME '.join(parts)}) TO {_q(tmp)} "
                        f"(FORMAT parquet, COMPRESSION zstd, "
                        f"KV_METADATA {{{SNAPSHOT_KEY.decode()}: {_q(sources)}}})")
        except duckdb.IOException:  # a file went away meanwhile: keep the last snapshot
            return False
        with open(tmp, "rb") as f:
            self.lake.write_bytes(self._snapshot_path(zone, table), f.read())
        os.remove(tmp)
        return True

    def _main_view(self, name: str, glob: bool) -> ViewInfo:
        """An unqualified DESIGN name: the clean table when it has files, else the raw one."""
        clean = self._view(f"clean.{name}", glob)
        raw = None if clean and clean.files else self._view(f"raw.{name}", glob)
        src = clean if clean and clean.files else raw if raw and raw.files else clean or raw
        assert src is not None
        zone = src.zone if src.files else "empty"
        sql = f"SELECT * FROM {src.schema}.{name}"
        deps: tuple[str, ...] = (src.qualified,)
        if name in JOINED and src.zone == "clean":
            other, keys, replaced = JOINED[name]
            if replaced is None:
                extra = [f.name for f in arrow_schema(LAKE_TABLES[other]) if f.name not in keys]
                cols = "t.*, " + ", ".join("j." + c for c in extra)
            else:
                cols = "t.* REPLACE (" + ", ".join(
                    f"COALESCE(j.{c}, t.{c}) AS {c}" for c in replaced) + ")"
            sql = (f"SELECT {cols} FROM clean.{name} t "
                   f"LEFT JOIN clean.{other} j USING ({', '.join(keys)})")
            deps += (f"clean.{other}",)
        return ViewInfo("main", name, zone, src.files, sql, deps)

    def _json_view(self, name: str, folder: str, pattern: str, cols: dict[str, str],
                   select: str, glob: bool = True) -> ViewInfo:
        """``glob``: over ``<folder><pattern>`` (catalog.duckdb: sees later files); else over
        the explicit list of the files matching it now (what a locked-down catalog may
        read: symlinks left out, ``_scan``)."""
        root = self.lake.path(folder)
        if self.lake.is_local:
            name_part = pattern.rpartition("/")[2]
            suffix = name_part.lstrip("*")
            files = [i.path for i in _scan(root, suffix, depth=pattern.count("/") - 1)
                     if name_part.startswith("*") or i.path.endswith("/" + name_part)]
        else:
            files = [f for f in self.lake.list_files(root, ".json")
                     if f[len(root):].count("/") == pattern.count("/")
                     and (pattern.endswith("/*.json") or f.endswith(pattern.rpartition("/")[2]))]
        if files:
            uris = [self._uri(f) for f in sorted(files)]
            src = (_q(self._uri(root) + pattern) if glob
                   else "[" + ", ".join(map(_q, uris)) + "]")
            sql = (f"SELECT {select} FROM read_json({src}, format='auto', "
                   f"columns={_struct(cols)})")
            return ViewInfo("main", name, folder, len(files), sql,
                            reads=() if glob else tuple(uris))
        empty = ", ".join(f"CAST(NULL AS {'VARCHAR' if t == 'JSON' else t}) AS {k}"
                          for k, t in cols.items())
        return ViewInfo("main", name, "empty", 0, f"SELECT {empty} WHERE false")

    def _names(self) -> list[str]:
        """Every qualified view name, each after the views it selects from."""
        tables = [f"{z}.{t}" for z in ("raw", "clean")
                  for t in sorted({*self._zone_tables(z), *LAKE_TABLES, *EXTRA_SCHEMAS}
                                  - {"manifests"})]
        return [*tables, *(f"main.{n}" for n in MAIN_NAMES), "main.manifests",
                "main.quarantine", "main.catalog_tables"]

    def _view(self, qualified: str, glob: bool = False) -> ViewInfo | None:
        """The plan of one view (None: no such name), listing only the tables it reads."""
        key = (qualified, glob)
        if key in self._planned:
            return self._planned[key]
        schema, _, name = qualified.partition(".")
        view: ViewInfo | None = None
        if schema in ("raw", "clean"):
            if name in ({*self._zone_tables(schema), *LAKE_TABLES, *EXTRA_SCHEMAS}
                        - {"manifests"}):
                view = self._table_view(schema, name, glob)
        elif schema == "main" and name in MAIN_NAMES:
            view = self._main_view(name, glob)
        elif qualified == "main.manifests":
            outputs = "CAST(outputs AS VARCHAR) AS outputs"
            mcols = ", ".join(k if k != "outputs" else outputs for k in MANIFEST_COLUMNS)
            view = self._json_view("manifests", "manifests", "/*/*.json", MANIFEST_COLUMNS,
                                   mcols, glob)
        elif qualified == "main.quarantine":
            view = self._json_view("quarantine", "quarantine", "/*/report.json",
                                   QUARANTINE_COLUMNS, ", ".join(QUARANTINE_COLUMNS), glob)
        elif qualified == "main.catalog_tables":
            rows = ", ".join(f"({_q(v.schema)}, {_q(v.name)}, {_q(v.zone)}, {v.files})"
                             for v in (self._view(n, glob) for n in self._names()[:-1])
                             if v is not None)
            view = ViewInfo("main", "catalog_tables", "catalog", 0,
                            f"SELECT * FROM (VALUES {rows}) t(schema, name, zone, files)")
        self._planned[key] = view
        return view

    def _plan(self, glob: bool = False) -> list[ViewInfo]:
        """Every view (lists every table of the lake)."""
        return [v for v in (self._view(n, glob) for n in self._names()) if v is not None]

    @property
    def views(self) -> list[ViewInfo]:
        """Every view of the catalog (planned on first use: this lists every table)."""
        if self._views is None:
            self._views = self._plan()
        return self._views

    def _closure(self, names: Iterable[str]) -> list[ViewInfo]:
        """The views named (qualified; unknown names are skipped) and the views they read,
        each after its dependencies."""
        out: dict[str, ViewInfo] = {}

        def visit(qualified: str) -> None:
            view = self._view(qualified)
            if view is None or qualified in out:
                return
            for dep in view.deps:
                visit(dep)
            out[qualified] = view

        for n in names:
            visit(n)
        return list(out.values())

    def _ensure(self, names: Iterable[str] | None) -> None:
        """Create the views that ``names`` (qualified; None: every view) need and this
        connection lacks. On a locked-down catalog the read-only database is rebuilt with
        them (``_lock``): the names only select among the catalog's own planned views."""
        wanted = self._closure(self._names() if names is None else names)
        missing = [v for v in wanted if v.qualified not in self._bound]
        if not missing:
            return
        if self._locked:
            self._lock([*self._bound.values(), *missing])
        else:
            self._apply(self.con, missing)
            self._bound.update((v.qualified, v) for v in missing)

    def _references(self, sql: str) -> set[str] | None:
        """Qualified names of the tables a statement reads, from DuckDB's parser alone
        (``json_serialize_sql``: nothing is bound or run); None when it cannot say (not a
        SELECT, a syntax error)."""
        try:
            row = self.con.execute("SELECT json_serialize_sql(?)", [sql]).fetchone()
        except duckdb.Error:
            return None
        tree = json.loads(row[0]) if row else {"error": True}
        if tree.get("error"):
            return None
        return {f"{schema}.{name}" for schema, name in _base_tables(tree["statements"], set())}

    def _rebind(self) -> None:
        """Plan every created view again and recreate them (after ``_reset`` or a schema
        change), dependencies first."""
        self._planned = {}
        views = self._closure(list(self._bound))
        if self._locked:
            self._lock(views)
        else:
            self._apply(self.con, views)
            self._bound = {v.qualified: v for v in views}

    def _guarded(self, run: Callable[[], pa.Table]) -> pa.Table:
        """Run; a table whose files do not all share the first file's schema fails with
        DuckDB's "schema mismatch": recreate every view with ``union_by_name`` and re-run."""
        try:
            return run()
        except duckdb.Error as e:
            if self._union or "schema mismatch" not in str(e):
                raise
        self._union = True
        self._rebind()
        return run()

    def _apply(self, con: duckdb.DuckDBPyConnection, views: list[ViewInfo]) -> None:
        con.execute("BEGIN TRANSACTION")  # one commit (a file database syncs per commit)
        try:
            con.execute("CREATE SCHEMA IF NOT EXISTS raw")
            con.execute("CREATE SCHEMA IF NOT EXISTS clean")
            for v in views:
                con.execute(f'CREATE OR REPLACE VIEW {v.schema}."{v.name}" AS {v.sql}')
        except BaseException:
            con.execute("ROLLBACK")
            raise
        con.execute("COMMIT")

    def refresh(self) -> dict[str, str]:
        """List the lake again: the views created so far are rebuilt over today's files,
        catalog.duckdb is rewritten (local, not ``read_only``); returns {main view name:
        backing zone}."""
        self._reset()
        if not self.read_only:
            self.write_snapshots()
            if self.lake.is_local:
                self._persist()
        self._rebind()
        return self.zones

    def _persist(self) -> None:
        """Write the same views into ``catalog.duckdb`` via a temporary file + atomic rename,
        with file paths relative to the lake root so that a copied or moved lake reads its
        own files: ``cd <lake> && duckdb catalog.duckdb`` (or ``SET file_search_path`` to the
        lake root from anywhere); ``v2xlake catalog refresh`` rewrites it."""
        final = self.lake.catalog_path
        # the owner tag: a refresh killed half-way leaves a file the next sweep removes
        tmp = f"{os.path.dirname(final)}/.catalog-{run_tag()}-{uuid.uuid4().hex}.duckdb"
        root = _q(self.lake.base + "/")[:-1]  # the quoted literal's opening: '<root>/
        travelling = [ViewInfo(v.schema, v.name, v.zone, v.files, v.sql.replace(root, "'"))
                      for v in self._plan(glob=True)]
        try:
            with self.lake.writing(final):
                try:
                    con = duckdb.connect(tmp)
                except duckdb.IOException as e:  # read-only lake, disk full: say which
                    raise OSError(_errno_of(e), str(e)) from e
                try:
                    con.execute(f"SET file_search_path = {_q(self.lake.base)}")  # to bind them
                    self._apply(con, travelling)
                finally:
                    con.close()
                os.replace(tmp, final)
        finally:
            for p in (tmp, tmp + ".wal"):
                with contextlib.suppress(OSError):
                    os.remove(p)

    @property
    def zones(self) -> dict[str, str]:
        return {v.name: v.zone for v in self.views if v.schema == "main"}

    def zone_of(self, name: str) -> str:
        return self.zones[name]

    # ------------------------------------------------------------------ queries
    def query(self, sql: str, params: list[object] | None = None) -> pa.Table:
        """Trusted SQL (the project's own); user text goes through ``user_query``. Creates
        the views it names first (every view when the parser cannot say which)."""
        self._ensure(self._references(sql))
        return self._guarded(lambda: self.con.execute(sql, params or []).fetch_arrow_table())

    def lock_down(self) -> None:
        """Make this catalog safe for user SQL, for good: its connection becomes a READ-ONLY
        one (the same views, in a private database file opened with ``read_only=True``) that
        may read the lake's own files and nothing else — no other file, no network, no
        ATTACH, no extension install or load — and whose settings cannot be changed back.

        Why a file: an in-memory database is always writable, so a statement-type check
        would be the only guard; a read-only database refuses CREATE / INSERT / COPY FROM
        by itself. The file lives in a private temporary folder (never in the lake, which
        may itself be read-only) and is removed by ``close``. Why ``allowed_directories``
        before ``enable_external_access = false``: with external access off DuckDB reads
        no file at all, views over the lake included (NOTES.md "DuckDB as a read-only
        surface"); the folders its views read (``QUERY_READABLE``: not ``landing/``) are
        the only ones it may still read."""
        if self._locked:
            return
        self._tmpdir = tempfile.mkdtemp(prefix="v2xlake-catalog-")
        # a catalog dropped without close() (or an interpreter ending) still removes it
        self._cleanup = weakref.finalize(self, shutil.rmtree, self._tmpdir, True)
        self._lock(list(self._bound.values()))

    def _lock(self, views: list[ViewInfo]) -> None:
        """(Re)build the private read-only database with ``views`` (only ever the catalog's
        own planned views: user text never reaches this writable connection), reopen it
        read-only and locked, and swap it in for the current connection."""
        assert self._tmpdir is not None
        path = os.path.join(self._tmpdir, f"catalog-{uuid.uuid4().hex[:8]}.duckdb")
        build = duckdb.connect(path)
        try:
            if not self.lake.is_local:
                self._setup_s3(build)  # creating a view binds it: s3:// needs httpfs
            self._apply(build, views)
        finally:
            build.close()
        con = duckdb.connect(path, read_only=True)
        if not self.lake.is_local:
            self._setup_s3(con)
        if self.lake.is_local:
            # exactly the files the views read, from listings that leave symlinks out:
            # DuckDB's allowed_directories is a text prefix that follows links (#25)
            files = sorted({f for v in views for f in v.reads})
            allow = f"SET allowed_paths = [{', '.join(map(_q, files))}]"
        else:  # no links on S3: the folders the views read
            readable = ", ".join(_q(self._uri(self.lake.path(zone)) + "/")
                                 for zone in QUERY_READABLE)
            allow = f"SET allowed_directories = [{readable}]"
        _, memory, _ = query_bounds()
        for stmt in (allow,
                     f"SET memory_limit = {_q(memory)}",
                     f"SET max_temp_directory_size = {_q(QUERY_SPILL)}",
                     "SET enable_progress_bar = false",
                     f"SET temp_directory = {_q(os.path.join(self._tmpdir, 'spill'))}",
                     "SET autoinstall_known_extensions = false",
                     "SET autoload_known_extensions = false",
                     "SET enable_external_access = false",
                     "SET lock_configuration = true"):
            con.execute(stmt)
        self.con.close()
        self.con = con
        if self._lockfile is not None:
            for p in (self._lockfile, self._lockfile + ".wal"):
                with contextlib.suppress(OSError):
                    os.remove(p)
        self._lockfile = path
        self._bound = {v.qualified: v for v in views}
        self._locked = True

    @property
    def locked(self) -> bool:
        return self._locked

    def _one_select(self, sql: str, what: str) -> duckdb.Statement:
        try:
            statements = self.con.extract_statements(sql)
        except duckdb.Error as e:
            raise QueryRefused(f"cannot parse the {what}: {_first_line(e)}") from e
        if len(statements) != 1:
            raise QueryRefused(f"exactly one statement, please (got {len(statements)})")
        kind = statements[0].type
        if kind.name != "SELECT":
            raise QueryRefused(f"only SELECT queries are allowed here (got {kind.name})")
        return statements[0]

    @contextlib.contextmanager
    def _deadline(self, timeout_s: float | None = None) -> Any:
        """Interrupt this connection's statement when it runs past ``timeout_s`` (the
        statement timeout of user SQL); what it raises then is a ``QueryTimeout``. DuckDB
        checks for an interrupt between chunks of rows: a single function call that runs
        long is not stopped (``select_clips`` and the CLI bound those harder)."""
        limit = query_bounds()[0] if timeout_s is None else timeout_s
        fired = threading.Event()

        def stop() -> None:
            fired.set()
            self.con.interrupt()

        timer = threading.Timer(limit, stop)
        timer.daemon = True
        timer.start()
        try:
            yield
        except Exception as e:
            if fired.is_set():
                raise QueryTimeout(f"query stopped after {limit:g} s (statement timeout; "
                                   "V2XLAKE_QUERY_TIMEOUT_S)") from None
            if "duckdb" in type(e).__module__ and "memory" in str(e).lower():
                raise QueryRefused(f"query refused: {_first_line(e)} (memory limit "
                                   f"{query_bounds()[1]}; V2XLAKE_QUERY_MEMORY)") from None
            raise
        finally:
            timer.cancel()

    def user_query(self, sql: str, max_rows: int | None = None) -> pa.Table:
        """One SELECT statement of user text on the locked-down, read-only connection
        (``lock_down``): COPY, ATTACH, INSTALL, PRAGMA, SET, a second statement... are
        refused before anything runs, and the connection could not do them anyway. Bounded:
        a statement timeout and DuckDB's memory limit; with ``max_rows`` (or
        ``V2XLAKE_QUERY_MAX_ROWS``) at most that many rows are fetched, else
        ``QueryRefused`` (add a LIMIT, or aggregate)."""
        cap = query_bounds()[2] if max_rows is None else max_rows
        if cap is None:
            self.lock_down()
            self._one_select(sql, "query")  # refused before any view is built
            self._ensure(self._references(sql))
            with self._deadline():
                return self._guarded(lambda: self.con.execute(
                    self._one_select(sql, "query")).fetch_arrow_table())
        head = self.user_query_head(sql, cap + 1, count_rest=False)
        if head.table.num_rows > cap:
            raise QueryRefused(f"the query returns more than {cap:,} rows: add a LIMIT or "
                               "aggregate (V2XLAKE_QUERY_MAX_ROWS)")
        return head.table

    def user_query_head(self, sql: str, max_rows: int, count_rest: bool = True,
                        timeout_s: float | None = None) -> QueryHead:
        """The first ``max_rows`` rows of a user query (``user_query``'s checks and bounds),
        streamed: no more than those rows (and one batch) are ever held; with
        ``count_rest`` the remaining rows are counted as they stream past."""
        self.lock_down()
        self._one_select(sql, "query")  # refused before any view is built
        self._ensure(self._references(sql))

        def run() -> QueryHead:  # the statement of the connection it runs on
            result = self.con.execute(self._one_select(sql, "query"))
            reader = result.fetch_record_batch(STREAM_BATCH_ROWS)
            batches, n = [], 0
            for batch in reader:
                if n < max_rows:
                    batches.append(batch.slice(0, max_rows - n))
                n += batch.num_rows
                if n >= max_rows and not count_rest:
                    break
            table = pa.Table.from_batches(batches, schema=reader.schema)
            return QueryHead(table, n)

        with self._deadline(timeout_s):
            return self._guarded(run)

    def parse_predicate(self, where: str) -> duckdb.Statement:
        """The statement ``SELECT clip_id FROM clips WHERE (<where>)``, once it is proven
        to be exactly that: DuckDB's own parser (``json_serialize_sql``) gives its syntax
        tree, which must equal the tree of ``... WHERE (true)`` everywhere but the WHERE
        clause (no UNION, ORDER, LIMIT, GROUP BY, CTE, other table: a ``)`` in the text
        cannot escape), and the WHERE clause may not hold a subquery (``IN (SELECT ...)``,
        ``EXISTS (TABLE raw.ins)``), a window, a star, a parameter, a column of another
        table or a function that reads state outside the row. Text is never pasted into
        SQL that runs without this check."""
        self.lock_down()
        self._ensure(["main.clips"])  # before the statement: it belongs to one connection
        wrapped = PREDICATE_WRAPPER.format(where)
        statement = self._one_select(wrapped, "--where predicate")
        tree = self._syntax_tree(wrapped)
        if tree.get("error"):
            raise QueryRefused(f"--where is not one SQL expression: "
                               f"{tree.get('error_message', 'parse error')}")
        (node,) = [s["node"] for s in tree["statements"]]
        predicate = node.pop("where_clause", None)
        reference = self._syntax_tree(PREDICATE_WRAPPER.format("true"))["statements"][0]["node"]
        reference.pop("where_clause", None)
        if predicate is None or _strip_locations(node) != _strip_locations(reference):
            raise QueryRefused(f"--where must be one boolean expression over clips columns: "
                               f"{where[:200]!r}")
        if problem := _predicate_problem(predicate):
            raise QueryRefused(f"--where {where[:200]!r}: {problem}; it must be one boolean "
                               "expression over clips columns, without subqueries")
        return statement

    def _syntax_tree(self, sql: str) -> dict[str, Any]:
        row = self.con.execute("SELECT json_serialize_sql(?)", [sql]).fetchone()
        assert row is not None
        tree: dict[str, Any] = json.loads(row[0])
        return tree

    def select_clips(self, where: str, columns: Sequence[str]) -> pa.Table:
        """Rows of ``clips`` (status ok) matching a user predicate (``parse_predicate``),
        ordered by clip id. The predicate runs as the parsed statement on the read-only
        connection; the columns and the status filter are the project's own."""
        self.parse_predicate(where)  # refused here, at once, before any child starts
        ids = predicate_ids(self.lake, where)
        cols = ", ".join('"' + c.replace('"', '""') + '"' for c in columns)
        return self.con.execute(
            f"SELECT {cols} FROM clips WHERE status = 'ok' AND list_contains(?, clip_id) "
            "ORDER BY clip_id", [ids]).fetch_arrow_table()

    def close(self) -> None:
        self.con.close()
        if self._cleanup is not None:
            self._cleanup()  # removes the read-only copy's folder, once
            self._cleanup = None
            self._tmpdir = None

    def __enter__(self) -> Catalog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# ---------------------------------------------------------------- --where in a child process
def _where_child() -> None:
    """The child of ``predicate_ids``: lake URI and predicate as JSON on stdin, the matching
    clip ids (or the refusal) as JSON on stdout."""
    args = json.loads(sys.stdin.read())
    out: dict[str, Any]
    try:
        with Catalog(Lake(args["lake"], create=False), read_only=True) as cat:
            statement = cat.parse_predicate(args["where"])
            try:
                with cat._deadline(args["timeout"]):
                    ids = [r[0] for r in cat.con.execute(statement).fetchall()]
            except duckdb.Error as e:
                raise QueryRefused(f"--where {args['where']!r}: {_first_line(e)}") from e
        out = {"ids": ids}
    except QueryRefused as e:
        out = {"refused": str(e), "timeout": isinstance(e, QueryTimeout)}
    sys.stdout.write(json.dumps(out))


def predicate_ids(lake: Lake, where: str, timeout_s: float | None = None) -> list[str]:
    """Clip ids whose ``clips`` row matches a user predicate (``Catalog.parse_predicate``),
    evaluated in a child process under the statement timeout and DuckDB's memory limit, and
    killed ``WHERE_GRACE_S`` later if it still runs: one call of a function DuckDB cannot
    interrupt (``length(repeat('a', 2000000000)) > 0`` ran six minutes) ends there."""
    limit = query_bounds()[0] if timeout_s is None else timeout_s
    code = "from v2xlake.storage.catalog import _where_child; _where_child()"
    try:
        # the child's private database goes to a folder this process removes: a child killed
        # at the deadline cannot remove its own
        with tempfile.TemporaryDirectory(prefix="v2xlake-where-") as tmp:
            done = subprocess.run(
                [sys.executable, "-c", code], capture_output=True, text=True,
                input=json.dumps({"lake": lake.uri, "where": where, "timeout": limit}),
                timeout=limit + WHERE_GRACE_S, env={**os.environ, "TMPDIR": tmp})
    except subprocess.TimeoutExpired:
        raise QueryTimeout(f"--where {where[:200]!r}: stopped after {limit:g} s (statement "
                           "timeout; V2XLAKE_QUERY_TIMEOUT_S)") from None
    try:
        out = json.loads(done.stdout)
    except ValueError:
        raise QueryRefused(f"--where {where[:200]!r}: its evaluation failed (exit "
                           f"{done.returncode}): {done.stderr.strip()[-300:]}") from None
    if "refused" in out:
        raise (QueryTimeout if out.get("timeout") else QueryRefused)(out["refused"])
    return [str(i) for i in out["ids"]]
