"""Pose sources as data (#12): bags written directly with rosbags in other drivers'
conventions — Odometry in a projected map frame with a large false origin, NavSatFix + Imu
orientation at other rates, a vendor INS with its own field names, degrees, yaw from east
and NED velocities, a fixed roadside pose — each with its bag log time lagging the header
stamps. Each goes through ingest and anonymize by a clip.yaml alone, and the clean
``ego_poses`` must reproduce the known motion (relative poses, sub-millimetre)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.compute as pc
import pytest
import yaml
from rosbags.rosbag2 import Writer
from rosbags.typesys import get_types_from_msg
from scipy.spatial.transform import Rotation

from tests.fixtures.minibag import T0, MiniClip, _cloud, _header, _quat, _store, _vec3
from tests.test_deskew import scipy_reference
from v2xlake.schemas.errors import ClipError
from v2xlake.storage.lake import Lake
from v2xlake.storage.reader import read_extrinsics
from v2xlake.tasks.anonymize.run import run_anonymize
from v2xlake.tasks.deskew.stage import run_deskew
from v2xlake.tasks.geodesy import LocalFrame
from v2xlake.tasks.ingest import run_ingest
from v2xlake.tasks.qa.core import run_qa
from v2xlake.tasks.reader import load_pose_track

ORIGIN = (48.137, 11.575, 520.0)  # the map frame's geodetic origin
OFFSET = np.array([691_000.0, 5_334_000.0, 0.0])  # a UTM-like false origin of the map
SECONDS = 1.0
VENDOR_MSG = """std_msgs/Header header
float64 Lat
float64 Lon
float64 Hgt
float32 RollDeg
float32 PitchDeg
float32 YawDegEastCcw
float32 VelE
float32 VelN
float32 VelD
uint8 SolStatus
"""
VENDOR_TYPE = "acme_ins/msg/Nav"


def truth(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A curving, climbing, rolling drive in the map's local ENU: (N, 3) p, (N, 3, 3) R."""
    s = (np.asarray(t, np.int64) - T0) / 1e9
    p = np.stack([15.0 * s + 2.0 * np.sin(0.7 * s), 4.0 * np.sin(0.9 * s), 0.3 * s], -1)
    yaw, pitch, roll = 0.4 + 0.5 * s, 0.03 * np.sin(2 * s), 0.02 * np.cos(3 * s)
    # body x forward / y left / z up; INS angles: pitch nose-up, roll right-wing-down
    R = Rotation.from_euler("ZYX", np.stack([yaw, -pitch, roll], -1)).as_matrix()
    return p, R


def _velocity(t: np.ndarray) -> np.ndarray:
    h = 1_000_000
    return (truth(t + h)[0] - truth(t - h)[0]) / 2e-3


def _msgs(kind: str, ts: Any) -> list[tuple[str, str, int, int, Any]]:
    """(topic, type, log time, header stamp, msg): log time lags the stamp by 35 ms."""
    T = ts.types
    out: list[tuple[str, str, int, int, Any]] = []
    lag = 35_000_000
    cfg = MiniClip(points=200)
    rng = np.random.default_rng(0)
    for i, t in enumerate(range(T0, T0 + int(SECONDS * 1e9), 100_000_000)):
        out.append(("/lidar", "sensor_msgs/msg/PointCloud2", t + 99_000_000 + lag, t,
                    _cloud(ts, rng, t, cfg, i, "lidar")))
    frame = LocalFrame(ORIGIN[0], ORIGIN[1])
    span = range(T0 - 50_000_000, T0 + int(SECONDS * 1e9) + 60_000_000, 10_000_000)
    if kind == "odometry":  # 50 Hz, projected map frame with a false origin
        for t in span[::2]:
            p, R = truth(np.array([t]))
            q = Rotation.from_matrix(R[0]).as_quat(scalar_first=True)
            v_body = R[0].T @ _velocity(np.array([t]))[0]
            pose = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](
                x=float(p[0, 0] + OFFSET[0]), y=float(p[0, 1] + OFFSET[1]),
                z=float(p[0, 2] + OFFSET[2])), orientation=_quat(ts, *q))
            tw = T["geometry_msgs/msg/Twist"](linear=_vec3(ts, *v_body),
                                              angular=_vec3(ts, 0.0, 0.0, 0.0))
            out.append(("/localization/odom", "nav_msgs/msg/Odometry", t + lag, t,
                        T["nav_msgs/msg/Odometry"](
                            header=_header(ts, t, "map"), child_frame_id="base_link",
                            pose=T["geometry_msgs/msg/PoseWithCovariance"](
                                pose=pose, covariance=np.zeros(36)),
                            twist=T["geometry_msgs/msg/TwistWithCovariance"](
                                twist=tw, covariance=np.zeros(36)))))
    elif kind == "navsat_imu":  # fixes at 20 Hz, orientation at 100 Hz
        for t in span:
            p, R = truth(np.array([t]))
            lat, lon, alt = frame.to_geodetic(p[0] + np.array([0.0, 0.0, ORIGIN[2]]))
            R_enu = frame.R_local_enu(lat, lon).reshape(3, 3).T @ R[0]
            q = Rotation.from_matrix(R_enu).as_quat(scalar_first=True)
            out.append(("/imu/data", "sensor_msgs/msg/Imu", t + lag, t, T["sensor_msgs/msg/Imu"](
                header=_header(ts, t, "imu"), orientation=_quat(ts, *q),
                orientation_covariance=np.zeros(9), angular_velocity=_vec3(ts, 0, 0, 0),
                angular_velocity_covariance=np.zeros(9),
                linear_acceleration=_vec3(ts, 0, 0, 9.81),
                linear_acceleration_covariance=np.zeros(9))))
            if (t - span[0]) % 50_000_000 == 0:
                out.append(("/gnss/fix", "sensor_msgs/msg/NavSatFix", t + 2 * lag, t,
                            T["sensor_msgs/msg/NavSatFix"](
                                header=_header(ts, t, "gnss"),
                                status=T["sensor_msgs/msg/NavSatStatus"](status=2, service=1),
                                latitude=float(lat), longitude=float(lon), altitude=float(alt),
                                position_covariance=np.zeros(9), position_covariance_type=0)))
    elif kind == "vendor":  # 100 Hz, degrees, yaw from east CCW, NED velocities
        for t in span:
            p, R = truth(np.array([t]))
            lat, lon, alt = frame.to_geodetic(p[0] + np.array([0.0, 0.0, ORIGIN[2]]))
            R_enu = frame.R_local_enu(lat, lon).reshape(3, 3).T @ R[0]
            yaw, negpitch, roll = Rotation.from_matrix(R_enu).as_euler("ZYX")
            v = frame.R_local_enu(lat, lon).reshape(3, 3).T @ _velocity(np.array([t]))[0]
            out.append(("/acme/nav", VENDOR_TYPE, t + lag, t, T[VENDOR_TYPE](
                header=_header(ts, t, "base_link"), Lat=float(lat), Lon=float(lon),
                Hgt=float(alt), RollDeg=math.degrees(roll), PitchDeg=math.degrees(-negpitch),
                YawDegEastCcw=math.degrees(yaw), VelE=float(v[0]), VelN=float(v[1]),
                VelD=float(-v[2]), SolStatus=4)))
    out.sort(key=lambda m: m[2])
    return out


