"""Nonsense in, a clear error out (#12, #16): each case is a clip built with rosbags directly
whose one defect must end in a ``ClipError`` naming clip, agent, topic and reason (or in a
QA finding), and the cases that are not defects (a FOV-limited scan, a 20 Hz camera, a
100 Hz INS, no-return points, a JPEG camera) must go through."""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import yaml
from rosbags.rosbag2 import Writer
from scipy.spatial.transform import Rotation

from tests.fixtures.real import REAL_DATA_INGEST, SHARED_REAL, requires_real_data
from tests.test_pose_sources import LAG, T0, T_EGO_LIDAR, _cloud, _hdr, _tf, _ts, _v3
from v2xlake.schemas.errors import ClipError
from v2xlake.storage.catalog import Catalog
from v2xlake.storage.lake import Lake
from v2xlake.tasks.anonymize.images import decode_image
from v2xlake.tasks.ingest import run_ingest
from v2xlake.tasks.ingest.images import jpeg_size
from v2xlake.tasks.qa.config import QaConfig, ScanSpan
from v2xlake.tasks.qa.stage import run_qa

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"
Q_LIDAR = Rotation.from_matrix(T_EGO_LIDAR[:3, :3]).as_quat(scalar_first=True).tolist()


def lidar_sensor(**kw: Any) -> dict[str, Any]:
    return {"name": "LIDAR_TOP", "modality": "lidar", "topic": "/lidar",
            "msg_type": "sensor_msgs/msg/PointCloud2", "rate_hz": 10,
            "extrinsic": {"translation": T_EGO_LIDAR[:3, 3].tolist(), "rotation": Q_LIDAR},
            "fields": {"time": {"field": "t", "unit": "ns", "reference": "header"}}, **kw}


def scans(ts: Any, n: int = 4, start: int = T0) -> list[tuple[str, str, int, Any]]:
    return [("/lidar", "sensor_msgs/msg/PointCloud2", t + 99_000_000 + LAG,
             _cloud(ts, t, k)) for k, t in enumerate(range(start, start + n * 100_000_000,
                                                           100_000_000))]


def imu_msg(ts: Any, t: int) -> Any:
    T = ts.types
    return T["sensor_msgs/msg/Imu"](
        header=_hdr(ts, t, "base_link"),
        orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=np.zeros(9), angular_velocity=_v3(ts, [0, 0, 0.1]),
        angular_velocity_covariance=np.zeros(9), linear_acceleration=_v3(ts, [0, 0, 9.81]),
        linear_acceleration_covariance=np.zeros(9))


