"""The catalog at scale (#18): views made for the tables a query names, explicit file lists,
files of another schema, table snapshots that are only ever a cache."""

from __future__ import annotations

import uuid
from pathlib import Path
from typing import Any

import duckdb
import pyarrow as pa
import pytest

from v2xlake.schemas.arrow import rows_to_table
from v2xlake.schemas.tables import LAKE_TABLES
from v2xlake.storage.catalog import SNAPSHOT_DIR, Catalog
from v2xlake.storage.lake import Lake


def _clip(lake: Lake, cid: str, n_boxes: int = 3, weather: str = "clear") -> None:
    lake.write_table("clean", "clips", rows_to_table(LAKE_TABLES["clips"], [dict(
        clip_id=cid, location="x", road_type="urban", weather=weather, lighting="day",
        work_zone=False, n_agents=2, reference_agent="red", duration_s=1.0,
        source="simulated", status="ok")]), clip_id=cid)
    for agent in ("red", "black"):
        rows = [dict(clip_id=cid, agent_id=agent, sensor="LIDAR_TOP", frame_idx=k,
                     t_ns=100_000_000 + k, instance_id=f"{cid}-{k}",
                     category="Car" if k % 2 else "Pedestrian", cx=float(k), cy=0.0, cz=0.0,
                     w=1.0, l=2.0, h=1.5, qw=1.0, qx=0.0, qy=0.0, qz=0.0, vx=0.0, vy=0.0,
                     vz=0.0, links=[], num_lidar_pts=k) for k in range(n_boxes)]
        lake.write_table("clean", "annotations", rows_to_table(LAKE_TABLES["annotations"], rows),
                         clip_id=cid, agent_id=agent)


def _truth(lake: Lake, sql: str) -> list[tuple[Any, ...]]:
    """The same question over every file by glob, with plain DuckDB: what must come out."""
    con = duckdb.connect()
    if not lake.is_local:
        Catalog._setup_s3(Catalog.__new__(Catalog), con)
    glob = lake.table_glob("clean", "annotations")
    return sorted(con.execute(sql.replace("{annotations}", (
        f"read_parquet('{glob}', hive_partitioning=true, union_by_name=true)"))).fetchall())


BOXES = ("SELECT clip_id, agent_id, category, count(*), sum(num_lidar_pts) FROM {annotations} "
         "GROUP BY ALL")


def _answer(lake: Lake) -> list[tuple[Any, ...]]:
    with Catalog(lake, read_only=True) as cat:
        return sorted(tuple(r.values()) for r in cat.query(
            BOXES.replace("{annotations}", "clean.annotations")).to_pylist())


def test_views_are_made_for_the_tables_a_query_names(tmp_path: Path) -> None:
    lake = Lake(tmp_path / "lake")
    for i in range(3):
        _clip(lake, f"c{i}")
    # a broken file in another table: a catalog that bound every view would fail on it
    bad = Path(lake.table_dir("clean", "ego_poses", "c0", "red")) / "part.parquet"
    bad.parent.mkdir(parents=True)
    bad.write_bytes(b"not parquet at all")
    with Catalog(lake, read_only=True) as cat:
        assert cat.query("SELECT count(*) FROM annotations").column(0)[0].as_py() == 18
        assert set(cat._bound) == {"clean.annotations", "clean.annotations_world",
                                   "main.annotations"}
        with pytest.raises(duckdb.Error):
            cat.query("SELECT count(*) FROM ego_poses")
        # the user's path: read-only database rebuilt with each query's views
        got = cat.user_query("SELECT weather, count(*) AS n FROM clips GROUP BY weather")
        assert got.to_pylist() == [{"weather": "clear", "n": 3}]
        assert cat.user_query("SELECT count(*) AS n FROM clean.annotations "
                              "WHERE category = 'Car'").to_pylist() == [{"n": 6}]
        assert cat.con.execute("SELECT current_setting('access_mode')").fetchone() == (
            "read_only",)
        with pytest.raises(duckdb.Error):
            cat.con.execute("CREATE VIEW v AS SELECT 1")
        assert cat.select_clips("weather = 'clear'", ["clip_id"]).num_rows == 3


