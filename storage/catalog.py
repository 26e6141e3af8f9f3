"""The DuckDB catalog: every lake table as SQL, straight over the Parquet files.

Why views over hive-partitioned Parquet and not DuckLake (full reasoning in
``docs/architecture-catalog.md``): each clip's stage writes its own files with an atomic rename
(or a single S3 PUT), so there is no shared commit that concurrent writers could lose; a view's
glob is evaluated at query time, so a clip becomes visible the moment its files land, with no
catalog write at all. A ``catalog.duckdb`` file holding the same views is (re)written by
``refresh()`` for external tools (the ``duckdb`` CLI, BI tools); it is replaced atomically,
so two processes refreshing at once cannot corrupt it.

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
import shutil
import tempfile
import uuid
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any
from urllib.parse import urlparse

import duckdb
import pyarrow as pa

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
MANIFEST_COLUMNS = {
    "clip_id": "VARCHAR", "stage": "VARCHAR", "status": "VARCHAR", "code_version": "VARCHAR",
    "params_hash": "VARCHAR", "inputs_hash": "VARCHAR", "outputs": "JSON", "error": "VARCHAR",
    "recorded_at": "VARCHAR",
}
QUARANTINE_COLUMNS = {"clip_id": "VARCHAR", "stage": "VARCHAR", "reason": "VARCHAR",
                      "quarantined_at": "VARCHAR"}


class QueryRefused(ValueError):
    """User SQL that is not allowed (not one SELECT, not one expression, not the lake's)."""


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


class Catalog:
    """DuckDB over one lake. ``Catalog(lake).query("SELECT ...")`` -> ``pyarrow.Table``.

    The live connection is in memory (any number of processes can hold one); ``refresh()``
    re-scans which tables exist and, for local lakes unless ``read_only``, rewrites
    ``<root>/catalog.duckdb``. Call ``refresh()`` after a table appears for the first time
    (new files of an existing table are visible without it).
    """

    def __init__(self, lake: Lake, read_only: bool = False) -> None:
        self.lake = lake
        self.read_only = read_only
        self.con = duckdb.connect()
        if not lake.is_local:
            self._setup_s3(self.con)
        self.views: list[ViewInfo] = []
        self._locked = False
        self._tmpdir: str | None = None  # the read-only copy of a locked-down catalog
        self.refresh()

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

    def _table_view(self, zone: str, table: str) -> ViewInfo:
        files = self.lake.list_files(self.lake.table_dir(zone, table), ".parquet")
        if files:
            sql = (f"SELECT * FROM read_parquet({_q(self.lake.table_glob(zone, table))}, "
                   "hive_partitioning=true, hive_types_autocast=false, union_by_name=true)")
            return ViewInfo(zone, table, zone, len(files), sql)
        model = LAKE_TABLES.get(table) or EXTRA_SCHEMAS.get(table)
        if model is None:
            sql = "SELECT NULL AS clip_id WHERE false"
        else:
            cols = ", ".join(f"CAST(NULL AS {duck_type(f.type)}) AS {f.name}"
                             for f in arrow_schema(model))
            sql = f"SELECT {cols} WHERE false"
        return ViewInfo(zone, table, "empty", 0, sql)

    def _json_view(self, name: str, folder: str, pattern: str, cols: dict[str, str],
                   select: str) -> ViewInfo:
        files = self.lake.list_files(self.lake.path(folder), ".json")
        if files:
            glob = self._uri(self.lake.path(folder)) + pattern
            sql = (f"SELECT {select} FROM read_json({_q(glob)}, format='auto', "
                   f"columns={_struct(cols)})")
            return ViewInfo("main", name, folder, len(files), sql)
        empty = ", ".join(f"CAST(NULL AS {'VARCHAR' if t == 'JSON' else t}) AS {k}"
                          for k, t in cols.items())
        return ViewInfo("main", name, "empty", 0, f"SELECT {empty} WHERE false")

    def _plan(self) -> list[ViewInfo]:
        views: list[ViewInfo] = []
        by_zone: dict[str, dict[str, ViewInfo]] = {}
        for zone in ("raw", "clean"):
            names = sorted({*self.lake.tables(zone), *LAKE_TABLES, *EXTRA_SCHEMAS}
                           - {"manifests"})
            by_zone[zone] = {t: self._table_view(zone, t) for t in names}
            views.extend(by_zone[zone].values())
        for name in MAIN_NAMES:
            clean, raw = by_zone["clean"].get(name), by_zone["raw"].get(name)
            src = clean if clean and clean.files else raw if raw and raw.files else clean or raw
            assert src is not None
            zone = src.zone if src.files else "empty"
            sql = f"SELECT * FROM {src.schema}.{name}"
            if name in JOINED and src.zone == "clean":
                other, keys, replaced = JOINED[name]
                if replaced is None:
                    extra = [f.name for f in arrow_schema(LAKE_TABLES[other])
                             if f.name not in keys]
                    cols = "t.*, " + ", ".join("j." + c for c in extra)
                else:
                    cols = "t.* REPLACE (" + ", ".join(
                        f"COALESCE(j.{c}, t.{c}) AS {c}" for c in replaced) + ")"
                sql = (f"SELECT {cols} FROM clean.{name} t "
                       f"LEFT JOIN clean.{other} j USING ({', '.join(keys)})")
            views.append(ViewInfo("main", name, zone, src.files, sql))
        outputs = "CAST(outputs AS VARCHAR) AS outputs"
        mcols = ", ".join(k if k != "outputs" else outputs for k in MANIFEST_COLUMNS)
        views.append(self._json_view("manifests", "manifests", "/*/*.json", MANIFEST_COLUMNS,
                                     mcols))
        views.append(self._json_view("quarantine", "quarantine", "/*/report.json",
                                     QUARANTINE_COLUMNS, ", ".join(QUARANTINE_COLUMNS)))
        rows = ", ".join(f"({_q(v.schema)}, {_q(v.name)}, {_q(v.zone)}, {v.files})"
                         for v in views)
        views.append(ViewInfo("main", "catalog_tables", "catalog", 0,
                              f"SELECT * FROM (VALUES {rows}) t(schema, name, zone, files)"))
        return views

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
        """Re-scan the lake and rebuild every view; returns {main view name: backing zone}."""
        self.views = self._plan()
        self._apply(self.con, self.views)
        if self.lake.is_local and not self.read_only:
            self._persist()
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
                      for v in self.views]
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
        """Trusted SQL (the project's own); user text goes through ``user_query``."""
        return self.con.execute(sql, params or []).fetch_arrow_table()

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
        surface"); the lake root is the one folder it may still read."""
        if self._locked:
            return
        self._tmpdir = tempfile.mkdtemp(prefix="v2xlake-catalog-")
        path = os.path.join(self._tmpdir, "catalog.duckdb")
        build = duckdb.connect(path)
        try:
            if not self.lake.is_local:
                self._setup_s3(build)  # creating a view binds it: s3:// needs httpfs
            self._apply(build, self.views)
        finally:
            build.close()
        con = duckdb.connect(path, read_only=True)
        if not self.lake.is_local:
            self._setup_s3(con)
        root = self.lake.base if self.lake.is_local else f"s3://{self.lake.base}"
        for stmt in (f"SET allowed_directories = [{_q(root + '/')}]",
                     f"SET temp_directory = {_q(os.path.join(self._tmpdir, 'spill'))}",
                     "SET autoinstall_known_extensions = false",
                     "SET autoload_known_extensions = false",
                     "SET enable_external_access = false",
                     "SET lock_configuration = true"):
            con.execute(stmt)
        self.con.close()
        self.con = con
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

    def user_query(self, sql: str) -> pa.Table:
        """One SELECT statement of user text on the locked-down, read-only connection
        (``lock_down``): COPY, ATTACH, INSTALL, PRAGMA, SET, a second statement... are
        refused before anything runs, and the connection could not do them anyway."""
        self.lock_down()
        statement = self._one_select(sql, "query")
        return self.con.execute(statement).fetch_arrow_table()

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
                               f"{where!r}")
        if problem := _predicate_problem(predicate):
            raise QueryRefused(f"--where {where!r}: {problem}; it must be one boolean "
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
        statement = self.parse_predicate(where)
        try:
            ids = [r[0] for r in self.con.execute(statement).fetchall()]
        except duckdb.Error as e:
            raise QueryRefused(f"--where {where!r}: {_first_line(e)}") from e
        cols = ", ".join('"' + c.replace('"', '""') + '"' for c in columns)
        return self.con.execute(
            f"SELECT {cols} FROM clips WHERE status = 'ok' AND list_contains(?, clip_id) "
            "ORDER BY clip_id", [ids]).fetch_arrow_table()

    def close(self) -> None:
        self.con.close()
        if self._tmpdir is not None:
            shutil.rmtree(self._tmpdir, ignore_errors=True)
            self._tmpdir = None

    def __enter__(self) -> Catalog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