def write(d: Path, agents: list[dict[str, Any]], bags: dict[str, list[tuple[str, str, int, Any]]],
          **top: Any) -> Path:
    """A clip folder: one bag per agent (messages sorted by log time) and its clip.yaml."""
    d.mkdir(parents=True, exist_ok=True)
    ts = _ts()
    for name, msgs in bags.items():
        with Writer(d / name, version=8) as w:
            conns: dict[str, Any] = {}
            for topic, typ, log_t, msg in sorted(msgs, key=lambda m: m[2]):
                if topic not in conns:
                    conns[topic] = w.add_connection(topic, typ, typestore=ts)
                w.write(conns[topic], log_t, ts.serialize_cdr(msg, typ))
    cfg = {"clip_id": d.name, "location": "x", "road_type": "local", "weather": "clear",
           "lighting": "day", "agents": agents, **top}
    (d / "clip.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    return d


def agent(aid: str = "car", sensors: list[dict[str, Any]] | None = None, **kw: Any
          ) -> dict[str, Any]:
    return {"agent_id": aid, "kind": "vehicle", "role": "reference", "bag": f"bag_{aid}",
            "tf_static_topic": None, "sensors": sensors or [lidar_sensor()], **kw}


def ingest_error(d: Path) -> ClipError:
    with pytest.raises(ClipError) as e:
        run_ingest(Lake(d.parent / f"lake-{d.name}"), d)
    return e.value


# --------------------------------------------------------------------------- clip.yaml
def test_unknown_key_is_named_with_the_known_one(tmp_path: Path) -> None:
    ts = _ts()
    s = lidar_sensor()
    s["extrinsics"] = s.pop("extrinsic")
    d = write(tmp_path / "typo", [agent(sensors=[s])], {"bag_car": scans(ts)})
    err = ingest_error(d)
    assert (err.clip_id, err.agent_id) == ("typo", "car")
    assert "agents[car].sensors[LIDAR_TOP]: unknown key 'extrinsics' (did you mean " \
        "'extrinsic'?)" in err.reason
    # inside a pose block (a union): the key is named with its place, no union tag
    d = write(tmp_path / "typo2", [agent(pose={"kind": "odometry", "sensor": "LIDAR_TOP",
                                               "datum": {"kind": "local", "ofset": [0, 0, 0]}})],
              {"bag_car": scans(ts)})
    assert "agents[car].pose.datum: unknown key 'ofset' (did you mean 'offset'?)" in \
        ingest_error(d).reason
    # a key that is missing is named too
    d = write(tmp_path / "typo3", [agent(pose={"kind": "odometry", "datum": {"kind": "local"}})],
              {"bag_car": scans(ts)})
    assert "agents[car].pose: missing key 'sensor'" in ingest_error(d).reason


def test_empty_sensor_list_names_the_agent(tmp_path: Path) -> None:
    d = write(tmp_path / "empty", [agent(), agent("rsu", role="cooperative")],
              {"bag_car": scans(_ts())})
    cfg = yaml.safe_load((d / "clip.yaml").read_text())
    cfg["agents"][1]["sensors"] = []
    (d / "clip.yaml").write_text(yaml.safe_dump(cfg))
    err = ingest_error(d)
    assert err.agent_id == "rsu" and "agents[rsu].sensors: List should have at least 1 item" \
        in err.reason


# --------------------------------------------------------------------------- LiDAR
def test_header_relative_time_declared_absolute_and_the_converse(tmp_path: Path) -> None:
    ts = _ts()
    d = write(tmp_path / "abs", [agent(sensors=[lidar_sensor(fields={"time": {
        "field": "t", "unit": "ns", "reference": "absolute"}})])], {"bag_car": scans(ts)})
    err = ingest_error(d)
    assert (err.agent_id, err.topic) == ("car", "/lidar")
    assert "declared absolute" in err.reason and "set reference: header" in err.reason
    # Ouster-style uint32 ns read as seconds from the header: a unit error, named as such
    d = write(tmp_path / "unit", [agent(sensors=[lidar_sensor(fields={"time": {
        "field": "t", "unit": "s", "reference": "header"}})])], {"bag_car": scans(ts)})
    assert "check the unit" in ingest_error(d).reason


def test_float_field_mapped_to_ring_is_refused(tmp_path: Path) -> None:
    d = write(tmp_path / "ring", [agent(sensors=[lidar_sensor(fields={
        "ring": "intensity", "time": {"field": "t", "unit": "ns", "reference": "header"}})])],
        {"bag_car": scans(_ts())})
    # intensity is 10.0 everywhere: whole numbers, so it is accepted as a float ring ...
    run_ingest(Lake(tmp_path / "lake"), d)
    # ... but x is not
    d = write(tmp_path / "ring2", [agent(sensors=[lidar_sensor(fields={
        "ring": "x", "time": {"field": "t", "unit": "ns", "reference": "header"}})])],
        {"bag_car": scans(_ts())})
    err = ingest_error(d)
    assert err.topic == "/lidar" and "ring field 'x' is float32 with non-integer" in err.reason


def test_zero_range_points_dropped_and_counted(tmp_path: Path) -> None:
    ts = _ts()
    msgs = scans(ts, 2)
    cloud = msgs[0][3]
    a = np.frombuffer(cloud.data, dtype=np.uint8).copy()
    rec = a.view(np.dtype({"names": ["x", "y", "z"], "formats": ["<f4"] * 3,
                           "offsets": [0, 4, 8], "itemsize": 24}))
    rec["x"][:100], rec["y"][:100], rec["z"][:100] = 0.0, 0.0, 0.0
    rec["x"][100:110] = np.nan
    msgs[0] = (*msgs[0][:3], type(cloud)(**{**cloud.__dict__, "data": a}))
    d = write(tmp_path / "zero", [agent()], {"bag_car": msgs})
    lake = Lake(tmp_path / "lake")
    run_ingest(lake, d)
    f = lake.read_table("raw", "lidar_frames", clip_id="zero").sort_by("frame_idx").to_pylist()
    assert (f[0]["n_zero"], f[0]["n_nan"], f[0]["n_points"]) == (100, 10, 2880 - 110)
    assert (f[1]["n_zero"], f[1]["n_nan"]) == (0, 0)
    pts = lake.read_table("raw", "lidar_points", clip_id="zero")
    r = np.hypot(pts["x"].to_numpy(), pts["y"].to_numpy())
    assert r.min() > 1.0  # no point left at the sensor origin


def test_fov_limited_scans_pass_when_declared(tmp_path: Path) -> None:
    """A VLP-32C limited to a 180 deg FOV spans 50 ms of its 100 ms period."""
    ts = _ts()
    msgs = scans(ts, 3)
    for _, _, _, m in msgs:
        a = np.frombuffer(m.data, dtype=np.uint8).view(np.dtype(
            {"names": ["t"], "formats": ["<u4"], "offsets": [16], "itemsize": 24}))
        a["t"] //= 2  # the same points over half the period  # type: ignore[misc]
    d = write(tmp_path / "fov", [agent()], {"bag_car": msgs})
    lake = Lake(tmp_path / "lake")
    run_ingest(lake, d)
    with pytest.raises(ClipError, match=r"scan_time_span: .*median 49\.86 ms, expected "
                       r"100\.0\.\.105\.0 ms"):
        run_qa(lake, "fov", QaConfig(scan_span=ScanSpan(min=1.0)))
    cfg = yaml.safe_load((d / "clip.yaml").read_text())
    cfg["agents"][0]["sensors"][0]["scan_fov_deg"] = 180
    (d / "clip.yaml").write_text(yaml.safe_dump(cfg))
    run_ingest(lake, d)
    assert run_qa(lake, "fov", QaConfig(scan_span=ScanSpan(min=0.9))).metrics["errors"] == 0


# --------------------------------------------------------------------------- time and order
def test_lidar_stamps_going_backwards_is_a_qa_error(tmp_path: Path) -> None:
    ts = _ts()
    msgs = scans(ts, 4)
    # scan 2 is stamped before scan 1 but arrives after it (its log time is later)
    msgs[1], msgs[2] = (msgs[1][0], msgs[1][1], msgs[1][2], msgs[2][3]), \
        (msgs[2][0], msgs[2][1], msgs[2][2], msgs[1][3])
    d = write(tmp_path / "back", [agent()], {"bag_car": msgs})
    lake = Lake(tmp_path / "lake")
    run_ingest(lake, d)
    with pytest.raises(ClipError, match=r"stamps_increasing: 1 of 4 header stamps on /lidar go "
                       r"back in time \(bag order\)") as e:
        run_qa(lake, "back")
    assert (e.value.agent_id, e.value.topic) == ("car", "/lidar")


def test_duplicated_imu_and_gnss_messages_are_dropped_and_counted(tmp_path: Path) -> None:
    ts = _ts()
    T = ts.types
    msgs = scans(ts, 3)
    for t in range(T0, T0 + 300_000_000, 10_000_000):
        msgs.append(("/imu", "sensor_msgs/msg/Imu", t + 1_000_000, imu_msg(ts, t)))
        if t % 50_000_000 == 0:  # every fifth sample delivered twice
            msgs.append(("/imu", "sensor_msgs/msg/Imu", t + 2_000_000, imu_msg(ts, t)))
        if t % 100_000_000 == 0:
            fix = T["sensor_msgs/msg/NavSatFix"](
                header=_hdr(ts, t, "base_link"),
                status=T["sensor_msgs/msg/NavSatStatus"](status=2, service=1), latitude=48.0,
                longitude=11.0, altitude=500.0, position_covariance=np.zeros(9),
                position_covariance_type=0)
            msgs += [("/fix", "sensor_msgs/msg/NavSatFix", t + 40_000_000, fix)] * 2
    sensors = [lidar_sensor(),
               {"name": "IMU", "modality": "imu", "topic": "/imu",
                "msg_type": "sensor_msgs/msg/Imu", "rate_hz": 100},
               {"name": "GNSS", "modality": "gnss", "topic": "/fix",
                "msg_type": "sensor_msgs/msg/NavSatFix", "rate_hz": 10}]
    d = write(tmp_path / "dup", [agent(sensors=sensors)], {"bag_car": msgs})
    lake = Lake(tmp_path / "lake")
    rep = run_ingest(lake, d)
    assert any("IMU: 6 message(s) on /imu repeat an earlier stamp: dropped" in n
               for n in rep.notes)
    assert lake.read_table("raw", "imu", clip_id="dup").num_rows == 30
    assert lake.read_table("raw", "gnss", clip_id="dup").num_rows == 3
    s = {r["sensor"]: r for r in lake.read_table("raw", "sensors", clip_id="dup").to_pylist()}
    assert (s["IMU"]["n_messages"], s["IMU"]["n_duplicates"]) == (30, 6)
    assert (s["GNSS"]["n_messages"], s["GNSS"]["n_duplicates"]) == (3, 3)
    qa = run_qa(lake, "dup")
    assert any("duplicate_messages car/IMU: 6 message(s) on /imu repeat an earlier stamp "
               "(dropped at ingest)" in n for n in qa.notes)


def test_agents_that_never_recorded_together_are_refused(tmp_path: Path) -> None:
    ts = _ts()
    d = write(tmp_path / "apart", [agent(), agent("other", role="cooperative")],
              {"bag_car": scans(ts, 3), "bag_other": scans(ts, 3, start=T0 + 3_600_000_000_000)})
    err = ingest_error(d)
    assert err.agent_id == "other" and "do not overlap in time" in err.reason


def test_rates_other_than_the_cats_rig_pass(tmp_path: Path) -> None:
    """20 Hz camera, 100 Hz INS-like IMU, 10 Hz LiDAR: QA uses the declared rates; a
    declared rate the stamps contradict is an error naming both."""
    ts = _ts()
    msgs = scans(ts, 5)
    for t in range(T0, T0 + 500_000_000, 10_000_000):
        msgs.append(("/imu", "sensor_msgs/msg/Imu", t + 1_000_000, imu_msg(ts, t)))
    jpg = _jpeg(64, 48)
    for t in range(T0, T0 + 500_000_000, 50_000_000):
        msgs += _camera(ts, t, jpg, (64, 48))
    sensors = [lidar_sensor(), _cam_sensor(20),
               {"name": "IMU", "modality": "imu", "topic": "/imu",
                "msg_type": "sensor_msgs/msg/Imu", "rate_hz": 100}]
    d = write(tmp_path / "rates", [agent(sensors=sensors, tf_static_topic="/tf_static")],
              {"bag_car": [*msgs, _static(ts)]})
    lake = Lake(tmp_path / "lake")
    run_ingest(lake, d)
    rep = run_qa(lake, "rates")
    assert rep.metrics["errors"] == 0 and rep.metrics["warnings"] >= 1  # no pose: a warning
    cfg = yaml.safe_load((d / "clip.yaml").read_text())
    cfg["agents"][0]["sensors"][1]["rate_hz"] = 30
    (d / "clip.yaml").write_text(yaml.safe_dump(cfg))
    run_ingest(lake, d)
    with pytest.raises(ClipError, match=r"rate: /cam: declared 30 Hz, stamps show 20\.000 Hz"):
        run_qa(lake, "rates")


# --------------------------------------------------------------------------- calibration
def _static(ts: Any, q: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
            ) -> tuple[str, str, int, Any]:
    m = np.eye(4)
    tf = _tf(ts, T0, "base_link", "camera", m)
    tf.transform.rotation.w, tf.transform.rotation.x = q[0], q[1]
    tf.transform.rotation.y, tf.transform.rotation.z = q[2], q[3]
    return ("/tf_static", "tf2_msgs/msg/TFMessage", T0,
            ts.types["tf2_msgs/msg/TFMessage"](transforms=[tf]))


def _jpeg(w: int, h: int) -> bytes:
    rng = np.random.default_rng(0)
    ok, buf = cv2.imencode(".jpg", rng.integers(0, 255, (h, w, 3), dtype=np.uint8))
    assert ok
    return bytes(buf.ravel())


def _camera(ts: Any, t: int, jpg: bytes, info_size: tuple[int, int]
            ) -> list[tuple[str, str, int, Any]]:
    T = ts.types
    w, h = info_size
    info = T["sensor_msgs/msg/CameraInfo"](
        header=_hdr(ts, t, "camera"), height=h, width=w, distortion_model="plumb_bob",
        d=np.zeros(5), k=np.array([w * 0.8, 0, w / 2, 0, w * 0.8, h / 2, 0, 0, 1.0]),
        r=np.eye(3).ravel(), p=np.zeros(12), binning_x=0, binning_y=0,
        roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                  do_rectify=False))
    img = T["sensor_msgs/msg/CompressedImage"](header=_hdr(ts, t, "camera"), format="jpeg",
                                               data=np.frombuffer(jpg, np.uint8))
    return [("/cam", "sensor_msgs/msg/CompressedImage", t + 25_000_000, img),
            ("/cam_info", "sensor_msgs/msg/CameraInfo", t + 25_000_000, info)]


