"""Catalog: typed empty views, zone fallback, concurrent writers, killed writers, S3."""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
import time
import uuid
from pathlib import Path
from typing import Any

import duckdb
import pyarrow as pa
import pytest

from tests.fixtures.minibag import MiniClip, write_clip
from v2xlake.schemas.arrow import arrow_schema
from v2xlake.schemas.tables import LAKE_TABLES, LidarPointRow
from v2xlake.storage.catalog import Catalog
from v2xlake.storage.lake import Lake
from v2xlake.tasks.ingest import run_ingest

DESIGN_NAMES = ("clips", "agents", "sensors", "calibrated_sensors", "ego_poses", "lidar_frames",
                "lidar_points", "camera_frames", "annotations", "instances", "registrations",
                "alignments", "qa_checks", "manifests")


def test_empty_lake_has_every_view_with_columns(tmp_path: Path) -> None:
    lake = Lake(tmp_path / "lake")
    cat = Catalog(lake)
    for name in DESIGN_NAMES:
        assert cat.query(f"SELECT count(*) FROM {name}").column(0)[0].as_py() == 0
    cols = [r["column_name"] for r in cat.query("DESCRIBE lidar_points").to_pylist()]
    assert cols == arrow_schema(LidarPointRow).names
    types = {r["column_name"]: r["column_type"]
             for r in cat.query("DESCRIBE raw.lidar_points").to_pylist()}
    assert types["t_ns"] == "BIGINT" and types["x"] == "FLOAT" and types["ring"] == "USMALLINT"
    for t in set(LAKE_TABLES) - {"manifests"}:  # manifests live as JSON, main.manifests
        cat.query(f"SELECT * FROM raw.{t}")
    # the persisted catalog file answers the same names for other tools
    con = duckdb.connect(lake.catalog_path, read_only=True)
    assert con.sql("SELECT count(*) FROM clips").fetchone() == (0,)
    con.close()


def test_clean_zone_takes_over_main_names(tmp_path: Path) -> None:
    lake = Lake(tmp_path / "lake")
    run_ingest(lake, write_clip(tmp_path / "c", MiniClip(seconds=0.2, points=50, cameras=())))
    cat = Catalog(lake)
    assert cat.zone_of("lidar_frames") == "raw" and cat.zone_of("ego_poses") == "empty"
    raw = lake.read_table("raw", "lidar_frames", clip_id="mini")
    shifted = raw.set_column(raw.schema.get_field_index("stamp_ns"), "stamp_ns",
                             pa.array([100_000_000] * raw.num_rows, pa.int64()))
    for agent in ("red", "black"):
        part = shifted.filter(pa.compute.equal(shifted["agent_id"], agent))
        lake.write_table("clean", "lidar_frames", part, clip_id="mini", agent_id=agent)
    assert cat.refresh()["lidar_frames"] == "clean"
    assert set(cat.query("SELECT DISTINCT stamp_ns FROM lidar_frames").column(0).to_pylist()) \
        == {100_000_000}
    assert cat.query("SELECT count(*) FROM raw.lidar_frames").column(0)[0].as_py() == 4
    zones = {r["name"]: r["zone"] for r in cat.query(
        "SELECT name, zone FROM catalog_tables WHERE schema = 'main'").to_pylist()}
    assert zones["lidar_frames"] == "clean" and zones["clips"] == "raw"


def _ingest_worker(lake_root: str, clip_dir: str) -> str:
    return run_ingest(Lake(lake_root), clip_dir).clip_id


def test_concurrent_ingests_lose_nothing(tmp_path: Path) -> None:
    n = 3
    clips = [write_clip(tmp_path / f"c{i}", MiniClip(
        seconds=0.2 + 0.1 * i, points=300, clip_id=f"conc-{i}", seed=i,
        storage=("sqlite3", "mcap", "ros1")[i])) for i in range(n)]
    lake_root = str(tmp_path / "lake")
    ctx = mp.get_context("spawn")
    with ctx.Pool(n) as pool:
        done = pool.starmap(_ingest_worker, [(lake_root, str(c)) for c in clips])
    assert sorted(done) == [f"conc-{i}" for i in range(n)]
    cat = Catalog(Lake(lake_root))
    frames = 2 * sum(2 + i for i in range(n))  # 2 agents x (seconds x 10 Hz)
    assert cat.query("SELECT count(*) FROM clips").column(0)[0].as_py() == n
    assert cat.query("SELECT count(*) FROM lidar_frames").column(0)[0].as_py() == frames
    assert cat.query("SELECT count(*) FROM lidar_points").column(0)[0].as_py() == frames * 300
    per_clip = cat.query("SELECT f.clip_id, sum(f.n_points) AS a, (SELECT count(*) FROM "
                         "lidar_points p WHERE p.clip_id = f.clip_id) AS b FROM lidar_frames f "
                         "GROUP BY f.clip_id").to_pylist()
    assert all(r["a"] == r["b"] for r in per_clip) and len(per_clip) == n
    leftovers = [p for p in Path(lake_root).rglob("*") if p.name.startswith(".")
                 or "_staging" in p.parts]
    assert leftovers == []


def _slow_writer(lake_root: str, started: Any) -> None:
    lake = Lake(lake_root)
    t = pa.table({"frame_idx": pa.array(range(100_000), pa.int32()),
                  "x": pa.array([1.0] * 100_000, pa.float32())})
    with lake.open_writer("raw", "killed", t.schema, clip_id="k", agent_id="a",
                          name="LIDAR_TOP") as w:
        for _ in range(10_000):
            w.write(t)
            started.set()


