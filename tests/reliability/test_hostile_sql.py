"""#16, critical: user text (SQL, --where predicates, the clip ids a query returns) never
reaches a writable connection or a path outside the lake. Each case is one an attacker or a
careless user tried; each failed before this suite existed."""

from __future__ import annotations

from pathlib import Path

import pytest
import test_flows_fakestages as fakes

from v2xlake.flows.bookkeeping import refresh_catalog, user_query
from v2xlake.flows.cli import main
from v2xlake.flows.release import build_release
from v2xlake.storage.catalog import QueryRefused
from v2xlake.storage.lake import Lake, checked_clip_id


@pytest.fixture(scope="module")
def lake(tmp_path_factory: pytest.TempPathFactory) -> Lake:
    """One lake for the module: every case here must leave it as it was (each checks)."""
    tmp_path = tmp_path_factory.mktemp("hostile")
    lake = Lake(tmp_path / "lake")
    for i, w in enumerate(("clear", "rain")):
        rep = fakes.fake_ingest(lake, fakes.make_fake_clip(tmp_path / "in", f"c{i}", weather=w))
        fakes.fake_annotate(lake, rep.clip_id)
    # raw zone secrets a release must never contain
    lake.write_bytes(lake.path("raw", "blobs", "c0", "red", "CAM", "000000.png"), b"FACE")
    refresh_catalog(lake)
    return lake


HOSTILE_QUERIES = [
    "COPY (SELECT 1) TO '{tmp}/pwned.csv'",
    "SELECT 1; COPY (SELECT 1) TO '{tmp}/pwned.csv'",
    "SELECT * FROM read_csv('/etc/passwd')",
    "SELECT * FROM read_text('/etc/hostname')",
    "SELECT * FROM read_parquet('{tmp}/other/*.parquet')",
    "ATTACH '{tmp}/evil.duckdb' AS evil",
    "INSTALL httpfs",
    "LOAD httpfs",
    "SET enable_external_access = true",
    "PRAGMA enable_profiling",
    "CREATE TABLE t AS SELECT 1",
    "COPY (SELECT 'x' AS clip_id) TO '{lake}/clean/clips/clip_id=forged/part.parquet'",
    "SELECT * FROM read_parquet('{lake}/../outside.parquet')",
    # a table function that runs SQL text: only a SELECT, and on a read-only database
    "SELECT * FROM query('COPY (SELECT 1) TO ''{lake}/clean/clips/clip_id=forged/p.parquet''')",
    "SELECT * FROM query('CREATE TABLE t AS SELECT 1')",
    "SELECT getenv('HOME')",
    "SELECT * FROM glob('{tmp}/*')",
    "SELECT * FROM read_text('/proc/self/environ')",
    "DETACH memory",
    "USE raw",
    "CALL pragma_version()",
    "EXPLAIN ANALYZE SELECT 1",
]


@pytest.mark.parametrize("sql", HOSTILE_QUERIES)
def test_query_is_read_only_and_lake_only(lake: Lake, tmp_path: Path, sql: str) -> None:
    (tmp_path / "other").mkdir(exist_ok=True)
    text = sql.format(tmp=tmp_path, lake=lake.base)
    with pytest.raises(Exception) as ei:
        user_query(lake, text)
    assert isinstance(ei.value, QueryRefused) or "duckdb" in type(ei.value).__module__
    assert not (tmp_path / "pwned.csv").exists() and not (tmp_path / "evil.duckdb").exists()
    assert not Path(lake.path("clean", "clips", "clip_id=forged")).exists()
    ids = user_query(lake, "SELECT clip_id FROM clips ORDER BY 1").column(0).to_pylist()
    assert ids == ["c0", "c1"]  # nothing forged; the lake's own views still answer


def test_user_sql_runs_on_a_read_only_database(lake: Lake) -> None:
    from v2xlake.storage.catalog import Catalog

    with Catalog(lake, read_only=True) as cat:
        cat.lock_down()
        assert cat.con.execute("SELECT current_setting('access_mode')").fetchone() == (
            "read_only",)
        with pytest.raises(Exception, match="read-only"):
            cat.con.execute("CREATE VIEW v AS SELECT 1")  # even the trusted side cannot
        with pytest.raises(Exception, match="lock"):
            cat.con.execute("SET enable_external_access = true")
        tmpdir = cat._tmpdir
        assert tmpdir and not tmpdir.startswith(lake.base)  # the copy is never in the lake
        assert cat.user_query("SELECT count(*) AS n FROM clips").to_pylist() == [{"n": 2}]
    assert not Path(tmpdir).exists()  # removed on close