def _cam_sensor(rate: float = 30) -> dict[str, Any]:
    return {"name": "CAM_FRONT", "modality": "camera", "topic": "/cam",
            "msg_type": "sensor_msgs/msg/CompressedImage", "camera_info_topic": "/cam_info",
            "rate_hz": rate}


def test_non_unit_tf_static_quaternion_is_refused(tmp_path: Path) -> None:
    ts = _ts()
    jpg = _jpeg(64, 48)
    bag = [*scans(ts, 2), *_camera(ts, T0, jpg, (64, 48)),
           _static(ts, (0.9, 0.3, 0.0, 0.0))]  # norm 0.949: a typo, 37 deg if normalised
    d = write(tmp_path / "quat", [agent(sensors=[lidar_sensor(), _cam_sensor()],
                                        tf_static_topic="/tf_static")], {"bag_car": bag})
    err = ingest_error(d)
    assert (err.agent_id, err.topic) == ("car", "/tf_static")
    assert "transform base_link -> camera" in err.reason and "norm 0.948683" in err.reason


@pytest.mark.parametrize("size", [(64, 60), (32, 24)])
def test_image_size_must_match_its_intrinsics(tmp_path: Path, size: tuple[int, int]) -> None:
    ts = _ts()
    jpg = _jpeg(64, 48)
    bag = [*scans(ts, 2), *_camera(ts, T0, jpg, size), _static(ts)]
    d = write(tmp_path / "size", [agent(sensors=[lidar_sensor(), _cam_sensor()],
                                        tf_static_topic="/tf_static")], {"bag_car": bag})
    err = ingest_error(d)
    assert (err.clip_id, err.agent_id, err.topic) == ("size", "car", "/cam")
    assert (f"images are 64x48 but its CameraInfo intrinsics (topic /cam_info) are for "
            f"{size[0]}x{size[1]}") in err.reason


