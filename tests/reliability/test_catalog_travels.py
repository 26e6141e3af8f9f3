"""#15 item 8: a catalog that travels. ``catalog.duckdb`` names the lake's files relative to
the lake root, so a copied or moved lake answers from its own files: from the plain DuckDB
client started in the lake folder, from any other folder once ``file_search_path`` names the
lake, and through ``v2xlake`` from anywhere; ``v2xlake catalog refresh`` rewrites it."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import duckdb
import pytest

from tests.fixtures.minibag import MiniClip, write_clip
from v2xlake.flows.bookkeeping import refresh_catalog, user_query
from v2xlake.flows.cli import main
from v2xlake.storage.lake import Lake
from v2xlake.tasks.ingest import run_ingest


def _count(con: duckdb.DuckDBPyConnection) -> int:
    row = con.execute("SELECT count(*) FROM lidar_frames").fetchone()
    assert row is not None
    return int(row[0])


def test_a_copied_lake_reads_its_own_files_from_anywhere(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    lake = Lake(tmp_path / "lake")
    run_ingest(lake, write_clip(tmp_path / "c", MiniClip(seconds=0.2, points=100,
                                                         cameras=(), clip_id="trav")))
    refresh_catalog(lake)
    copy = tmp_path / "elsewhere" / "copy"
    shutil.copytree(lake.base, copy)
    shutil.rmtree(Path(lake.base, "raw", "lidar_frames"))  # the original loses its frames
    db = str(copy / "catalog.duckdb")
    here = os.getcwd()
    try:
        os.chdir(tmp_path)  # neither lake's folder
        with duckdb.connect(db, read_only=True) as con:
            con.execute(f"SET file_search_path = '{copy}'")
            assert _count(con) == 4  # the copy's own files, not the original's
        with duckdb.connect(db, read_only=True) as con:  # relative paths need the root
            with pytest.raises(duckdb.IOException):
                _count(con)
        os.chdir(copy)  # `cd <lake> && duckdb catalog.duckdb`
        with duckdb.connect(db, read_only=True) as con:
            assert _count(con) == 4
        os.chdir(tmp_path)
        n = user_query(Lake(copy), "SELECT count(*) AS n FROM lidar_frames")
        assert n.column(0).to_pylist() == [4]
        assert main(["catalog", "refresh", "--lake", str(copy)]) == 0
    finally:
        os.chdir(here)
    text = (copy / "catalog.duckdb").read_bytes().decode("latin-1")
    assert str(tmp_path) not in text  # no absolute path survives a refresh either
    capsys.readouterr()
