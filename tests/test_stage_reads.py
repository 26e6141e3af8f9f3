"""Stage.reads enforced: a stage's lake handle reads only the tables the stage declares (and
its own). A table read but not declared would be missing from the stage's manifest key, so
a change to it would not re-run the stage; the handle refuses the read instead."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pyarrow as pa
import pytest

from v2xlake.schemas.stage import Stage
from v2xlake.storage.frames import PointFrameIndex, partition_files
from v2xlake.storage.lake import Lake


def handle(lake: Lake, stage: Stage[Any]) -> Lake:
    """The stage's handle with its declared reads enforced, as the flow should hand it
    over; the simulated-clip tests (``test_align_sim``, ``test_ingest_sim``) run ingest,
    qa, deskew, annotate and align through it, which checks their declarations."""
    return lake.for_stage(stage.name, [(t.zone, t.name) for t in stage.owns],
                          reads=[(t.zone, t.name) for t in stage.reads])


def _lake(tmp_path: Path) -> Lake:
    lake = Lake(tmp_path / "lake")
    for table in ("lidar_frames", "ego_poses"):
        lake.write_table("clean", table, pa.table({"frame_idx": [0, 1]}), clip_id="c",
                         agent_id="a")
    return lake


def test_a_handle_reads_only_declared_and_owned_tables(tmp_path: Path) -> None:
    lake = _lake(tmp_path)
    h = lake.for_stage("deskew", [("clean", "deskew_frames")],
                       reads=[("clean", "lidar_frames")])
    assert h.read_table("clean", "lidar_frames", clip_id="c").num_rows == 2
    assert h.read_table("clean", "deskew_frames", clip_id="c").num_rows == 0  # its own
    with pytest.raises(PermissionError, match=r"reads clean\.ego_poses but does not declare"):
        h.read_table("clean", "ego_poses", clip_id="c")
    with pytest.raises(PermissionError, match="ego_poses"):
        partition_files(h, "clean", "ego_poses", "c")
    with pytest.raises(PermissionError, match="ego_poses"):
        PointFrameIndex.build(h, "clean", "ego_poses", "c", "a")
    with pytest.raises(PermissionError, match=r"raw\.lidar_frames"):  # zones are apart
        h.read_table("raw", "lidar_frames", clip_id="c")
    # without declared reads (tools, tests, a flow that does not pass them) anything goes
    free = lake.for_stage("deskew", [("clean", "deskew_frames")])
    assert free.read_table("clean", "ego_poses", clip_id="c").num_rows == 2