@requires_real_data("calib/pjlab_lidar2camera")
def test_real_calibration_for_1080_rows_on_a_1200_row_image(tmp_path: Path) -> None:
    """The real PJLab camera: its intrinsic file says 1920x1080, the image has 1200 rows."""
    import json

    calib = SHARED_REAL / "calib" / "pjlab_lidar2camera"
    p = json.loads((calib / "center_camera-intrinsic.json").read_text())[
        "center_camera-intrinsic"]["param"]
    K = np.array(p["cam_K"]["data"])
    img = cv2.imread(str(calib / "0.png"))
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 90])
    assert ok
    ts = _ts()
    cam = {**_cam_sensor(), "intrinsics": {
        "width": p["img_dist_w"], "height": p["img_dist_h"], "fx": float(K[0, 0]),
        "fy": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2])}}
    cam.pop("camera_info_topic")  # the calibration file's intrinsics, in clip.yaml
    bag = [*scans(ts, 2), _camera(ts, T0, bytes(buf.ravel()), (1, 1))[0], _static(ts)]
    d = write(tmp_path / "pjlab", [agent(sensors=[lidar_sensor(), cam],
                                         tf_static_topic="/tf_static")], {"bag_car": bag})
    err = ingest_error(d)
    assert "images are 1920x1200 but its clip.yaml intrinsics are for 1920x1080" in err.reason


