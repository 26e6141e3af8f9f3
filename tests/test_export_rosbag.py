"""ROS 2 bag export read back by rosbags (sqlite3 and MCAP) and the mcap package, plus the
ROS 2 -> ROS 1 -> ROS 2 round trip."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from tests.export_fixtures import build_clean_clip
from v2xlake.storage.lake import Lake
from v2xlake.storage.reader import iter_point_frames
from v2xlake.tasks.export.rosbag import convert_bag, export_rosbag

TOPICS = {"/red/lidar/points": 10, "/red/camera/CAM_FRONT/image/compressed": 30,
          "/red/camera/CAM_FRONT/camera_info": 30, "/red/imu": -1, "/red/ins/odometry": -1,
          "/tf_static": 1}


@pytest.fixture(scope="module")
def lake(tmp_path_factory: pytest.TempPathFactory) -> Lake:
    lk = Lake(tmp_path_factory.mktemp("bag") / "lake")
    build_clean_clip(lk, "clip-a", seconds=1.0)
    return lk


def _read_all(path: Path) -> dict[str, list[tuple[int, object]]]:
    out: dict[str, list[tuple[int, object]]] = {}
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as r:
        for c, t, raw in r.messages():
            out.setdefault(c.topic, []).append((t, r.deserialize(raw, c.msgtype)))
    return out


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_rosbag_readable(lake: Lake, tmp_path: Path, storage: str) -> None:
    rep = export_rosbag(lake, "clip-a", "red", tmp_path, storage=storage)  # type: ignore[arg-type]
    bag = tmp_path / "clip-a_red"
    msgs = _read_all(bag)
    counts = {k: len(v) for k, v in msgs.items()}
    n_pose = lake.read_table("clean", "ego_poses", clip_id="clip-a", agent_id="red").num_rows
    for topic, n in TOPICS.items():
        assert counts[topic] == (n if n > 0 else n_pose), (topic, counts)
    assert rep.metrics["red:/red/lidar/points"] == 10
    # raw points and per-point time survive exactly
    src = {f.frame_idx: f for f in iter_point_frames(lake, "clip-a", "red", table="lidar_points")}
    t0, pc = msgs["/red/lidar/points"][3]
    pcm: Any = pc
    spec: Any = {"names": [f.name for f in pcm.fields],
                 "formats": ["<u2" if f.datatype == 4 else "<f4" for f in pcm.fields],
                 "offsets": [f.offset for f in pcm.fields], "itemsize": pcm.point_step}
    arr: Any = np.frombuffer(bytes(pcm.data), dtype=np.dtype(spec))
    s = src[3]
    assert np.allclose(np.c_[arr["x"], arr["y"], arr["z"]], s.xyz)
    assert np.allclose(arr["time"], (s.t_ns - t0) / 1e9, atol=1e-7)
    assert arr["time"].min() >= 0 and arr["time"].max() < 0.1
    assert t0 == 100_000_000 + 3 * 100_000_000  # relative time axis
    # timestamps are in order
    all_t = sorted(t for v in msgs.values() for t, _ in v)
    assert all_t[0] >= 0 and all_t[-1] < 2_000_000_000
    if storage == "mcap":
        from mcap.reader import make_reader

        mcap_file = next(bag.glob("*.mcap"))
        with open(mcap_file, "rb") as f:
            reader = make_reader(f)
            summary = reader.get_summary()
            assert summary is not None
            schemas = {s.name for s in summary.schemas.values()}
            n = sum(1 for _ in reader.iter_messages(topics=["/red/lidar/points"]))
        assert "sensor_msgs/msg/PointCloud2" in schemas and n == 10


def test_ros1_roundtrip(lake: Lake, tmp_path: Path) -> None:
    export_rosbag(lake, "clip-a", "black", tmp_path / "r2", storage="sqlite3")
    src = tmp_path / "r2" / "clip-a_black"
    ros1 = convert_bag(src, tmp_path / "black.bag", to="ros1")
    assert ros1.exists() and ros1.suffix == ".bag"
    with AnyReader([ros1]) as r:
        types = {c.topic: c.msgtype for c in r.connections}
        md5 = {c.topic: c.digest for c in r.connections}
    assert types["/black/lidar/points"] == "sensor_msgs/msg/PointCloud2"
    # ROS 1 subscribers match on md5: these must be the Noetic definitions
    assert md5["/tf_static"] == "94810edda583a504dfda3829e70d7eec"
    assert md5["/black/lidar/points"] == "1158d486dd51d683ce2f1be655c3c181"
    assert md5["/black/imu"] == "6a62c6daae103f4ff57a132d6f95cec2"
    back = convert_bag(ros1, tmp_path / "back", to="ros2", storage="mcap")
    a, b = _read_all(src), _read_all(back)
    assert {k: len(v) for k, v in a.items()} == {k: len(v) for k, v in b.items()}
    pa_, pb = a["/black/lidar/points"][5][1], b["/black/lidar/points"][5][1]
    assert bytes(pa_.data) == bytes(pb.data)  # type: ignore[attr-defined]
    ia, ib = a["/black/imu"][7][1], b["/black/imu"][7][1]
    assert ia.linear_acceleration.z == ib.linear_acceleration.z  # type: ignore[attr-defined]
