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
          "/tf": -1, "/tf_static": 1, "/red/boxes": 10}


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


# ------------------------------------------------------------------ Foxglove-ready MCAP
def _mcap_messages(path: Path) -> tuple[Any, list[tuple[str, int, Any]]]:
    """Every message through the mcap package (what Foxglove's readers implement): CRCs
    checked, chunks decompressed, CDR decoded with the schema's own ROS 2 name."""
    from mcap.reader import make_reader

    ts = get_typestore(Stores.ROS2_HUMBLE)
    out = []
    with open(next(path.glob("*.mcap")), "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        for schema, channel, msg in reader.iter_messages(log_time_order=True):
            assert schema is not None and channel.message_encoding == "cdr"
            out.append((channel.topic, msg.log_time, ts.deserialize_cdr(msg.data, schema.name)))
    return summary, out


def _stamp_ns(h: Any) -> int:
    return int(h.stamp.sec) * 1_000_000_000 + int(h.stamp.nanosec)


def _tf_matrix(tr: Any) -> np.ndarray:
    from v2xlake.tasks.geometry import transform

    t, q = tr.translation, tr.rotation
    return transform(np.array([t.x, t.y, t.z]), np.array([q.w, q.x, q.y, q.z]))


def test_mcap_for_foxglove(lake: Lake, tmp_path: Path) -> None:
    from v2xlake.tasks.export.rosbag import RosbagExportConfig
    from v2xlake.tasks.interpolate import PoseTrack
    from v2xlake.tasks.reader import load_clip

    cfg = RosbagExportConfig(storage="mcap", combine_agents=True,
                             lidar_table="lidar_points_deskewed")
    export_rosbag(lake, "clip-a", None, tmp_path, config=cfg)
    summary, msgs = _mcap_messages(tmp_path / "clip-a_all")
    assert summary is not None
    assert {c.compression for c in summary.chunk_indexes} == {"zstd"}
    # one timeline: the clip's relative axis, every message's log time = its header stamp
    st = summary.statistics
    assert st.message_start_time == 100_000_000 - 2 * 8_000_000  # first pose sample
    assert st.message_end_time < 1_500_000_000
    topics = {t for t, _, _ in msgs}
    assert {"/red/lidar/points", "/black/lidar/points", "/red/boxes", "/black/boxes", "/tf",
            "/tf_static", "/red/camera/CAM_FRONT/camera_info"} <= topics
    for topic, log_t, m in msgs:
        hs = [m.header] if hasattr(m, "header") else [x.header for x in getattr(
            m, "transforms", getattr(m, "markers", []))]
        assert all(_stamp_ns(h) == log_t for h in hs), topic
    # frame tree: map -> <agent>/base_link (dynamic), <agent>/base_link -> sensors (static)
    static = [x for t, _, m in msgs if t == "/tf_static" for x in m.transforms]
    assert {(x.header.frame_id, x.child_frame_id) for x in static} == {
        (f"{a}/base_link", f"{a}/{s}") for a in ("red", "black")
        for s in ("lidar_top", "cam_front")}
    dyn: dict[str, list[tuple[int, np.ndarray]]] = {}
    for t, log_t, m in msgs:
        if t == "/tf":
            for x in m.transforms:
                assert x.header.frame_id == "map"
                dyn.setdefault(x.child_frame_id, []).append((log_t, _tf_matrix(x.transform)))
    assert set(dyn) == {"red/base_link", "black/base_link"}
    # resolving a cloud's frame through the tree gives the lake's T_world_lidar
    clip = load_clip(lake, "clip-a")
    for t, log_t, m in msgs:
        if t != "/black/lidar/points":
            continue
        assert m.header.frame_id == "black/lidar_top"
        samples = dyn["black/base_link"]
        from v2xlake.schemas.geometry import matrix_to_quat

        track = PoseTrack.create(np.array([s[0] for s in samples]),
                                 np.array([s[1][:3, 3] for s in samples]),
                                 np.array([matrix_to_quat(s[1][:3, :3]) for s in samples]))
        st_l = next(_tf_matrix(x.transform) for x in static
                    if x.child_frame_id == "black/lidar_top")
        T = track.matrices(log_t)[0] @ st_l
        agent = clip.agents["black"]
        expect = agent.T_world_ego(log_t)[0] @ agent.sensors["LIDAR_TOP"].T_ego_sensor
        assert np.allclose(T, expect, atol=1e-6)
    # boxes: DELETEALL then a CUBE + label per box, same marker id for the same instance
    # in both agents' arrays, in the LiDAR frame
    marks = [(t, m) for t, _, m in msgs if t.endswith("/boxes")]
    assert len(marks) == 20
    ids: dict[str, set[int]] = {}
    for t, m in marks:
        assert m.markers[0].action == 3  # DELETEALL
        cubes = [x for x in m.markers[1:] if x.type == 1]
        labels = [x for x in m.markers[1:] if x.type == 9]
        assert len(cubes) == len(labels) > 0
        assert {x.header.frame_id for x in cubes} == {t.split("/")[1] + "/lidar_top"}
        for c, lab in zip(cubes, labels, strict=True):
            ids.setdefault(lab.text.split()[-1], set()).add(c.id)
            if lab.text.endswith("car-parked"):  # (l, w, h): length along the box x axis
                assert (c.scale.x, c.scale.y, c.scale.z) == (4.5, 1.9, 1.6)
    assert all(len(v) == 1 for v in ids.values()) and "car-parked" in ids
    n_red = sum(1 for t, m in marks if t == "/red/boxes")
    assert n_red == 10


def test_cli_export_rosbag_mcap(lake: Lake, tmp_path: Path) -> None:
    from v2xlake.flows.cli import main

    assert main(["export", "rosbag", "--storage", "mcap", "--lake", lake.uri, "--out",
                 str(tmp_path / "o")]) == 0
    assert sorted(p.name for p in (tmp_path / "o").iterdir()) == ["clip-a_black", "clip-a_red"]
    assert list((tmp_path / "o" / "clip-a_red").glob("*.mcap"))
    assert main(["export", "bev", "--storage", "mcap", "--lake", lake.uri, "--out",
                 str(tmp_path / "b")]) == 2