def test_jpeg_is_stored_as_delivered_and_read_by_anonymize(tmp_path: Path) -> None:
    from v2xlake.tasks.anonymize.stage import run_anonymize

    ts = _ts()
    jpg = _jpeg(64, 48)
    assert jpeg_size(jpg) == (64, 48)
    bag = [*scans(ts, 2), *_camera(ts, T0, jpg, (64, 48)), _static(ts)]
    d = write(tmp_path / "jpg", [agent(sensors=[lidar_sensor(), _cam_sensor()],
                                       tf_static_topic="/tf_static")], {"bag_car": bag})
    lake = Lake(tmp_path / "lake")
    run_ingest(lake, d)
    row = lake.read_table("raw", "camera_frames", clip_id="jpg").to_pylist()[0]
    assert row["blob"].endswith(".jpg") and (row["width"], row["height"]) == (64, 48)
    blob = lake.read_blob("raw", row["blob"])
    assert blob == jpg and row["sha256"] == hashlib.sha256(jpg).hexdigest()
    assert decode_image(blob).shape == (48, 64, 3)  # the one reader anonymize uses
    run_anonymize(lake, "jpg")
    clean = lake.read_table("clean", "camera_frames", clip_id="jpg").to_pylist()[0]
    assert clean["blob"] == row["blob"][:-4] + ".png"  # named by what anonymize wrote
    assert decode_image(lake.read_blob("clean", clean["blob"])).shape == (48, 64, 3)