def _clip(tmp: Path, kind: str) -> Path:
    d = tmp / kind
    d.mkdir(parents=True)
    ts = _store(False)
    if kind == "vendor":
        ts.register(get_types_from_msg(VENDOR_MSG, VENDOR_TYPE))
        msg_dir = d / "msgs" / "acme_ins" / "msg"
        msg_dir.mkdir(parents=True)
        (msg_dir / "Nav.msg").write_text(VENDOR_MSG)
    with Writer(d / "bag", version=8) as w:
        conns: dict[str, Any] = {}
        for topic, typ, log_t, _stamp, msg in _msgs(kind, ts):
            if topic not in conns:
                conns[topic] = w.add_connection(topic, typ, typestore=ts)
            w.write(conns[topic], log_t, ts.serialize_cdr(msg, typ))
    pose: dict[str, Any] = {
        "odometry": {"kind": "odometry", "topic": "/localization/odom",
                     "msg_type": "nav_msgs/msg/Odometry",
                     "datum": {"lat": ORIGIN[0], "lon": ORIGIN[1], "alt": ORIGIN[2],
                               "offset": OFFSET.tolist()}},
        "navsat_imu": {"kind": "navsat_imu", "topic": "/gnss/fix", "attitude_topic": "/imu/data"},
        "vendor": {"kind": "ins", "topic": "/acme/nav", "msg_type": VENDOR_TYPE,
                   "angle_unit": "deg", "heading": "east_ccw", "velocity_axes": "ned",
                   "fields": {"lat": "Lat", "lon": "Lon", "height": "Hgt", "roll": "RollDeg",
                              "pitch": "PitchDeg", "heading": "YawDegEastCcw",
                              "v_east": "VelE", "v_north": "VelN", "v_up": "VelD",
                              "status": "SolStatus"}},
        "fixed": {"kind": "fixed", "position": [ORIGIN[0], ORIGIN[1], ORIGIN[2]],
                  "attitude": [0.0, 0.0, 90.0]},
    }[kind]
    cfg: dict[str, Any] = {
        "clip_id": f"pose-{kind.replace('_', '-')}", "location": "x", "road_type": "arterial",
        "weather": "clear", "lighting": "day", "agents": [{
            "agent_id": "car", "kind": "roadside" if kind == "fixed" else "vehicle",
            "role": "reference", "bag": "bag", "tf_static_topic": None, "pose": pose,
            "sensors": [{"name": "LIDAR_TOP", "modality": "lidar", "topic": "/lidar",
                         "msg_type": "sensor_msgs/msg/PointCloud2", "rate_hz": 10,
                         "extrinsic": {"translation": [0.5, 0.0, 1.8],
                                       "rotation": [1.0, 0.0, 0.0, 0.0]},
                         "fields": {"time": {"field": "timestamp", "unit": "s",
                                             "reference": "absolute"}}}]}]}
    if kind == "vendor":
        cfg["message_definitions"] = ["msgs/acme_ins/msg/Nav.msg"]
    (d / "clip.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    return d


@pytest.mark.parametrize("kind", ["odometry", "navsat_imu", "vendor"])
def test_pose_source_reproduces_the_motion(tmp_path: Path, kind: str) -> None:
    lake = Lake(tmp_path / "lake")
    cid = run_ingest(lake, _clip(tmp_path, kind)).clip_id
    assert lake.read_table("raw", "agents", clip_id=cid).column("has_ins").to_pylist() == [True]
    qa = run_qa(lake, cid)  # the pose track covers every scan at its own rate
    assert qa.metrics["errors"] == 0 and not [n for n in qa.notes if "coverage" in n]
    run_anonymize(lake, cid)
    track = load_pose_track(lake, cid, "car")
    raw_t = lake.read_table("raw", "ins", clip_id=cid).column("t_ns").to_numpy()
    clean_t = track.t_ns
    t_abs = raw_t[np.isin(raw_t - raw_t[0], clean_t - clean_t[0])]
    M = track.matrices(clean_t)
    p, R = truth(t_abs)
    T_true = np.zeros((len(p), 4, 4))
    T_true[:, :3, :3], T_true[:, :3, 3], T_true[:, 3, 3] = R, p, 1.0
    # one rigid transform separates the clip world from the map: compare relative poses
    rel = np.linalg.inv(M[0]) @ M
    rel_true = np.linalg.inv(T_true[0]) @ T_true
    dp = np.linalg.norm(rel[:, :3, 3] - rel_true[:, :3, 3], axis=1).max()
    dR = max(np.linalg.norm(Rotation.from_matrix(a.T @ b).as_rotvec())
             for a, b in zip(rel[:, :3, :3], rel_true[:, :3, :3], strict=True))
    assert dp < 1e-3, f"{kind}: {dp * 1e3:.3f} mm"
    assert dR < 1e-5, f"{kind}: {dR:.2e} rad"
    # velocities (ENU axes; the body twist and the NED velocities converted): the speed
    ego = lake.read_table("clean", "ego_poses", clip_id=cid).sort_by("t_ns")
    speed = np.linalg.norm(np.stack([ego[c].to_numpy() for c in ("vx", "vy", "vz")], 1), axis=1)
    true_speed = np.linalg.norm(_velocity(t_abs), axis=1)
    tol = 0.05 if kind == "navsat_imu" else 1e-3  # finite differences of 20 Hz fixes
    assert np.abs(speed[1:-1] - true_speed[1:-1]).max() < tol
    # deskew on this track is exact against per-point SciPy interpolation of the same poses
    rep = run_deskew(lake, cid)
    assert rep.status == "done" and rep.metrics["n_frames_skipped"] == 0
    raw = lake.read_table("clean", "lidar_points", clip_id=cid)
    out = lake.read_table("clean", "lidar_points_deskewed", clip_id=cid)
    ref_t = {d["frame_idx"]: d["deskew_ref_ns"] for d in
             lake.read_table("clean", "deskew_frames", clip_id=cid).to_pylist()}
    e = read_extrinsics(lake, cid, "car")["LIDAR_TOP"]
    for k in (0, 5):
        r = raw.filter(pc.equal(raw["frame_idx"], k))
        d = out.filter(pc.equal(out["frame_idx"], k))
        xyz = np.stack([r[c].to_numpy() for c in "xyz"], 1).astype(np.float64)
        want = scipy_reference(xyz, r["t_ns"].to_numpy(), track, e, ref_t[k])
        got = np.stack([d[c].to_numpy() for c in "xyz"], 1)
        assert np.abs(got - want).max() < 1e-4  # float32 storage


def test_fixed_roadside_pose_spans_the_recording(tmp_path: Path) -> None:
    lake = Lake(tmp_path / "lake")
    cid = run_ingest(lake, _clip(tmp_path, "fixed")).clip_id
    run_anonymize(lake, cid)
    track = load_pose_track(lake, cid, "car")
    frames = lake.read_table("clean", "lidar_frames", clip_id=cid)
    assert track.covers(frames.column("t_start_ns").to_numpy()).all()
    assert track.covers(frames.column("t_end_ns").to_numpy()).all()
    assert np.allclose(track.xyz, track.xyz[0])  # it does not move
    # heading 90 deg from north = facing east: body x is the world's +x
    assert np.allclose(track.matrices(track.t_ns[:1])[0, :3, 0], [1, 0, 0], atol=1e-6)


def test_a_pose_topic_missing_from_the_bag_is_named(tmp_path: Path) -> None:
    d = _clip(tmp_path, "odometry")
    cfg = yaml.safe_load((d / "clip.yaml").read_text())
    cfg["agents"][0]["pose"]["topic"] = "/odom_typo"
    (d / "clip.yaml").write_text(yaml.safe_dump(cfg))
    with pytest.raises(ClipError, match="pose topic") as e:
        run_ingest(Lake(tmp_path / "lake"), d)
    assert e.value.topic == "/odom_typo" and e.value.agent_id == "car"
