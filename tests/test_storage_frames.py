"""The frame index of a points table (``storage/frames.py``) and the rule it serves: the lake's
Parquet layout is known in ``storage/`` only."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest

from v2xlake.storage.frames import PointFrameIndex, iter_row_groups, partition_files
from v2xlake.storage.lake import Lake

PACKAGE = Path(__file__).resolve().parents[1] / "v2xlake"



def _points(frames: list[int], sensor: str, n: int = 5) -> pa.Table:
    f = np.repeat(np.array(frames, np.int64), n)
    return pa.table({
        "clip_id": pa.array(["c"] * len(f)), "agent_id": pa.array(["a"] * len(f)),
        "sensor": pa.array([sensor] * len(f)).dictionary_encode(),
        "frame_idx": f, "t_ns": np.arange(len(f), dtype=np.int64) + 1000 * f,
        "x": np.arange(len(f), dtype=np.float32), "y": np.zeros(len(f), np.float32),
        "z": np.full(len(f), 7.0 if sensor == "LIDAR_TOP" else 9.0, np.float32)})


@pytest.fixture
def lake(tmp_path: Path) -> Lake:
    lk = Lake(tmp_path / "lake")
    # one file per LiDAR written frame by frame (the lake's layout) ...
    lk.write_table("clean", "lidar_points", _points([0, 1, 2], "LIDAR_TOP"), clip_id="c",
                   agent_id="a", name="LIDAR_TOP", row_group_by="frame_idx")
    lk.write_table("clean", "lidar_points", _points([1, 2], "LIDAR_LEFT", 3), clip_id="c",
                   agent_id="a", name="LIDAR_LEFT", row_group_by="frame_idx")
    # ... and a file whose one row group holds several frames (written without row_group_by)
    lk.write_table("clean", "lidar_points", _points([3, 4], "LIDAR_TOP", 2), clip_id="c",
                   agent_id="a", name="late")
    return lk


def test_index_reads_exactly_one_frame_of_one_lidar(lake: Lake) -> None:
    idx = PointFrameIndex.build(lake, "clean", "lidar_points", "c", "a")
    assert idx.frames() == [0, 1, 2, 3, 4]
    top = idx.read(1, "LIDAR_TOP", ["t_ns", "z"])
    assert top is not None and top.column_names == ["t_ns", "z"]
    assert top.num_rows == 5 and set(top["z"].to_pylist()) == {7.0}
    assert (np.asarray(top["t_ns"]) // 1000 == 1).all()
    left = idx.read(1, "LIDAR_LEFT", ["z"])
    assert left is not None and left.num_rows == 3 and set(left["z"].to_pylist()) == {9.0}
    both = idx.read(2, None)
    assert both is not None and both.num_rows == 8
    shared = idx.read(4, "LIDAR_TOP", ["frame_idx"])  # filtered out of a shared row group
    assert shared is not None and shared["frame_idx"].to_pylist() == [4, 4]
    empty = idx.read(0, "LIDAR_LEFT", ["z"])  # the frame exists, not for this LiDAR
    assert empty is not None and empty.num_rows == 0
    assert idx.read(9, "LIDAR_TOP") is None


def test_partition_files_and_row_group_ranges(lake: Lake) -> None:
    files = partition_files(lake, "clean", "lidar_points", "c")
    assert sorted((a, n) for _, a, n in files) == [("a", "LIDAR_LEFT"), ("a", "LIDAR_TOP"),
                                                   ("a", "late")]
    path = next(p for p, _, n in files if n == "LIDAR_TOP")
    groups = list(iter_row_groups(lake, path, 1, 99))
    assert [g["frame_idx"][0].as_py() for g in groups] == [1, 2]


def _opens_parquet(path: Path) -> bool:
    tree = ast.parse(path.read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Import) and any(a.name == "pyarrow.parquet" for a in node.names):
            return True
        if isinstance(node, ast.ImportFrom) and (
                node.module == "pyarrow.parquet"
                or (node.module == "pyarrow" and any(a.name == "parquet" for a in node.names))):
            return True
    return False


def test_no_parquet_is_opened_outside_storage() -> None:
    offenders = {str(p.relative_to(PACKAGE)) for p in PACKAGE.rglob("*.py")
                 if p.relative_to(PACKAGE).parts[0] != "storage" and _opens_parquet(p)}
    assert not offenders, "open Parquet through v2xlake/storage/"