# --------------------------------------------------------------------------- real bags
@requires_real_data("bags/velodyne_vlp16_pointcloud2_ros2")
def test_real_vlp16_pointcloud2_float_second_time(tmp_path: Path) -> None:
    """The real VLP-16 bag: velodyne_pointcloud layout, time = float32 s from the header
    stamp, free-running stamps, no pose; ingested and QA'd through tests/fixtures/vlp16."""
    lake = Lake(tmp_path / "lake")
    rep = run_ingest(lake, FIXTURES / "vlp16", REAL_DATA_INGEST)
    assert rep.metrics["lidar_frames"] == 4
    cat = Catalog(lake)
    frames = cat.query("SELECT * FROM lidar_frames ORDER BY frame_idx").to_pylist()
    assert [f["n_points"] + f["n_nan"] + f["n_zero"] for f in frames] == [
        14885, 14845, 14868, 14816]
    for f in frames:  # float seconds from the stamp, at ns resolution; one revolution
        assert -10_000 < f["t_start_ns"] - f["stamp_ns"] < 10_000
        assert 99_000_000 < f["t_end_ns"] - f["t_start_ns"] < 100_300_000
    rings = cat.query("SELECT count(DISTINCT ring) AS n FROM lidar_points").to_pylist()
    assert rings[0]["n"] == 15
    qa = run_qa(lake, "velodyne-vlp16-real")
    assert qa.metrics["errors"] == 0
    assert any("free-running clock" in n for n in qa.notes)  # stamps are not PPS-locked


