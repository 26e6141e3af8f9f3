"""ROS 2 bag export of radars: a simulated clip with a front radar per vehicle exports one
PointCloud2 topic per radar whose messages, read back with rosbags' AnyReader, give exactly
the lake's ``radar_points`` of each scan at the scan's stamp, and /tf_static carries the
radar's extrinsic."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from tests.export_fixtures import run_stages
from v2xlake.storage.lake import Lake
from v2xlake.tasks.export.rosbag import RosbagExportConfig, export_rosbag
from v2xlake.tasks.reader import load_clip
from v2xlake.tasks.simulate import SimConfig, simulate

NEEDED = ("ingest", "qa", "anonymize")  # the raw scans and radar tables are clean by then


@pytest.fixture(scope="module")
def radar_lake(tmp_path_factory: pytest.TempPathFactory) -> tuple[Lake, str]:
    tmp = tmp_path_factory.mktemp("bagradar")
    clip = simulate(tmp / "clip", SimConfig.preset(
        "small", seconds=0.5, seed=3, cameras=(), radar=True, write_lidar_truth=False))
    lake = Lake(tmp / "lake")
    return lake, run_stages(lake, clip, NEEDED)


def _read(bag: Path) -> tuple[dict[str, list[tuple[int, Any]]], list[Any]]:
    ts = get_typestore(Stores.ROS2_HUMBLE)
    msgs: dict[str, list[tuple[int, Any]]] = {}
    static: list[Any] = []
    with AnyReader([bag], default_typestore=ts) as r:
        for conn, t, raw in r.messages():
            m = r.deserialize(raw, conn.msgtype)
            if conn.topic == "/tf_static":
                static.extend(m.transforms)
            msgs.setdefault(conn.topic, []).append((t, m))
    return msgs, static


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_radar_topic_equals_lake_points(radar_lake: tuple[Lake, str], tmp_path: Path,
                                        storage: str) -> None:
    lake, cid = radar_lake
    rep = export_rosbag(lake, cid, "red", tmp_path, config=RosbagExportConfig(storage=storage))
    assert rep.status == "done"
    msgs, static = _read(tmp_path / f"{cid}_red")
    topic = "/red/radar/RADAR_FRONT/points"
    assert topic in msgs and "/black/radar/RADAR_FRONT/points" not in msgs
    frames = lake.read_table("clean", "radar_frames", clip_id=cid, agent_id="red")
    pts = lake.read_table("clean", "radar_points", clip_id=cid, agent_id="red")
    stamps = sorted(frames["stamp_ns"].to_pylist())
    got = msgs[topic]
    assert [t for t, _ in got] == stamps == [
        m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for _, m in got]
    assert rep.metrics[f"red:{topic}"] == len(stamps) == frames.num_rows
    stamp_of = dict(zip(frames["frame_idx"].to_pylist(), frames["stamp_ns"].to_pylist(),
                        strict=True))
    fi = pts["frame_idx"].to_numpy()
    checked = 0
    for f, t in stamp_of.items():
        m = next(m for tt, m in got if tt == t)
        assert m.header.frame_id == "red/radar_front"
        assert [x.name for x in m.fields] == ["x", "y", "z", "velocity", "rcs"]
        arr = np.frombuffer(m.data.tobytes(), np.float32).reshape(-1, 5)
        sel = fi == f
        assert m.width == len(arr) == int(sel.sum())
        if not sel.any():
            continue
        order = np.argsort(pts["t_ns"].to_numpy()[sel], kind="stable")
        lake_xyz = np.stack([pts[c].to_numpy()[sel] for c in "xyz"], 1)[order]
        lake_v = pts["velocity"].to_numpy()[sel][order]
        np.testing.assert_array_equal(arr[:, :3], lake_xyz.astype(np.float32))
        np.testing.assert_array_equal(arr[:, 3], lake_v.astype(np.float32))
        checked += 1
    assert checked >= 5
    # the radar's extrinsic is in /tf_static, so tf places the scans on the vehicle
    cal = load_clip(lake, cid).agents["red"].sensors["RADAR_FRONT"].T_ego_sensor
    (tf,) = [x for x in static if x.child_frame_id == "red/radar_front"]
    assert tf.header.frame_id == "red/base_link"
    tr = tf.transform.translation
    np.testing.assert_allclose([tr.x, tr.y, tr.z], cal[:3, 3], atol=1e-9)


def test_radar_can_be_left_out(radar_lake: tuple[Lake, str], tmp_path: Path) -> None:
    lake, cid = radar_lake
    export_rosbag(lake, cid, None, tmp_path,
                  config=RosbagExportConfig(storage="mcap", radar=False, combine_agents=True))
    msgs, _ = _read(tmp_path / f"{cid}_all")
    assert not [t for t in msgs if "/radar/" in t]