def test_query_cli_refuses_with_one_line(lake: Lake, tmp_path: Path,
                                        capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["query", f"COPY (SELECT 1) TO '{tmp_path}/x.csv'", "--lake", lake.uri]) == 2
    err = capsys.readouterr().err
    assert "only SELECT" in err and "Traceback" not in err
    assert not (tmp_path / "x.csv").exists()


HOSTILE_WHERE = [
    "1=0) UNION SELECT '../../raw','x','clear','day' --",
    "true; COPY (SELECT 1) TO '/tmp/pwned_where.csv'",
    "clip_id IN (SELECT clip_id FROM raw.ins)",
    "clip_id = (SELECT '../../raw')",
    "length(read_text('/etc/passwd')) > 0",
    # subqueries without SELECT or FROM: TABLE, VALUES, SUMMARIZE, PIVOT
    "EXISTS (TABLE raw.ins)",
    "clip_id IN (VALUES ('c0'))",
    "clip_id = ANY((VALUES ('c0')))",
    "clip_id IN (SUMMARIZE raw.ins)",
    "(PIVOT clips ON weather) IS NULL",
    "clip_id IN (FROM raw.ins SELECT clip_id)",
    # not one expression over one row of clips
    "true ORDER BY 1",
    "true GROUP BY clip_id",
    "true) UNION (SELECT '../../raw'",
    "true LIMIT 1",
    "COLUMNS(*) IS NOT NULL",
    "row_number() OVER () = 1",
    "clip_id = $1",
    "clip_id = getvariable('x')",
    "current_setting('allowed_directories') IS NOT NULL",
    "raw.clips.weather = 'rain'",
    "weather = 'rain' /* unclosed",
]


@pytest.mark.parametrize("where", HOSTILE_WHERE)
def test_release_where_is_one_expression_over_clips(lake: Lake, where: str) -> None:
    with pytest.raises(Exception) as ei:
        build_release(lake.uri, "evil", where, ["lake"], 0, (0.7, 0.15, 0.15))
    assert isinstance(ei.value, ValueError | QueryRefused) or \
        "duckdb" in type(ei.value).__module__, repr(ei.value)
    assert not Path(lake.path("releases", "evil")).exists()
    assert not Path("/tmp/pwned_where.csv").exists()


def test_a_good_predicate_still_selects(lake: Lake) -> None:
    meta = build_release(lake.uri, "rainy", "weather = 'rain' AND NOT work_zone", ["lake"], 0,
                         (1.0, 0.0, 0.0))
    assert meta["clip_ids"] == ["c1"]
    # a comment cannot eat a closing parenthesis: the predicate is parsed, never pasted
    meta = build_release(lake.uri, "rainy2", "weather = 'rain' -- ) OR (true", ["lake"], 0,
                         (1.0, 0.0, 0.0))
    assert meta["clip_ids"] == ["c1"]
    released = list(Path(lake.path("releases", "rainy")).rglob("*"))
    assert not [p for p in released if "/raw/" in str(p)]


@pytest.mark.parametrize("cid", ["../../raw", "..", "a/b", "/etc", "c0/../../x", "", ".hidden",
                                 "c0\x00", "c 0"])
def test_clip_ids_are_checked_before_any_path(lake: Lake, cid: str) -> None:
    with pytest.raises(ValueError, match="clip id"):
        checked_clip_id(lake, cid)
    assert checked_clip_id(lake, "c0") == "c0"


def test_a_symlinked_clip_folder_cannot_point_outside(lake: Lake, tmp_path: Path) -> None:
    outside = tmp_path / "outside"
    outside.mkdir()
    Path(lake.path("clean", "blobs")).mkdir(parents=True, exist_ok=True)
    Path(lake.path("clean", "blobs", "sneaky")).symlink_to(outside)
    with pytest.raises(ValueError, match="outside the lake"):
        checked_clip_id(lake, "sneaky")