# --------------------------------------------------------------------------- radar
RADAR_DT = np.dtype({"names": ["x", "y", "z", "v_r", "rcs", "snr"],
                     "formats": ["<f4"] * 6, "offsets": [0, 4, 8, 12, 16, 20], "itemsize": 24})


def radar_scan(ts: Any, t: int, n: int = 300, seed: int = 0) -> Any:
    """A 4D imaging radar scan in a Continental ARS548-like layout: one time per scan."""
    rng = np.random.default_rng(seed)
    a = np.zeros(n, RADAR_DT)
    az = rng.uniform(-1.0, 1.0, n)
    r = rng.uniform(2.0, 150.0, n)
    a["x"], a["y"], a["z"] = r * np.cos(az), r * np.sin(az), rng.uniform(-1, 3, n)
    a["v_r"], a["rcs"], a["snr"] = rng.uniform(-20, 20, n), rng.uniform(-10, 30, n), 12.0
    a["x"][:5] = np.nan  # invalid detections: dropped and counted
    PF = ts.types["sensor_msgs/msg/PointField"]
    return ts.types["sensor_msgs/msg/PointCloud2"](
        header=_hdr(ts, t, "radar"), height=1, width=n,
        fields=[PF(name=k, offset=4 * i, datatype=7, count=1) for i, k in enumerate(
            RADAR_DT.names)], is_bigendian=False, point_step=24, row_step=24 * n,
        data=a.view(np.uint8), is_dense=False)


def radar_sensor() -> dict[str, Any]:
    return {"name": "RADAR_FRONT", "modality": "radar", "topic": "/radar/points",
            "msg_type": "sensor_msgs/msg/PointCloud2", "rate_hz": 20,
            "extrinsic": {"translation": [3.6, 0.0, 0.5], "rotation": [1.0, 0.0, 0.0, 0.0]},
            "fields": {"velocity": "v_r", "rcs": "rcs", "intensity": None, "ring": None}}


def test_radar_points_and_a_radar_only_agent(tmp_path: Path) -> None:
    """A vehicle with LiDAR + radar and a roadside agent with only a radar: radar scans land
    in radar_frames / radar_points (raw, then clean with relative time)."""
    from v2xlake.tasks.anonymize.stage import run_anonymize

    ts = _ts()
    radar = [("/radar/points", "sensor_msgs/msg/PointCloud2", t + 30_000_000,
              radar_scan(ts, t, seed=k)) for k, t in enumerate(range(T0, T0 + 400_000_000,
                                                                      50_000_000))]
    d = write(tmp_path / "radar", [
        agent(sensors=[lidar_sensor(), radar_sensor()]),
        agent("rsu", sensors=[radar_sensor()], role="cooperative", kind="roadside")],
        {"bag_car": [*scans(ts, 4), *radar], "bag_rsu": radar})
    lake = Lake(tmp_path / "lake")
    rep = run_ingest(lake, d)
    assert not [n for n in rep.notes if "radar" in n]
    frames = lake.read_table("raw", "radar_frames", clip_id="radar")
    assert frames.num_rows == 16 and set(frames["n_nan"].to_pylist()) == {5}
    pts = lake.read_table("raw", "radar_points", clip_id="radar", agent_id="rsu")
    assert pts.num_rows == 8 * 295 and pts.schema.field("velocity").type == "float"
    first = pts.filter(pts["frame_idx"].to_numpy() == 0)
    assert set(first["t_ns"].to_pylist()) == {T0}  # one time per scan: its stamp
    want = np.frombuffer(radar[0][3].data, RADAR_DT)[5:]
    assert np.array_equal(first["velocity"].to_numpy(), want["v_r"])
    assert np.array_equal(first["rcs"].to_numpy(), want["rcs"])
    assert run_qa(lake, "radar").metrics["errors"] == 0
    run_anonymize(lake, "radar")
    clean = Catalog(lake).query("SELECT min(t_ns) AS t FROM radar_points").to_pylist()
    assert clean[0]["t"] == 100_000_000  # the clip's relative axis


