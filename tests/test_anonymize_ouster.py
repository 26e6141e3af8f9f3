"""A real clip with no INS (the Ouster OS1-128 bag): anonymize must still write a clean zone.

Regression: ingest writes an *empty* raw ``ins`` partition for such a clip, and the stage used
to assert on a local frame it could not have.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.fixtures.real import REAL_DATA_INGEST, requires_real_data
from v2xlake.storage.lake import Lake
from v2xlake.tasks.anonymize.stage import run_anonymize
from v2xlake.tasks.ingest import run_ingest

REPO = Path(__file__).resolve().parents[1]
OUSTER = REPO / "tests" / "fixtures" / "ouster"
pytestmark = requires_real_data("bags/ouster_os1_128_3frames_ros2")


@pytest.fixture(scope="module")
def anonymized(tmp_path_factory: pytest.TempPathFactory) -> tuple[Lake, str, object]:
    lake = Lake(tmp_path_factory.mktemp("lake"))
    clip_id = run_ingest(lake, OUSTER, REAL_DATA_INGEST).clip_id
    # the case being tested: the raw ins partition exists and is empty
    assert lake.list_files(lake.table_dir("raw", "ins", clip_id), ".parquet")
    assert lake.read_table("raw", "ins", clip_id=clip_id).num_rows == 0
    return lake, clip_id, run_anonymize(lake, clip_id)


def test_clip_without_ins_is_anonymized(anonymized: tuple) -> None:
    lake, clip_id, report = anonymized
    raw_frames = lake.read_table("raw", "lidar_frames", clip_id=clip_id)
    clean_frames = lake.read_table("clean", "lidar_frames", clip_id=clip_id)
    assert clean_frames.num_rows == raw_frames.num_rows > 0
    raw_pts = lake.read_table("raw", "lidar_points", clip_id=clip_id, columns=["t_ns"])
    clean_pts = lake.read_table("clean", "lidar_points", clip_id=clip_id, columns=["t_ns"])
    assert clean_pts.num_rows == raw_pts.num_rows
    for table in ("clips", "agents", "sensors", "calibrated_sensors"):
        assert lake.read_table("clean", table, clip_id=clip_id).num_rows > 0, table
    # no poses can be made without INS, and WGS84 never reaches the clean zone
    assert lake.read_table("clean", "ego_poses", clip_id=clip_id).num_rows == 0
    assert not lake.list_files(lake.table_dir("clean", "ego_poses", clip_id), ".parquet")
    assert lake.read_table("clean", "ins", clip_id=clip_id).num_rows == 0
    assert any("no INS" in n and "ego_poses" in n for n in report.notes), report.notes
    assert report.metrics["n_images"] == 0


def test_clean_times_are_relative(anonymized: tuple) -> None:
    lake, clip_id, _ = anonymized
    t = lake.read_table("clean", "lidar_frames", clip_id=clip_id).column("t_start_ns")
    assert min(t.to_pylist()) == 100_000_000