def test_files_of_another_schema(tmp_path: Path) -> None:
    lake = Lake(tmp_path / "lake")
    old = pa.table({"x": pa.array([1], pa.int64())})
    new = pa.table({"x": pa.array([2], pa.int64()), "y": pa.array(["b"])})
    # the newest file has a column the first lacks: the view unions by name
    lake.write_table("clean", "evolve", old, clip_id="a")
    lake.write_table("clean", "evolve", new, clip_id="b")
    with Catalog(lake, read_only=True) as cat:
        rows = cat.query("SELECT clip_id, x, y FROM clean.evolve ORDER BY clip_id").to_pylist()
    assert rows == [{"clip_id": "a", "x": 1, "y": None}, {"clip_id": "b", "x": 2, "y": "b"}]
    # first and newest agree, a file in between lacks a column: the query is re-run
    lake2 = Lake(tmp_path / "lake2")
    lake2.write_table("clean", "evolve", new, clip_id="a")
    lake2.write_table("clean", "evolve", old, clip_id="b")
    lake2.write_table("clean", "evolve", new, clip_id="c")
    with Catalog(lake2, read_only=True) as cat:
        assert "union_by_name" not in cat._view("clean.evolve").sql  # type: ignore[union-attr]
        assert cat.query("SELECT count(*), count(y) FROM clean.evolve").to_pylist() == [
            {"count_star()": 3, "count(y)": 2}]
        assert cat._union


def test_snapshots_answer_like_the_files(tmp_path: Path) -> None:
    lake = Lake(tmp_path / "lake")
    for i in range(6):
        _clip(lake, f"c{i}")
    with Catalog(lake, read_only=True) as cat:
        assert "clean.annotations" in cat.write_snapshots(min_files=1)
    snap = Path(lake.path(SNAPSHOT_DIR, "clean", "annotations.parquet"))
    assert snap.exists()
    with Catalog(lake, read_only=True) as cat:
        assert SNAPSHOT_DIR in cat._view("clean.annotations").sql  # type: ignore[union-attr]
    assert _answer(lake) == _truth(lake, BOXES)
    # after the snapshot: a new clip, a clip rewritten with other rows, a clip removed
    _clip(lake, "c6")
    _clip(lake, "c0", n_boxes=5)
    lake.delete_partition("clean", "annotations", "c1")
    assert _answer(lake) == _truth(lake, BOXES)
    with Catalog(lake, read_only=True) as cat:  # incremental: only what changed is read
        cat.write_snapshots(min_files=1)
        use = cat._snapshot_use("clean", "annotations", cat._listing("clean", "annotations"))
        assert use == ([], [])
    assert _answer(lake) == _truth(lake, BOXES)
    # a snapshot that cannot be read is ignored, not trusted
    snap.write_bytes(b"garbage")
    assert _answer(lake) == _truth(lake, BOXES)
    # a table below the file count gets none; a plain refresh makes the large ones
    assert Catalog(lake).write_snapshots() == []


@pytest.mark.slow
def test_snapshots_on_s3(s3_env: Any) -> None:
    lake = Lake(f"s3://{s3_env.bucket}/scale-{uuid.uuid4().hex[:8]}")
    for i in range(3):
        _clip(lake, f"s{i}")
    with Catalog(lake, read_only=True) as cat:
        assert "clean.annotations" in cat.write_snapshots(min_files=1)
    _clip(lake, "s3")
    assert _answer(lake) == _truth(lake, BOXES)
    with Catalog(lake, read_only=True) as cat:
        assert SNAPSHOT_DIR in cat._view("clean.annotations").sql  # type: ignore[union-attr]
        assert cat.user_query("SELECT count(*) AS n FROM annotations").to_pylist() == [
            {"n": 24}]