def test_radar_without_a_velocity_field_is_refused(tmp_path: Path) -> None:
    s = radar_sensor()
    s["fields"].pop("velocity")
    d = write(tmp_path / "nov", [agent(sensors=[lidar_sensor(), s])], {"bag_car": scans(_ts())})
    assert "radar sensor 'RADAR_FRONT' needs a 'fields' mapping with its radial velocity" in \
        ingest_error(d).reason


def test_no_pose_clip_keeps_its_anonymized_images(tmp_path: Path) -> None:
    """No pose at all: ingest, QA (a warning) and anonymize run, the anonymized images are
    in the clean zone; the absence is agents.has_ins false / pose_source 'none' / no
    ego_poses, and deskew and register say "not applicable"."""
    from v2xlake.tasks.anonymize.stage import run_anonymize
    from v2xlake.tasks.deskew.stage import run_deskew
    from v2xlake.tasks.register.stage import run_register

    ts = _ts()
    jpg = _jpeg(64, 48)
    bag = [*scans(ts, 4), _static(ts)]
    for k in range(8):
        bag += _camera(ts, T0 + k * 50_000_000, jpg, (64, 48))
    d = write(tmp_path / "nopose", [agent(sensors=[lidar_sensor(), _cam_sensor(20)],
                                          tf_static_topic="/tf_static", pose={"kind": "none"})],
              {"bag_car": bag})
    lake = Lake(tmp_path / "lake")
    run_ingest(lake, d)
    qa = run_qa(lake, "nopose")
    assert qa.metrics["errors"] == 0 and qa.metrics["warnings"] >= 1
    run_anonymize(lake, "nopose")
    frames = lake.read_table("clean", "camera_frames", clip_id="nopose").to_pylist()
    assert len(frames) == 8
    assert all(decode_image(lake.read_blob("clean", f["blob"])).shape == (48, 64, 3)
               for f in frames)
    a = lake.read_table("clean", "agents", clip_id="nopose").to_pylist()[0]
    assert (a["has_ins"], a["pose_source"], a["pose_frame"]) == (False, "none", None)
    assert lake.read_table("clean", "ego_poses", clip_id="nopose").num_rows == 0
    assert run_deskew(lake, "nopose").status == "not_applicable"
    assert run_register(lake, "nopose").status == "not_applicable"


# --------------------------------------------------------------------------- no pose
def _no_pose_clip(tmp_path: Path) -> Path:
    """A LiDAR + camera recording without any INS, as many roadside units deliver."""
    ts = _ts()
    jpg = _jpeg(64, 48)
    cams = [m for k in range(8) for m in _camera(ts, T0 + k * 50_000_000, jpg, (64, 48))]
    bag = [*scans(ts, 4), *cams, _static(ts)]
    return write(tmp_path / "nopose", [agent(sensors=[lidar_sensor(), _cam_sensor(rate=20)],
                                             tf_static_topic="/tf_static")], {"bag_car": bag})


@pytest.mark.slow
def test_no_pose_clip_runs_the_whole_flow(prefect_server: object, tmp_path: Path) -> None:
    """Issue #12: a clip without any pose was ingested and anonymized, then quarantined (and
    its anonymized images deleted) when deskew refused it. The stages that need poses now
    say why they do not apply, and what the others made stays."""
    from v2xlake.flows.pipeline import process_clip
    from v2xlake.storage.quarantine import is_quarantined

    lake = Lake(tmp_path / "lake")
    summary = process_clip(str(_no_pose_clip(tmp_path)), lake.uri)
    assert summary["status"] == "ok", summary
    status = {s["stage"]: s["status"] for s in summary["stages"]}
    assert status["ingest"] == status["anonymize"] == "done"
    for stage in ("deskew", "register", "align"):
        assert status[stage] == "not_applicable", (stage, status)
    reasons = {s["stage"]: s["report"]["reason"] for s in summary["stages"]}
    assert "car: agents.has_ins is false" in reasons["deskew"]
    assert not is_quarantined(lake, "nopose")
    assert lake.read_table("clean", "camera_frames", clip_id="nopose").num_rows == 8