def _slow_ingest(lake_root: str, clip_dir: str, started: Any) -> None:
    started.set()
    run_ingest(Lake(lake_root), clip_dir)


def test_killed_writer_leaves_nothing_visible(tmp_path: Path) -> None:
    lake_root = str(tmp_path / "lake")
    lake = Lake(lake_root)
    ctx = mp.get_context("spawn")
    started = ctx.Event()
    p = ctx.Process(target=_slow_writer, args=(lake_root, started))
    p.start()
    assert started.wait(60)
    time.sleep(0.3)
    assert p.pid is not None
    os.kill(p.pid, signal.SIGKILL)
    p.join()
    part_dir = lake.table_dir("raw", "killed", "k", "a")
    hidden = [f for f in os.listdir(part_dir)]
    assert hidden and all(f.startswith(".") for f in hidden)  # the partial bytes exist...
    assert lake.list_files(part_dir, ".parquet") == []  # ...but are invisible
    cat = Catalog(lake)
    assert cat.zones.get("lidar_points") == "empty"
    assert cat.query("SELECT count(*) FROM raw.killed").column(0)[0].as_py() == 0

    # an ingest killed half-way leaves nothing of its clip in the raw zone
    clip = write_clip(tmp_path / "big", MiniClip(seconds=2.0, points=20_000, clip_id="big"))
    started2 = ctx.Event()
    q = ctx.Process(target=_slow_ingest, args=(lake_root, str(clip), started2))
    q.start()
    assert started2.wait(60)
    deadline = time.time() + 60
    while time.time() < deadline and not list(Path(lake_root).glob("_staging/*/*/raw")):
        time.sleep(0.01)
    time.sleep(0.05)
    assert q.pid is not None
    os.kill(q.pid, signal.SIGKILL)
    q.join()
    assert [f for f in lake.list_files(lake.path("raw")) if "clip_id=big" in f] == []
    cat.refresh()
    assert cat.query("SELECT count(*) FROM lidar_points").column(0)[0].as_py() == 0
    # the next ingest of that clip clears the killed run's staging folder
    assert list(Path(lake_root).glob("_staging/big/*"))
    rep = run_ingest(lake, clip)
    assert any("stale staging" in n for n in rep.notes)
    assert not Path(lake_root, "_staging").exists()


# --------------------------------------------------------------------------- S3 (SeaweedFS)
def test_s3_lake_ingest_and_catalog(tmp_path: Path, s3_env: Any) -> None:
    """The same API against a real S3 server (tests/conftest.py: ``weed mini``)."""
    lake = Lake(f"s3://{s3_env.bucket}/catalog-test-{uuid.uuid4().hex[:8]}")
    clip = write_clip(tmp_path / "c", MiniClip(seconds=0.2, points=100, clip_id="s3clip"))
    run_ingest(lake, clip)
    assert lake.exists(lake.path("landing", "s3clip", "clip.yaml"))
    assert lake.read_table("raw", "lidar_frames", clip_id="s3clip").num_rows == 4
    assert lake.list_files(lake.path("_staging")) == []
    cat = Catalog(lake)
    assert cat.query("SELECT count(*) FROM lidar_points").column(0)[0].as_py() == 400
    assert cat.query("SELECT count(*) FROM camera_frames").column(0)[0].as_py() == 12
    assert cat.query("SELECT count(*) FROM ego_poses").column(0)[0].as_py() == 0
    key = cat.query("SELECT blob FROM camera_frames LIMIT 1").column(0)[0].as_py()
    assert lake.read_blob("raw", key).startswith(b"\x89PNG")
    # a killed / failed writer on S3: the multipart upload is aborted, no object appears
    t = pa.table({"x": pa.array([1.0], pa.float32())})
    with pytest.raises(RuntimeError), lake.open_writer("raw", "failed", t.schema,
                                                       clip_id="s3clip") as w:
        w.write(t)
        raise RuntimeError("boom")
    assert lake.list_files(lake.table_dir("raw", "failed"), ".parquet") == []


def test_the_persisted_catalog_travels_with_the_lake(tmp_path: Path) -> None:
    """#15: catalog.duckdb holds paths relative to the lake, so a moved lake reads its own
    files from the plain duckdb client started in the lake folder."""
    import os
    import shutil

    import duckdb

    from tests.fixtures.minibag import MiniClip, write_clip
    from v2xlake.tasks.ingest import run_ingest

    lake = Lake(tmp_path / "lake")
    run_ingest(lake, write_clip(tmp_path / "c", MiniClip(seconds=0.2, points=100,
                                                         cameras=(), clip_id="trav")))
    Catalog(lake).close()  # persists catalog.duckdb
    moved = tmp_path / "elsewhere" / "lake2"
    shutil.move(lake.base, moved)
    here = os.getcwd()
    try:
        os.chdir(moved)
        con = duckdb.connect(str(moved / "catalog.duckdb"), read_only=True)
        n = con.execute("SELECT count(*) FROM lidar_frames").fetchone()
        con.close()
    finally:
        os.chdir(here)
    assert n is not None and n[0] == 4
    assert str(tmp_path / "lake") not in (moved / "catalog.duckdb").read_bytes().decode(
        "latin-1")
