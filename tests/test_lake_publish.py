"""The one publish protocol of every stage (``Lake.for_stage(..., atomic_clip=)``, then
``publish_stage`` or ``discard_stage``): Parquet partitions and blobs are staged, nothing is
visible before the publish, a failed run leaves nothing, ``replace_clip`` replaces a clip's
whole zone (ingest), and the deprecated ``staging()`` / ``publish()`` names behave as the
protocol they wrap."""

from __future__ import annotations

from pathlib import Path

import pyarrow as pa
import pytest

from v2xlake.storage.lake import Lake

CLIP = "c1"
OWNS = [("raw", "clips"), ("raw", "agents")]


def _t(n: int, clip_id: str = CLIP) -> pa.Table:
    return pa.table({"clip_id": [clip_id] * n, "x": list(range(n))})


def _seed(lake: Lake) -> None:
    """What an earlier ingest and QA left: raw clips, agents, qa_checks and a blob."""
    lake.write_table("raw", "clips", _t(1), clip_id=CLIP)
    lake.write_table("raw", "agents", _t(2), clip_id=CLIP)
    lake.write_table("raw", "qa_checks", _t(3), clip_id=CLIP)
    lake.write_blob("raw", f"{CLIP}/red/CAM/000000.png", b"old")
    lake.write_table("raw", "clips", _t(1, "other"), clip_id="other")


def test_staged_tables_and_blobs_appear_only_at_publish(tmp_path: Path) -> None:
    lake = Lake(tmp_path / "lake")
    _seed(lake)
    h = lake.for_stage("ingest", OWNS, atomic_clip=CLIP)
    path, _ = h.write_table("raw", "clips", _t(5), clip_id=CLIP)
    key = h.write_blob("raw", f"{CLIP}/red/CAM/000001.png", b"new")
    assert path.startswith(h.stage_root or "?")
    assert lake.read_table("raw", "clips", clip_id=CLIP).num_rows == 1  # not yet
    assert lake.read_blob("raw", f"{CLIP}/red/CAM/000000.png") == b"old"
    moved = h.publish_stage()
    assert lake.read_table("raw", "clips", clip_id=CLIP).num_rows == 5
    assert lake.read_blob("raw", key) == b"new"
    # the clip's blobs are replaced as a folder: the old frame is gone
    assert not lake.exists(lake.blob_path("raw", f"{CLIP}/red/CAM/000000.png"))
    # partitions the run did not touch stay
    assert lake.read_table("raw", "agents", clip_id=CLIP).num_rows == 2
    assert lake.read_table("raw", "clips", clip_id="other").num_rows == 1
    assert moved[h.stage_root + f"/raw/clips/clip_id={CLIP}"] == lake.table_dir(
        "raw", "clips", CLIP)
    assert not lake.exists(lake.path("_staging"))


def test_replace_clip_replaces_the_whole_zone_of_the_clip(tmp_path: Path) -> None:
    """Ingest's re-run: tables it did not write this time go, any owner's (QA's checks of
    the old bags), and so do the clip's blobs; other clips are untouched."""
    lake = Lake(tmp_path / "lake")
    _seed(lake)
    h = lake.for_stage("ingest", OWNS, atomic_clip=CLIP)
    h.write_table("raw", "clips", _t(4), clip_id=CLIP)
    h.replace_clip("raw", CLIP)
    assert lake.read_table("raw", "qa_checks", clip_id=CLIP).num_rows == 3  # not yet
    h.publish_stage()
    assert lake.read_table("raw", "clips", clip_id=CLIP).num_rows == 4
    for table in ("agents", "qa_checks"):
        assert not lake.exists(lake.table_dir("raw", table, CLIP)), table
    assert not lake.exists(lake.path("raw", "blobs", CLIP))
    assert lake.read_table("raw", "clips", clip_id="other").num_rows == 1
    with pytest.raises(RuntimeError, match="staged handle"):
        lake.for_stage("ingest", OWNS).replace_clip("raw", CLIP)


def test_a_failed_run_leaves_nothing(tmp_path: Path) -> None:
    lake = Lake(tmp_path / "lake")
    _seed(lake)
    h = lake.for_stage("ingest", OWNS, atomic_clip=CLIP)
    h.write_table("raw", "clips", _t(9), clip_id=CLIP)
    h.write_blob("raw", f"{CLIP}/red/CAM/000009.png", b"x")
    h.delete_blobs("raw", CLIP)
    h.replace_clip("raw", CLIP)
    h.discard_stage()
    assert lake.read_table("raw", "clips", clip_id=CLIP).num_rows == 1
    assert lake.read_table("raw", "qa_checks", clip_id=CLIP).num_rows == 3
    assert lake.read_blob("raw", f"{CLIP}/red/CAM/000000.png") == b"old"
    assert not lake.exists(lake.path("_staging"))


def test_a_chunk_handle_publishes_with_the_flow_handle(tmp_path: Path) -> None:
    """A cluster worker's chunk writes into the same run folder (``stage_root``); the flow's
    handle publishes what the chunk wrote, blobs included, without being told."""
    lake = Lake(tmp_path / "lake")
    _seed(lake)
    h = lake.for_stage("ingest", OWNS, atomic_clip=CLIP)
    chunk = Lake(lake.uri).for_stage("ingest", OWNS, stage_root=h.stage_root)
    chunk.write_table("raw", "agents", _t(7), clip_id=CLIP, agent_id="red")
    chunk.write_blob("raw", f"{CLIP}/red/CAM/000002.png", b"chunk")
    h.publish_stage()
    assert lake.read_table("raw", "agents", clip_id=CLIP).num_rows == 7
    assert lake.read_blob("raw", f"{CLIP}/red/CAM/000002.png") == b"chunk"


def test_unstaged_blob_deletion_is_immediate(tmp_path: Path) -> None:
    lake = Lake(tmp_path / "lake")
    _seed(lake)
    lake.delete_blobs("raw", CLIP)
    assert not lake.exists(lake.path("raw", "blobs", CLIP))
