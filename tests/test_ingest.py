"""Ingest: every storage, the real Ouster bag, the real malformed bags, damaged input."""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pyarrow.parquet as pq
import pytest
import yaml

from tests.fixtures.minibag import T0, MiniClip, write_clip
from tests.fixtures.real import REAL_DATA_INGEST, requires_real_data
from v2xlake.schemas.clip import PointTimeField, TimeReference, TimeUnit
from v2xlake.schemas.errors import ClipError
from v2xlake.storage.catalog import Catalog
from v2xlake.storage.lake import Lake
from v2xlake.tasks.ingest import IngestConfig, clip_inputs, run_ingest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
REAL = SHARED / "data" / "real" / "bags"
OUSTER_FIXTURE = REPO / "tests" / "fixtures" / "ouster"


def count(cat: Catalog, sql: str) -> int:
    return int(cat.query(sql).column(0)[0].as_py())


def raw_is_empty(lake: Lake, clip_id: str) -> bool:
    return not [f for f in lake.list_files(lake.path("raw")) if f"clip_id={clip_id}" in f
                or f"/blobs/{clip_id}/" in f]


@pytest.mark.parametrize("storage", ["sqlite3", "mcap", "ros1"])
def test_ingest_each_storage_counts_via_catalog(tmp_path: Path, storage: str) -> None:
    clip = write_clip(tmp_path / "clip", MiniClip(storage=storage, seconds=0.3, points=500,
                                                  clip_id=f"c-{storage}"))
    lake = Lake(tmp_path / "lake")
    rep = run_ingest(lake, clip)
    assert rep.clip_id == f"c-{storage}" and rep.metrics["lidar_frames"] == 6
    cat = Catalog(lake)
    cid = f"clip_id = 'c-{storage}'"
    assert count(cat, f"SELECT count(*) FROM clips WHERE {cid}") == 1
    assert count(cat, f"SELECT count(*) FROM agents WHERE {cid} AND has_ins") == 2
    assert count(cat, f"SELECT count(*) FROM lidar_frames WHERE {cid}") == 6
    assert count(cat, f"SELECT count(*) FROM lidar_points WHERE {cid}") == 6 * 500
    assert count(cat, f"SELECT count(*) FROM camera_frames WHERE {cid}") == 2 * 9
    # INS runs 48 ms before and after the LiDAR: (300 + 96) / 8 samples per agent
    assert count(cat, f"SELECT count(*) FROM raw.ins WHERE {cid}") == 2 * 50
    assert count(cat, f"SELECT count(*) FROM imu WHERE {cid}") == 2 * 30
    assert count(cat, f"SELECT count(*) FROM gnss WHERE {cid}") == 2 * 3
    assert count(cat, f"SELECT count(*) FROM annotations WHERE {cid}") == 2
    # every sensor calibrated: LiDAR + camera from tf_static, camera intrinsics from CameraInfo
    cal = {(r["agent_id"], r["sensor"]): r for r in cat.query(
        f"SELECT * FROM calibrated_sensors WHERE {cid}").to_pylist()}
    assert len(cal) == 2 * 5
    lid = cal[("red", "LIDAR_TOP")]
    assert (lid["tx"], lid["tz"], lid["source"]) == (0.5, 1.8, "tf_static")
    cam = cal[("black", "CAM_FRONT")]
    assert cam["source"] == "tf_static+camera_info" and cam["fx"] == 50.0
    assert cam["distortion_model"] == "plumb_bob"
    # per-point absolute time reconstructed to the ns from float64 seconds, in frame order
    pts = cat.query(f"SELECT frame_idx, t_ns, return_id FROM lidar_points WHERE {cid} "
                    "AND agent_id = 'red' ORDER BY frame_idx").to_pydict()
    fr = np.asarray(pts["frame_idx"])
    t = np.asarray(pts["t_ns"])
    start = T0 + fr * 100_000_000
    assert np.all(np.abs(t - start - (np.arange(t.size) % 500) * (99_000_000 // 500)) < 1_000)
    assert set(pts["return_id"]) == {1}
    f = cat.query(f"SELECT * FROM lidar_frames WHERE {cid} AND agent_id='red' "
                  "ORDER BY frame_idx").to_pylist()
    assert [r["stamp_ns"] for r in f] == [T0, T0 + 100_000_000, T0 + 200_000_000]
    assert all(abs(r["t_end_ns"] - r["t_start_ns"] - 98_802_000) < 1_000 for r in f)
    # one row group per frame, sorted by frame
    files = lake.list_files(lake.table_dir("raw", "lidar_points", f"c-{storage}", "red"))
    meta = pq.ParquetFile(files[0]).metadata
    assert meta.num_row_groups == 3 and meta.row_group(0).num_rows == 500
    # image blobs: PNG kept byte for byte, checksum recorded
    row = cat.query(f"SELECT blob, sha256, width, height FROM camera_frames WHERE {cid} "
                    "LIMIT 1").to_pylist()[0]
    png = lake.read_blob("raw", row["blob"])
    assert hashlib.sha256(png).hexdigest() == row["sha256"]
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
    assert img is not None and img.shape == (row["height"], row["width"], 3) == (48, 64, 3)
    # landing holds the clip as delivered, no staging left behind
    assert lake.exists(lake.path("landing", f"c-{storage}", "clip.yaml"))
    assert not lake.exists(lake.path("_staging"))


def test_reingest_replaces_partitions(tmp_path: Path) -> None:
    clip = write_clip(tmp_path / "clip", MiniClip(seconds=0.2, points=100, cameras=()))
    lake = Lake(tmp_path / "lake")
    run_ingest(lake, clip)
    run_ingest(lake, clip)
    assert count(Catalog(lake, read_only=True), "SELECT count(*) FROM lidar_points") == 400


@requires_real_data("bags/ouster_os1_128_3frames_ros2")
def test_ouster_real_bag(tmp_path: Path) -> None:
    lake = Lake(tmp_path / "lake")
    rep = run_ingest(lake, OUSTER_FIXTURE, REAL_DATA_INGEST)
    assert any("no pose" in n for n in rep.notes)
    cat = Catalog(lake)
    cid = "ouster-os1-128-real"
    assert cat.query("SELECT has_ins FROM agents").to_pylist() == [{"has_ins": False}]
    frames = cat.query("SELECT * FROM lidar_frames ORDER BY frame_idx").to_pylist()
    assert [r["n_points"] + r["n_nan"] + r["n_zero"] for r in frames] == [131072] * 3
    assert frames[0]["stamp_ns"] == 1650410295350216000
    for r in frames:  # uint32 ns from the header stamp -> absolute, ~one revolution
        assert r["t_start_ns"] == r["stamp_ns"]
        assert 99_000_000 < r["t_end_ns"] - r["t_start_ns"] < 100_100_000
    assert count(cat, "SELECT count(DISTINCT ring) FROM lidar_points") == 128
    assert count(cat, "SELECT count(*) FROM imu") == 30
    assert count(cat, f"SELECT count(*) FROM raw.ins WHERE clip_id = '{cid}'") == 0
    cal = {r["sensor"]: r for r in cat.query("SELECT * FROM calibrated_sensors").to_pylist()}
    assert cal["IMU"]["tx"] == pytest.approx(0.006253) and cal["IMU"]["source"] == "tf_static"
    # the landing zone holds the bag, and a clip.yaml that points at it
    land = yaml.safe_load(lake.read_bytes(lake.path("landing", cid, "clip.yaml")))
    assert lake.exists(lake.path("landing", cid, land["agents"][0]["bag"], "metadata.yaml"))


def _real_clip(tmp: Path, cid: str, bag: str, topic: str, typ: str) -> Path:
    d = tmp / cid
    d.mkdir()
    (d / "clip.yaml").write_text(yaml.safe_dump({
        "clip_id": cid, "location": "x", "road_type": "local", "weather": "clear",
        "lighting": "day", "agents": [{
            "agent_id": "a", "kind": "vehicle", "role": "reference", "bag": str(REAL / bag),
            "sensors": [{"name": "LIDAR_TOP", "modality": "lidar", "topic": topic,
                         "msg_type": typ, "fields": {"time": {
                             "field": "time", "unit": "s", "reference": "header"}}}]}]}))
    return d


@requires_real_data("bags/nebula_vlp16_packets_only")
def test_vlp16_packets_only_is_a_clear_error(tmp_path: Path) -> None:
    d = _real_clip(tmp_path, "vlp", "nebula_vlp16_packets_only", "/velodyne_packets",
                   "velodyne_msgs/msg/VelodyneScan")
    lake = Lake(tmp_path / "lake")
    with pytest.raises(ClipError) as e:
        run_ingest(lake, d, REAL_DATA_INGEST)
    msg = str(e.value)
    assert e.value.topic == "/velodyne_packets" and "nebula_vlp16_packets_only" in msg
    assert "velodyne_msgs/msg/VelodyneScan" in msg and "PointCloud2" in msg
    assert raw_is_empty(lake, "vlp") and not lake.exists(lake.path("_staging"))
    assert count(Catalog(lake), "SELECT count(*) FROM lidar_points") == 0


@requires_real_data("bags/nebula_hesai_qt128_empty_storage_id")
def test_qt128_empty_storage_identifier(tmp_path: Path) -> None:
    d = _real_clip(tmp_path, "qt", "nebula_hesai_qt128_empty_storage_id", "/pandar_packets",
                   "pandar_msgs/msg/PandarScan")
    lake = Lake(tmp_path / "lake")
    # without recovery: the file and the field are named
    with pytest.raises(ClipError) as e:
        run_ingest(lake, d, REAL_DATA_INGEST.model_copy(update={
            "recover_empty_storage_id": False}))
    assert e.value.path and e.value.path.endswith("metadata.yaml")
    assert "storage_identifier" in str(e.value)
    # with the documented recovery the bag opens (sqlite3 detected) and fails on the packets
    with pytest.raises(ClipError) as e2:
        run_ingest(lake, d, REAL_DATA_INGEST)
    assert e2.value.topic == "/pandar_packets" and "pandar_msgs/msg/PandarScan" in str(e2.value)
    assert raw_is_empty(lake, "qt")


@pytest.mark.parametrize("storage", ["sqlite3", "mcap", "ros1"])
def test_truncated_bag(tmp_path: Path, storage: str) -> None:
    clip = write_clip(tmp_path / "clip", MiniClip(storage=storage, seconds=0.5, points=3000,
                                                  clip_id="trunc"))
    data = clip / "black.bag" if storage == "ros1" else next(
        p for p in (clip / "black").iterdir() if p.suffix in (".db3", ".mcap"))
    raw = data.read_bytes()
    data.write_bytes(raw[: int(len(raw) * 0.6)])
    lake = Lake(tmp_path / "lake")
    with pytest.raises(ClipError) as e:
        run_ingest(lake, clip)
    assert e.value.agent_id == "black" and "black" in (e.value.path or "")
    assert raw_is_empty(lake, "trunc")  # agent red had been ingested fine: nothing published


def test_missing_topic_is_named(tmp_path: Path) -> None:
    clip = write_clip(tmp_path / "clip", MiniClip(seconds=0.2, points=100, clip_id="miss"))
    cfg = yaml.safe_load((clip / "clip.yaml").read_text())
    cfg["agents"][1]["sensors"][0]["topic"] = "/black/lidar/nope"
    (clip / "clip.yaml").write_text(yaml.safe_dump(cfg))
    lake = Lake(tmp_path / "lake")
    with pytest.raises(ClipError) as e:
        run_ingest(lake, clip)
    assert e.value.topic == "/black/lidar/nope" and e.value.agent_id == "black"
    assert "/black/lidar/points" in str(e.value)  # what the bag does have
    assert raw_is_empty(lake, "miss")


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_custom_type_definition_from_bag_or_clip_yaml(tmp_path: Path, storage: str) -> None:
    """rosbags writes the .msg text into the bag; a bag carrying it needs no
    message_definitions, and a wrong .msg path in clip.yaml is a named error."""
    clip = write_clip(tmp_path / "clip", MiniClip(seconds=0.2, points=100, clip_id="def",
                                                  storage=storage, cameras=()))
    cfg = yaml.safe_load((clip / "clip.yaml").read_text())
    cfg["message_definitions"] = []
    (clip / "clip.yaml").write_text(yaml.safe_dump(cfg))
    lake = Lake(tmp_path / "lake")
    run_ingest(lake, clip)
    assert lake.read_table("raw", "ins", clip_id="def").num_rows == 2 * 37
    cfg["message_definitions"] = ["msgs/v2xlake_msgs/msg/Missing.msg"]
    (clip / "clip.yaml").write_text(yaml.safe_dump(cfg))
    with pytest.raises(ClipError) as e:
        run_ingest(lake, clip)
    assert (e.value.path or "").endswith("Missing.msg")


def test_nan_points_dropped_and_counted(tmp_path: Path) -> None:
    clip = write_clip(tmp_path / "clip", MiniClip(seconds=0.3, points=1000, nan_fraction=0.1,
                                                  all_nan_frame=1, clip_id="nan", cameras=()))
    lake = Lake(tmp_path / "lake")
    rep = run_ingest(lake, clip)
    assert any("frame 1: no point with a return" in n for n in rep.notes)
    cat = Catalog(lake)
    fr = cat.query("SELECT agent_id, frame_idx, n_points, n_nan, t_start_ns, stamp_ns "
                   "FROM lidar_frames ORDER BY agent_id, frame_idx").to_pylist()
    assert all(r["n_points"] + r["n_nan"] == 1000 for r in fr)
    assert [r["n_points"] for r in fr if r["frame_idx"] == 1] == [0, 0]
    assert all(800 < r["n_points"] < 960 for r in fr if r["frame_idx"] != 1)
    assert count(cat, "SELECT count(*) FROM lidar_points") == sum(r["n_points"] for r in fr)
    assert count(cat, "SELECT count(*) FROM lidar_points WHERE isnan(x)") == 0


def test_clip_inputs_lists_every_file(tmp_path: Path) -> None:
    clip = write_clip(tmp_path / "clip", MiniClip(seconds=0.1, points=10, storage="ros1"))
    cid, files = clip_inputs(clip)
    names = sorted(p.name for p in files)
    assert cid == "mini"
    assert names == sorted(["clip.yaml", "red.bag", "black.bag", "InsPva.msg",
                            "annotations.json"])


# --------------------------------------------------------------------------- unit level
def _cloud_msg(arr: np.ndarray, fields: list[tuple[str, int, int, int]], big: bool = False,
               pad: int = 0, height: int = 1) -> Any:
    from types import SimpleNamespace as NS

    step = arr.dtype.itemsize
    width = arr.size // height
    rows = arr.view(np.uint8).reshape(height, width * step)
    data = np.concatenate([rows, np.zeros((height, pad), np.uint8)], axis=1).ravel()
    return NS(height=height, width=width, point_step=step, row_step=width * step + pad,
              is_bigendian=big, data=data,
              fields=[NS(name=n, offset=o, datatype=d, count=c) for n, o, d, c in fields])


def test_pointcloud_layouts() -> None:
    from v2xlake.schemas.clip import LidarFields
    from v2xlake.tasks.ingest.pointcloud import decode_cloud, point_times_ns

    n = 12
    dt = np.dtype({"names": ["x", "y", "z", "t", "ring"], "formats": [">f4", ">f4", ">f4",
                                                                       ">u4", ">u2"],
                   "offsets": [0, 4, 8, 16, 20], "itemsize": 24})
    a = np.zeros(n, dt)
    a["x"], a["y"], a["z"] = np.arange(n), -np.arange(n), 2.0
    a["t"] = np.arange(n) * 1000
    a["ring"] = np.arange(n) % 4
    a["x"][3] = np.inf
    fields = [("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1), ("t", 16, 6, 1),
              ("ring", 20, 4, 1)]
    msg = _cloud_msg(a, fields, big=True, pad=8, height=3)
    lf = LidarFields(intensity=None, ring="ring", time=PointTimeField(
        field="t", unit=TimeUnit.NS, reference=TimeReference.HEADER))
    c = decode_cloud(msg, lf, stamp_ns=5_000)
    assert c.n_nan == 1 and c.n_points == 11
    assert c.x.tolist() == [float(i) for i in range(n) if i != 3]
    assert c.t_ns.tolist() == [5_000 + i * 1000 for i in range(n) if i != 3]
    assert c.ring.dtype == np.uint16 and c.ring.tolist() == [i % 4 for i in range(n) if i != 3]
    assert c.intensity.tolist() == [0.0] * 11 and (c.t_start_ns, c.t_end_ns) == (5_000, 16_000)
    # float seconds relative to the header, and absolute float64 seconds
    rel = PointTimeField(field="t", unit=TimeUnit.S, reference=TimeReference.HEADER)
    assert point_times_ns(np.array([0.0, 0.5], np.float32), rel, 10).tolist() == [10, 500_000_010]
    ab = PointTimeField(field="t", unit=TimeUnit.S, reference=TimeReference.ABSOLUTE)
    t = point_times_ns(np.array([1_700_000_000.123456]), ab, 1_700_000_000_100_000_000)
    assert abs(int(t[0]) - 1_700_000_000_123_456_000) < 300
    us = PointTimeField(field="t", unit=TimeUnit.US, reference=TimeReference.ABSOLUTE)
    assert point_times_ns(np.array([7], np.uint64), us, 0).tolist() == [7_000]
    with pytest.raises(KeyError, match="time field 'nope'"):
        decode_cloud(msg, LidarFields(time=PointTimeField(field="nope", unit=TimeUnit.NS,
                                                          reference=TimeReference.HEADER),
                                      intensity=None), 0)


def test_images_to_png() -> None:
    from types import SimpleNamespace as NS

    from v2xlake.tasks.ingest.images import compressed_to_png, image_to_png, png_size

    rng = np.random.default_rng(1)
    rgb = rng.integers(0, 255, (5, 7, 3), dtype=np.uint8)
    step = 7 * 3 + 3  # padded rows
    buf = np.zeros((5, step), np.uint8)
    buf[:, :21] = rgb.reshape(5, 21)
    png, w, h = image_to_png(NS(encoding="rgb8", height=5, width=7, step=step, is_bigendian=0,
                                data=buf.ravel()))
    assert (w, h) == (7, 5) == png_size(png)
    back = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
    assert back is not None and np.array_equal(back[..., ::-1], rgb)  # lossless, BGR on disk
    mono16 = rng.integers(0, 65535, (4, 6), dtype=np.uint16)
    png, _, _ = image_to_png(NS(encoding="mono16", height=4, width=6, step=12, is_bigendian=0,
                                data=mono16.view(np.uint8).ravel()))
    back16 = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
    assert back16 is not None and np.array_equal(back16, mono16)
    _ok, jpg = cv2.imencode(".jpg", rgb)
    png, w, h = compressed_to_png(NS(format="jpeg", data=jpg.ravel()))
    assert png.startswith(b"\x89PNG") and (w, h) == (7, 5)
    with pytest.raises(ValueError, match="unsupported image encoding"):
        image_to_png(NS(encoding="yuv422", height=1, width=1, step=2, is_bigendian=0,
                        data=np.zeros(2, np.uint8)))


def test_tf_chain_lookup() -> None:
    from v2xlake.schemas.geometry import Transform
    from v2xlake.tasks.ingest.calibration import TfTree

    tree = TfTree(IngestConfig().quat_tolerance)
    T_base_mount = Transform(translation=[1, 0, 2], rotation=[0.7071067811865476, 0, 0,
                                                               0.7071067811865476]).matrix()
    T_mount_lidar = Transform(translation=[0, 0.5, 0], rotation=[1, 0, 0, 0]).matrix()
    T_base_imu = Transform(translation=[0, 0, 0.1], rotation=[1, 0, 0, 0]).matrix()
    tree.add("base_link", "mount", T_base_mount)
    tree.add("mount", "lidar", T_mount_lidar)
    tree.add("/base_link", "imu", T_base_imu)
    T = tree.lookup("base_link", "lidar")
    assert T is not None and np.allclose(T, T_base_mount @ T_mount_lidar)
    T2 = tree.lookup("imu", "lidar")  # through the common parent, one edge inverted
    assert T2 is not None and np.allclose(T2, np.linalg.inv(T_base_imu) @ T)
    assert tree.lookup("base_link", "camera") is None
    assert np.allclose(tree.lookup("lidar", "lidar"), np.eye(4))  # type: ignore[arg-type]


@requires_real_data("bags/ouster_os1_128_3frames_ros2")
def test_ouster_fixture_points_at_shared_data() -> None:
    cfg = yaml.safe_load((OUSTER_FIXTURE / "clip.yaml").read_text())
    bag = (OUSTER_FIXTURE / cfg["agents"][0]["bag"]).resolve()
    assert bag == (REAL / "ouster_os1_128_3frames_ros2").resolve() and bag.is_dir()
    assert shutil.disk_usage(bag).total > 0


def test_pose_quaternions_follow_the_configured_tolerance() -> None:
    """``ingest.quat_tolerance`` is the one tolerance for pose quaternions too (the pose
    builders once had 1e-3 written in twice, whatever the parameter said)."""
    from v2xlake.tasks.ingest.pose import PoseError, unit_quaternions

    q = np.array([[0.0, 0.0, 0.0, 1.002]])  # norm 1.002
    with pytest.raises(PoseError, match=r"tolerance 0\.001: ingest\.quat_tolerance"):
        unit_quaternions(q, IngestConfig().quat_tolerance, "INS")
    assert np.allclose(unit_quaternions(q, 0.01), [[0, 0, 0, 1]])
