"""Pose sources as data (#12), end to end, on bags written directly with rosbags in other
drivers' conventions (not through the simulator's writer), each with a known motion and its
bag log times lagging the header stamps:

- ``odometry``: ``nav_msgs/Odometry`` at 50 Hz in a map frame that is the ENU frame of a
  geodetic origin minus a false origin, of a ``gnss_link`` child frame mounted rotated and
  offset from ``base_link`` (tf_static), body twist with angular rate;
- ``utm``: ``PoseWithCovarianceStamped`` at 20 Hz in UTM zone 32 with an offset;
- ``local``: ``PoseStamped`` at 50 Hz in a local ENU map with no geodetic reference;
- ``split``: ``NavSatFix`` of an antenna on a lever arm at 20 Hz + ``Imu`` orientation of an
  upside-down, yawed IMU at 100 Hz;
- ``vendor``: a vendor INS message at 100 Hz: degrees, yaw from east counter-clockwise,
  nose-up pitch, NED velocities, its own field names;
- ``tf``: dynamic ``/tf`` ``map -> odom`` (10 Hz) ``-> base_link`` (50 Hz);
- ``fixed`` (a roadside unit's surveyed pose) and ``none``.

For each: the raw track matches the truth in absolute terms (WGS84 / map), the clean
``ego_poses`` match the truth moved into the clip world (sub-millimetre, micro-radian), the
velocities match, and deskew of a scan recorded from the moving platform recovers the
static scene to well under a millimetre.
"""

from __future__ import annotations

import math
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.compute as pc
import pytest
import yaml
from rosbags.rosbag2 import Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from scipy.spatial.transform import Rotation

from tests.test_deskew import scipy_reference
from v2xlake.schemas.errors import ClipError
from v2xlake.storage.lake import Lake
from v2xlake.storage.reader import read_extrinsics
from v2xlake.tasks.anonymize.stage import run_anonymize
from v2xlake.tasks.deskew.stage import run_deskew
from v2xlake.tasks.geodesy import (
    LocalFrame,
    R_ecef_enu,
    ecef_to_geodetic,
    geodetic_to_ecef,
    geodetic_to_utm,
    rot_z,
)
from v2xlake.tasks.ingest import run_ingest
from v2xlake.tasks.qa.stage import run_qa
from v2xlake.tasks.reader import load_pose_track

T0 = 1_700_000_000 * 1_000_000_000
ORIGIN = (48.137154, 11.576124, 520.0)  # the truth frame: ENU tangent here (UTM zone 32)
SECONDS = 0.6
LAG = 35_000_000  # bag log time behind the header stamp
VENDOR_MSG = """std_msgs/Header header
float64 Lat
float64 Lon
float64 Hgt
float32 RollDeg
float32 PitchDeg
float32 YawDegEastCcw
float64 VelN
float64 VelE
float64 VelD
uint8 SolStatus
"""
VENDOR_TYPE = "acme_ins/msg/Nav"
R0 = R_ecef_enu(np.array(ORIGIN[0]), np.array(ORIGIN[1]))
O0 = geodetic_to_ecef(np.array(ORIGIN[0]), np.array(ORIGIN[1]), np.array(ORIGIN[2]))


def rigid(R: np.ndarray, t: Any) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = R, t
    return m


# mounts on the vehicle: T_ego_x
T_EGO_GNSS = rigid(Rotation.from_euler("z", 90, degrees=True).as_matrix(), [0.8, -0.3, 1.9])
T_EGO_IMU = rigid(Rotation.from_euler("zx", [90, 180], degrees=True).as_matrix(),
                  [0.2, 0.1, 0.5])
T_EGO_LIDAR = rigid(Rotation.from_euler("zyx", [1.5, 0.8, -0.5], degrees=True).as_matrix(),
                    [0.9, 0.05, 1.85])


def truth(t_ns: np.ndarray) -> np.ndarray:
    """``T_truth_ego`` (N, 4, 4): a curving, climbing, rolling drive (truth = ENU at ORIGIN)."""
    s = (np.asarray(t_ns, np.int64) - T0) / 1e9
    p = np.stack([15.0 * s + 2.0 * np.sin(0.7 * s) + 40.0, 4.0 * np.sin(0.9 * s) - 25.0,
                  0.3 * s + 1.0], -1)
    yaw, pitch, roll = 0.4 + 0.5 * s, 0.03 * np.sin(2 * s), 0.02 * np.cos(3 * s)
    R = Rotation.from_euler("ZYX", np.stack([yaw, -pitch, roll], -1)).as_matrix()
    m = np.zeros((len(s), 4, 4))
    m[:, :3, :3], m[:, :3, 3], m[:, 3, 3] = R, p, 1.0
    return m


def rates(t_ns: np.ndarray, T_ego_x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Velocity of frame x's origin (truth axes) and its angular rate (x's own axes)."""
    h = 100_000
    a, b = truth(t_ns - h) @ T_ego_x, truth(t_ns + h) @ T_ego_x
    v = (b[:, :3, 3] - a[:, :3, 3]) / 2e-4
    w = Rotation.from_matrix(b[:, :3, :3] @ np.swapaxes(a[:, :3, :3], 1, 2)).as_rotvec() / 2e-4
    x = (truth(t_ns) @ T_ego_x)[:, :3, :3]
    return v, np.einsum("nji,nj->ni", x, w)


def geodetic(T: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Truth-frame poses -> lat, lon, h and ``R_enu_body`` at each position."""
    e = O0 + T[:, :3, 3] @ R0.T
    lat, lon, h = ecef_to_geodetic(e)
    R = np.einsum("nji,jk,nkl->nil", R_ecef_enu(lat, lon), R0, T[:, :3, :3])
    return lat, lon, h, R


# --------------------------------------------------------------------------- bags
def _ts() -> Any:
    ts = get_typestore(Stores.ROS2_HUMBLE)
    ts.register(get_types_from_msg(VENDOR_MSG, VENDOR_TYPE))
    return ts


def _hdr(ts: Any, t: int, frame: str) -> Any:
    return ts.types["std_msgs/msg/Header"](
        stamp=ts.types["builtin_interfaces/msg/Time"](sec=t // 1_000_000_000,
                                                      nanosec=t % 1_000_000_000),
        frame_id=frame)


def _v3(ts: Any, v: Any) -> Any:
    return ts.types["geometry_msgs/msg/Vector3"](x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _pose(ts: Any, T: np.ndarray) -> Any:
    q = Rotation.from_matrix(T[:3, :3]).as_quat()
    return ts.types["geometry_msgs/msg/Pose"](
        position=ts.types["geometry_msgs/msg/Point"](x=float(T[0, 3]), y=float(T[1, 3]),
                                                     z=float(T[2, 3])),
        orientation=ts.types["geometry_msgs/msg/Quaternion"](
            x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])))


def _tf(ts: Any, t: int, parent: str, child: str, T: np.ndarray) -> Any:
    q = Rotation.from_matrix(T[:3, :3]).as_quat()
    return ts.types["geometry_msgs/msg/TransformStamped"](
        header=_hdr(ts, t, parent), child_frame_id=child,
        transform=ts.types["geometry_msgs/msg/Transform"](
            translation=_v3(ts, T[:3, 3]),
            rotation=ts.types["geometry_msgs/msg/Quaternion"](
                x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))))


N_COLS, N_LASERS = 360, 8


def sweep(t0: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A spinning scan's points in the LiDAR frame at their own times: (N, 3) and t (N,)."""
    rng = np.random.default_rng(seed)
    col = np.repeat(np.arange(N_COLS), N_LASERS)
    t = t0 + (col * 100_000_000) // N_COLS
    az = 2 * np.pi * col / N_COLS
    el = np.radians(np.tile(np.linspace(-15, 10, N_LASERS), N_COLS))
    r = rng.uniform(4.0, 40.0, col.size)
    xyz = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], 1) * r[:, None]
    return xyz.astype(np.float32), t.astype(np.int64)


def deskew_truth(xyz: np.ndarray, t: np.ndarray, t_ref: int,
                 T_ego_lidar: np.ndarray = T_EGO_LIDAR) -> np.ndarray:
    """Where each point lies in the LiDAR frame at ``t_ref`` (the scene is static)."""
    L = truth(t) @ T_ego_lidar
    ref = np.linalg.inv((truth(np.array([t_ref])) @ T_ego_lidar)[0])
    rel = ref @ L
    return np.einsum("nij,nj->ni", rel[:, :3, :3], xyz.astype(np.float64)) + rel[:, :3, 3]


def _cloud(ts: Any, t0: int, k: int) -> Any:
    xyz, t = sweep(t0, k)
    dt = np.dtype({"names": ["x", "y", "z", "intensity", "t", "ring"],
                   "formats": ["<f4", "<f4", "<f4", "<f4", "<u4", "<u2"],
                   "offsets": [0, 4, 8, 12, 16, 20], "itemsize": 24})
    a = np.zeros(len(t), dt)
    a["x"], a["y"], a["z"] = xyz.T
    a["intensity"], a["t"], a["ring"] = 10.0, t - t0, np.arange(len(t)) % N_LASERS
    PF = ts.types["sensor_msgs/msg/PointField"]
    fields = [PF(name=n, offset=o, datatype=c, count=1) for n, o, c in (
        ("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 12, 7), ("t", 16, 6),
        ("ring", 20, 4))]
    return ts.types["sensor_msgs/msg/PointCloud2"](
        header=_hdr(ts, t0, "lidar"), height=1, width=len(t), fields=fields,
        is_bigendian=False, point_step=24, row_step=24 * len(t), data=a.view(np.uint8),
        is_dense=True)


def pose_messages(kind: str, ts: Any) -> list[tuple[str, str, int, Any]]:
    """(topic, type, header stamp, msg) of the pose source of one scenario."""
    T = ts.types
    out: list[tuple[str, str, int, Any]] = []
    span = np.arange(T0 - 100_000_000, T0 + int(SECONDS * 1e9) + 100_000_000, 10_000_000)
    if kind == "odometry":  # map = ENU at ORIGIN minus an offset; the pose is of gnss_link
        off = np.array([1000.0, -2000.0, 5.0])
        t = span[::2]
        B = truth(t) @ T_EGO_GNSS
        v, w = rates(t, T_EGO_GNSS)
        for i, ti in enumerate(t):
            M = B[i].copy()
            M[:3, 3] -= off
            tw = T["geometry_msgs/msg/Twist"](linear=_v3(ts, B[i, :3, :3].T @ v[i]),
                                              angular=_v3(ts, w[i]))
            out.append(("/localization/odom", "nav_msgs/msg/Odometry", int(ti),
                        T["nav_msgs/msg/Odometry"](
                            header=_hdr(ts, int(ti), "map"), child_frame_id="gnss_link",
                            pose=T["geometry_msgs/msg/PoseWithCovariance"](
                                pose=_pose(ts, M), covariance=np.zeros(36)),
                            twist=T["geometry_msgs/msg/TwistWithCovariance"](
                                twist=tw, covariance=np.zeros(36)))))
    elif kind == "utm":  # UTM 32 grid axes; map = UTM - offset
        t = span[::5]
        lat, lon, h, R_enu = geodetic(truth(t))
        e, n, gamma = geodetic_to_utm(lat, lon, 32)
        R_grid = np.einsum("nji,njk->nik", rot_z(-gamma), R_enu)  # R_grid_enu = Rz(gamma)
        for i, ti in enumerate(t):
            M = rigid(R_grid[i], [e[i] - 690_000.0, n[i] - 5_330_000.0, h[i]])
            out.append(("/pose", "geometry_msgs/msg/PoseWithCovarianceStamped", int(ti),
                        T["geometry_msgs/msg/PoseWithCovarianceStamped"](
                            header=_hdr(ts, int(ti), "map"),
                            pose=T["geometry_msgs/msg/PoseWithCovariance"](
                                pose=_pose(ts, M), covariance=np.zeros(36)))))
    elif kind == "local":  # a local ENU map, no geodetic reference, offset (100, 200, 10)
        t = span[::2]
        B = truth(t)
        for i, ti in enumerate(t):
            M = B[i].copy()
            M[:3, 3] += [100.0, 200.0, 10.0]
            out.append(("/pose", "geometry_msgs/msg/PoseStamped", int(ti),
                        T["geometry_msgs/msg/PoseStamped"](header=_hdr(ts, int(ti), "map"),
                                                           pose=_pose(ts, M))))
    elif kind == "split":  # antenna fixes at 20 Hz, IMU orientation at 100 Hz
        lat, lon, h, _ = geodetic(truth(span) @ T_EGO_GNSS)
        _, _, _, R_imu = geodetic(truth(span) @ T_EGO_IMU)
        q = Rotation.from_matrix(R_imu).as_quat()
        for i, ti in enumerate(span):
            out.append(("/imu/data", "sensor_msgs/msg/Imu", int(ti), T["sensor_msgs/msg/Imu"](
                header=_hdr(ts, int(ti), "imu_link"),
                orientation=T["geometry_msgs/msg/Quaternion"](
                    x=float(q[i, 0]), y=float(q[i, 1]), z=float(q[i, 2]), w=float(q[i, 3])),
                orientation_covariance=np.zeros(9), angular_velocity=_v3(ts, [0, 0, 0]),
                angular_velocity_covariance=np.zeros(9),
                linear_acceleration=_v3(ts, [0, 0, 9.81]),
                linear_acceleration_covariance=np.zeros(9))))
            if i % 5 == 0:
                out.append(("/gnss/fix", "sensor_msgs/msg/NavSatFix", int(ti),
                            T["sensor_msgs/msg/NavSatFix"](
                                header=_hdr(ts, int(ti), "gnss_link"),
                                status=T["sensor_msgs/msg/NavSatStatus"](status=2, service=1),
                                latitude=float(lat[i]), longitude=float(lon[i]),
                                altitude=float(h[i]), position_covariance=np.zeros(9),
                                position_covariance_type=0)))
    elif kind == "vendor":  # degrees, yaw from east CCW, nose-up pitch, NED velocity
        lat, lon, h, R_enu = geodetic(truth(span))
        v_truth, _ = rates(span, np.eye(4))
        v_enu = np.einsum("nji,jk,nk->ni", R_ecef_enu(lat, lon), R0, v_truth)
        yaw, negpitch, roll = Rotation.from_matrix(R_enu).as_euler("ZYX").T
        for i, ti in enumerate(span):
            out.append(("/acme/nav", VENDOR_TYPE, int(ti), T[VENDOR_TYPE](
                header=_hdr(ts, int(ti), "base_link"), Lat=float(lat[i]), Lon=float(lon[i]),
                Hgt=float(h[i]), RollDeg=math.degrees(roll[i]),
                PitchDeg=math.degrees(-negpitch[i]), YawDegEastCcw=math.degrees(yaw[i]),
                VelN=float(v_enu[i, 1]), VelE=float(v_enu[i, 0]), VelD=float(-v_enu[i, 2]),
                SolStatus=2)))
    elif kind == "tf":  # map -> odom at 10 Hz (constant), odom -> base_link at 50 Hz
        T_map_odom = rigid(Rotation.from_euler("z", 30, degrees=True).as_matrix(),
                           [-500.0, 300.0, 2.0])
        T_odom = np.linalg.inv(T_map_odom) @ truth(span)
        for i, ti in enumerate(span):
            tfs = []
            if i % 2 == 0:
                tfs.append(_tf(ts, int(ti), "odom", "base_link", T_odom[i]))
            if i % 10 == 0:
                tfs.append(_tf(ts, int(ti), "map", "odom", T_map_odom))
            if tfs:
                out.append(("/tf", "tf2_msgs/msg/TFMessage", int(ti),
                            T["tf2_msgs/msg/TFMessage"](transforms=tfs)))
    return out


POSE: dict[str, tuple[dict[str, Any], list[dict[str, Any]]]] = {
    "odometry": ({"kind": "odometry", "sensor": "ODOM", "map_frame": "map",
                  "datum": {"kind": "geodetic", "offset": [1000.0, -2000.0, 5.0],
                            "origin": {"latitude": ORIGIN[0], "longitude": ORIGIN[1],
                                       "height": ORIGIN[2]}}},
                 [{"name": "ODOM", "modality": "ins", "topic": "/localization/odom",
                   "msg_type": "nav_msgs/msg/Odometry", "rate_hz": 50}]),
    "utm": ({"kind": "odometry", "sensor": "POSE",
             "datum": {"kind": "utm", "utm_zone": 32, "offset": [690000.0, 5330000.0, 0.0]}},
            [{"name": "POSE", "modality": "ins", "topic": "/pose",
              "msg_type": "geometry_msgs/msg/PoseWithCovarianceStamped", "rate_hz": 20}]),
    "local": ({"kind": "odometry", "sensor": "POSE",
               "datum": {"kind": "local", "offset": [-100.0, -200.0, -10.0]}},
              [{"name": "POSE", "modality": "ins", "topic": "/pose",
                "msg_type": "geometry_msgs/msg/PoseStamped", "rate_hz": 50}]),
    "split": ({"kind": "split", "position": "GNSS", "attitude": "IMU", "sample_at": "position"},
              [{"name": "GNSS", "modality": "gnss", "topic": "/gnss/fix",
                "msg_type": "sensor_msgs/msg/NavSatFix", "rate_hz": 20},
               {"name": "IMU", "modality": "imu", "topic": "/imu/data",
                "msg_type": "sensor_msgs/msg/Imu", "rate_hz": 100}]),
    "vendor": ({"kind": "ins", "sensor": "INS", "angle_unit": "deg", "heading": "east_ccw",
                "velocity_frame": "ned",
                "fields": {"latitude": "Lat", "longitude": "Lon", "height": "Hgt",
                           "roll": "RollDeg", "pitch": "PitchDeg", "heading": "YawDegEastCcw",
                           "velocity": {"x": "VelN", "y": "VelE", "z": "VelD"},
                           "status": "SolStatus"}},
               [{"name": "INS", "modality": "ins", "topic": "/acme/nav",
                 "msg_type": VENDOR_TYPE, "rate_hz": 100}]),
    "tf": ({"kind": "tf", "sensor": "TF", "parent_frame": "map",
            "datum": {"kind": "geodetic", "origin": {"latitude": ORIGIN[0],
                                                     "longitude": ORIGIN[1],
                                                     "height": ORIGIN[2]}}},
           [{"name": "TF", "modality": "ins", "topic": "/tf",
             "msg_type": "tf2_msgs/msg/TFMessage"}]),
    "fixed": ({"kind": "fixed", "geodetic": {"latitude": ORIGIN[0], "longitude": ORIGIN[1],
                                             "height": ORIGIN[2]},
               "attitude": {"heading": 90.0}}, []),
    "none": ({"kind": "none"}, []),
}


def write_clip(tmp: Path, kind: str) -> Path:
    d = tmp / kind
    d.mkdir(parents=True)
    ts = _ts()
    msgs = [(topic, typ, stamp + LAG, msg) for topic, typ, stamp, msg in pose_messages(kind, ts)]
    for k, t0 in enumerate(range(T0, T0 + int(SECONDS * 1e9), 100_000_000)):
        msgs.append(("/lidar", "sensor_msgs/msg/PointCloud2", t0 + 99_000_000 + LAG,
                     _cloud(ts, t0, k)))
    static = [_tf(ts, T0, "base_link", "gnss_link", T_EGO_GNSS),
              _tf(ts, T0, "base_link", "imu_link", T_EGO_IMU)]
    msgs.append(("/tf_static", "tf2_msgs/msg/TFMessage", T0,
                 ts.types["tf2_msgs/msg/TFMessage"](transforms=static)))
    msgs.sort(key=lambda m: m[2])
    with Writer(d / "bag", version=8) as w:
        conns: dict[str, Any] = {}
        for topic, typ, log_t, msg in msgs:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, typ, typestore=ts)
            w.write(conns[topic], log_t, ts.serialize_cdr(msg, typ))
    pose, sensors = POSE[kind]
    q = Rotation.from_matrix(T_EGO_LIDAR[:3, :3]).as_quat(scalar_first=True)
    cfg: dict[str, Any] = {
        "clip_id": f"pose-{kind}", "location": "x", "road_type": "arterial",
        "weather": "clear", "lighting": "day", "agents": [{
            "agent_id": "car", "kind": "roadside" if kind == "fixed" else "vehicle",
            "role": "reference", "bag": "bag", "pose": pose,
            "sensors": [{"name": "LIDAR_TOP", "modality": "lidar", "topic": "/lidar",
                         "msg_type": "sensor_msgs/msg/PointCloud2", "rate_hz": 10,
                         "extrinsic": {"translation": T_EGO_LIDAR[:3, 3].tolist(),
                                       "rotation": q.tolist()},
                         "fields": {"time": {"field": "t", "unit": "ns",
                                             "reference": "header"}}}, *sensors]}]}
    if kind == "vendor":
        msg_dir = d / "msgs" / "acme_ins" / "msg"
        msg_dir.mkdir(parents=True)
        (msg_dir / "Nav.msg").write_text(VENDOR_MSG)
        cfg["message_definitions"] = ["msgs/acme_ins/msg/Nav.msg"]
    (d / "clip.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    return d


# --------------------------------------------------------------------------- the checks
def raw_truth_error(lake: Lake, cid: str, kind: str) -> tuple[float, float, np.ndarray]:
    """Largest position (m) and attitude (rad) error of the raw track against the truth,
    in absolute terms (ECEF for a georeferenced track, the map for a local one)."""
    ins = lake.read_table("raw", "ins", clip_id=cid)
    if kind == "local":
        ego = lake.read_table("raw", "ego_poses", clip_id=cid)
        assert ins.num_rows == 0 and ego.num_rows > 2
        t = ego["t_ns"].to_numpy()
        Tt = truth(t)
        p = np.stack([ego[c].to_numpy() for c in "xyz"], 1)
        q = np.stack([ego[c].to_numpy() for c in ("qx", "qy", "qz", "qw")], 1)
        dR = Rotation.from_matrix(np.swapaxes(Tt[:, :3, :3], 1, 2)
                                  @ Rotation.from_quat(q).as_matrix()).magnitude()
        return float(np.abs(p - Tt[:, :3, 3]).max()), float(dR.max()), t
    t = ins["t_ns"].to_numpy()
    lat, lon, h, R_enu = geodetic(truth(t))
    got = geodetic_to_ecef(ins["lat"].to_numpy(), ins["lon"].to_numpy(), ins["alt"].to_numpy())
    want = geodetic_to_ecef(lat, lon, h)
    from v2xlake.tasks.geodesy import attitude_to_matrix

    R = attitude_to_matrix(ins["roll"].to_numpy(), ins["pitch"].to_numpy(),
                           ins["azimuth"].to_numpy())
    dR = Rotation.from_matrix(np.swapaxes(R_enu, 1, 2) @ R).magnitude()
    return float(np.linalg.norm(got - want, axis=1).max()), float(dR.max()), t


def world_of_truth(lake: Lake, cid: str, kind: str) -> np.ndarray:
    """The rigid ``T_world_truth`` the clean zone must use: ENU at the first pose's
    lat/lon shifted to it (georeferenced), or the map shifted in xy (local)."""
    if kind == "local":
        first = truth(lake.read_table("raw", "ego_poses", clip_id=cid)["t_ns"].to_numpy()[:1])
        return rigid(np.eye(3), [-first[0, 0, 3], -first[0, 1, 3], 0.0])
    ins = lake.read_table("raw", "ins", clip_id=cid).sort_by("t_ns")
    f = LocalFrame(ins["lat"][0].as_py(), ins["lon"][0].as_py())
    Rf = R_ecef_enu(np.array(f.lat0), np.array(f.lon0))
    of = geodetic_to_ecef(np.array(f.lat0), np.array(f.lon0), np.array(0.0))
    return rigid(Rf.T @ R0, Rf.T @ (O0 - of))


@pytest.mark.parametrize("kind", ["odometry", "utm", "local", "split", "vendor", "tf"])
def test_pose_source_reproduces_the_motion(tmp_path: Path, kind: str) -> None:
    lake = Lake(tmp_path / "lake")
    cid = run_ingest(lake, write_clip(tmp_path, kind)).clip_id
    agents = lake.read_table("raw", "agents", clip_id=cid).to_pylist()
    assert agents[0]["has_ins"] and agents[0]["pose_source"] == POSE[kind][0]["kind"]
    assert agents[0]["pose_frame"] == ("map" if kind == "local" else "wgs84")
    dp, dr, t_raw = raw_truth_error(lake, cid, kind)
    assert dp < 1e-4 and dr < 2e-6, f"raw {kind}: {dp * 1e3:.4f} mm, {dr:.2e} rad"
    qa = run_qa(lake, cid)
    assert qa.metrics["errors"] == 0 and qa.metrics["warnings"] == 0, qa.notes
    run_anonymize(lake, cid)
    ego = lake.read_table("clean", "ego_poses", clip_id=cid).sort_by("t_ns")
    delta = int(t_raw.min()) - int(ego["t_ns"].to_numpy().min())  # absolute - relative
    t_abs = ego["t_ns"].to_numpy() + delta
    W = world_of_truth(lake, cid, kind)
    want = W @ truth(t_abs)
    p = np.stack([ego[c].to_numpy() for c in "xyz"], 1)
    q = np.stack([ego[c].to_numpy() for c in ("qx", "qy", "qz", "qw")], 1)
    err_p = np.linalg.norm(p - want[:, :3, 3], axis=1).max()
    err_r = Rotation.from_matrix(np.swapaxes(want[:, :3, :3], 1, 2)
                                 @ Rotation.from_quat(q).as_matrix()).magnitude().max()
    assert err_p < 1e-4 and err_r < 2e-6, f"{kind}: {err_p * 1e3:.4f} mm, {err_r:.2e} rad"
    assert np.hypot(p[0, 0], p[0, 1]) < 1e-6  # the clip world starts at the first pose
    # velocities of the ego origin: given (Odometry twist with the lever arm's w x r, NED)
    # or differentiated (finite differences of the samples: looser)
    v = np.stack([ego[c].to_numpy() for c in ("vx", "vy", "vz")], 1)
    v_true = rates(t_abs, np.eye(4))[0] @ W[:3, :3].T
    tol = 1e-4 if kind in ("odometry", "vendor") else 0.02
    assert np.abs(v - v_true)[1:-1].max() < tol
    # deskew through this track recovers the static scene, and agrees with per-point SciPy
    rep = run_deskew(lake, cid)
    assert rep.status == "done" and rep.metrics["n_frames_skipped"] == 0
    raw = lake.read_table("clean", "lidar_points", clip_id=cid)
    out = lake.read_table("clean", "lidar_points_deskewed", clip_id=cid)
    ref_t = {d["frame_idx"]: d["deskew_ref_ns"] for d in
             lake.read_table("clean", "deskew_frames", clip_id=cid).to_pylist()}
    track = load_pose_track(lake, cid, "car")
    e = read_extrinsics(lake, cid, "car")["LIDAR_TOP"]
    for k in (0, 3, 5):
        r = raw.filter(pc.equal(raw["frame_idx"], k))
        d = out.filter(pc.equal(out["frame_idx"], k))
        xyz = np.stack([r[c].to_numpy() for c in "xyz"], 1).astype(np.float64)
        got = np.stack([d[c].to_numpy() for c in "xyz"], 1).astype(np.float64)
        scene = deskew_truth(xyz, r["t_ns"].to_numpy() + delta, ref_t[k] + delta)
        rms = float(np.sqrt(np.mean(np.sum((got - scene) ** 2, 1))))
        # sub-millimetre: what is left is linear interpolation between pose samples of a
        # curving drive (0.7 mm at 20 Hz, 0.1 mm at 50 Hz), not the source's conversion
        assert rms < 1e-3, f"{kind} frame {k}: deskew {rms * 1e3:.3f} mm RMS from the scene"
        want_k = scipy_reference(xyz, r["t_ns"].to_numpy(), track, e, ref_t[k])
        assert np.abs(got - want_k).max() < 1e-4  # float32 storage


def test_fixed_roadside_pose_spans_the_recording(tmp_path: Path) -> None:
    lake = Lake(tmp_path / "lake")
    cid = run_ingest(lake, write_clip(tmp_path, "fixed")).clip_id
    assert run_qa(lake, cid).metrics["errors"] == 0
    run_anonymize(lake, cid)
    track = load_pose_track(lake, cid, "car")
    frames = lake.read_table("clean", "lidar_frames", clip_id=cid)
    assert track.covers(frames.column("t_start_ns").to_numpy()).all()
    assert track.covers(frames.column("t_end_ns").to_numpy()).all()
    assert np.allclose(track.xyz, [0.0, 0.0, ORIGIN[2]], atol=1e-6)  # it does not move
    # heading 90 deg from north = facing east: body x is the world's +x
    assert np.allclose(track.matrices(track.t_ns[:1])[0, :3, 0], [1, 0, 0], atol=1e-9)
    assert run_deskew(lake, cid).status == "done"


def test_no_pose_keeps_ingest_qa_and_anonymize(tmp_path: Path) -> None:
    """A clip without any pose: ingest, QA (a warning) and anonymize run; the absence is
    visible as agents.has_ins false, pose_source 'none', no ego_poses; deskew says why."""
    lake = Lake(tmp_path / "lake")
    cid = run_ingest(lake, write_clip(tmp_path, "none")).clip_id
    a = lake.read_table("raw", "agents", clip_id=cid).to_pylist()[0]
    assert (a["has_ins"], a["pose_source"], a["pose_frame"]) == (False, "none", None)
    qa = run_qa(lake, cid)
    assert qa.metrics["errors"] == 0 and any("pose: none configured" in n for n in qa.notes)
    run_anonymize(lake, cid)
    assert lake.read_table("clean", "ego_poses", clip_id=cid).num_rows == 0
    assert lake.read_table("clean", "lidar_points", clip_id=cid).num_rows > 0
    rep = run_deskew(lake, cid)
    assert rep.status == "not_applicable" and "has_ins is false" in (rep.reason or "")


def _edit(d: Path, fn: Any) -> None:
    cfg = yaml.safe_load((d / "clip.yaml").read_text())
    fn(cfg)
    (d / "clip.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))


def test_pose_errors_name_clip_agent_topic(tmp_path: Path) -> None:
    # a pose sensor that is not declared
    d = write_clip(tmp_path / "a", "odometry")
    _edit(d, lambda c: c["agents"][0]["pose"].update(sensor="ODOMETRY"))
    with pytest.raises(ClipError, match=r"pose names sensor 'ODOMETRY', which is not in its "
                       r"sensors \['LIDAR_TOP', 'ODOM'\]") as e:
        run_ingest(Lake(tmp_path / "lake"), d)
    assert e.value.clip_id == "pose-odometry"
    # the map frame the messages are in is not the one clip.yaml names
    d = write_clip(tmp_path / "b", "odometry")
    _edit(d, lambda c: c["agents"][0]["pose"].update(map_frame="earth"))
    with pytest.raises(ClipError, match=r"frame\(s\) \['map'\], clip.yaml says map_frame "
                       "'earth'") as e:
        run_ingest(Lake(tmp_path / "lake"), d)
    assert (e.value.agent_id, e.value.topic) == ("car", "/localization/odom")
    # a child frame with no static transform to the ego frame
    d = write_clip(tmp_path / "c", "odometry")
    _edit(d, lambda c: c["agents"][0].update(tf_static_topic=None))
    with pytest.raises(ClipError, match="pose is of frame 'gnss_link' but no static "
                       "transform connects it to ego frame 'base_link'"):
        run_ingest(Lake(tmp_path / "lake"), d)
    # an Odometry pose source pointed at a NavSatFix
    d = write_clip(tmp_path / "d", "split")
    _edit(d, lambda c: c["agents"][0].update(pose={"kind": "odometry", "sensor": "GNSS",
                                                   "datum": {"kind": "local"}}))
    with pytest.raises(ClipError, match="pose source 'odometry' reads") as e:
        run_ingest(Lake(tmp_path / "lake"), d)
    assert e.value.topic == "/gnss/fix"
    # a datum that is incomplete is refused by the schema
    d = write_clip(tmp_path / "e", "utm")
    _edit(d, lambda c: c["agents"][0]["pose"]["datum"].pop("utm_zone"))
    with pytest.raises(ClipError, match="datum kind 'utm' needs utm_zone"):
        run_ingest(Lake(tmp_path / "lake"), d)


def test_agents_in_different_worlds_are_refused(tmp_path: Path) -> None:
    """A georeferenced agent and one in a local map without datum are not one clip."""
    d = write_clip(tmp_path, "local")
    geo = write_clip(tmp_path / "g", "split")
    shutil.copytree(geo / "bag", d / "bag2")

    def add(c: dict[str, Any]) -> None:
        other = yaml.safe_load((geo / "clip.yaml").read_text())["agents"][0]
        c["agents"].append({**other, "agent_id": "car2", "role": "cooperative", "bag": "bag2"})
    _edit(d, add)
    with pytest.raises(ClipError, match="not in one world: car in a local map without "
                       r"geodetic reference \(datum: local\); car2 georeferenced"):
        run_ingest(Lake(tmp_path / "lake"), d)


# three LiDARs on one vehicle, each with its own driver's per-point time convention
T_EGO_LEFT = rigid(Rotation.from_euler("zx", [90, -20], degrees=True).as_matrix(),
                   [0.2, 0.9, 1.2])
T_EGO_FRONT = rigid(Rotation.from_euler("y", 5, degrees=True).as_matrix(), [2.1, 0.0, 0.8])
EXTRA_LIDARS = {
    # RoboSense blind-spot (rslidar_sdk): timestamp float64, absolute seconds
    "LIDAR_LEFT": ("/rslidar_points", T_EGO_LEFT, "<f8", "s", "absolute"),
    # Livox solid-state (livox_ros_driver2 PointCloud2): timestamp float64, absolute ns
    "LIDAR_FRONT": ("/livox/lidar", T_EGO_FRONT, "<f8", "ns", "absolute"),
}


def _cloud_as(ts: Any, t0: int, k: int, frame: str, fmt: str, unit: str) -> Any:
    xyz, t = sweep(t0, 100 + k)
    dt = np.dtype({"names": ["x", "y", "z", "intensity", "timestamp"],
                   "formats": ["<f4", "<f4", "<f4", "<f4", fmt],
                   "offsets": [0, 4, 8, 12, 16], "itemsize": 24})
    a = np.zeros(len(t), dt)
    a["x"], a["y"], a["z"] = xyz.T
    a["timestamp"] = t / 1e9 if unit == "s" else t.astype(np.float64)
    PF = ts.types["sensor_msgs/msg/PointField"]
    fields = [PF(name=n, offset=o, datatype=c, count=1) for n, o, c in (
        ("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 12, 7), ("timestamp", 16, 8))]
    return ts.types["sensor_msgs/msg/PointCloud2"](
        header=_hdr(ts, t0, frame), height=1, width=len(t), fields=fields,
        is_bigendian=False, point_step=24, row_step=24 * len(t), data=a.view(np.uint8),
        is_dense=True)


def test_several_lidars_per_agent_each_deskewed_exactly(tmp_path: Path) -> None:
    """Mechanical (Ouster ns from the stamp) + blind-spot (RoboSense absolute s) +
    solid-state (Livox absolute ns) on one agent: each is deskewed into its own scan-start
    frame from the agent's one pose track, through its own extrinsic."""
    d = write_clip(tmp_path, "odometry")
    ts = _ts()
    from rosbags.rosbag2 import Reader
    with Reader(d / "bag") as r:
        msgs = [(c.topic, c.msgtype, t, raw) for c, t, raw in r.messages()]
    shutil.rmtree(d / "bag")
    for name, (topic, _T, fmt, unit, _ref) in EXTRA_LIDARS.items():
        for k, t0 in enumerate(range(T0, T0 + int(SECONDS * 1e9), 100_000_000)):
            msg = _cloud_as(ts, t0, k, name.lower(), fmt, unit)
            msgs.append((topic, "sensor_msgs/msg/PointCloud2", t0 + 99_000_000 + LAG,
                         ts.serialize_cdr(msg, "sensor_msgs/msg/PointCloud2")))
    with Writer(d / "bag", version=8) as w:
        conns: dict[str, Any] = {}
        for topic, typ, log_t, raw in sorted(msgs, key=lambda m: m[2]):
            if topic not in conns:
                conns[topic] = w.add_connection(topic, typ, typestore=ts)
            w.write(conns[topic], log_t, raw)
    cfg = yaml.safe_load((d / "clip.yaml").read_text())
    for name, (topic, T, _fmt, unit, ref) in EXTRA_LIDARS.items():
        q = Rotation.from_matrix(T[:3, :3]).as_quat(scalar_first=True)
        cfg["agents"][0]["sensors"].append({
            "name": name, "modality": "lidar", "topic": topic, "rate_hz": 10,
            "msg_type": "sensor_msgs/msg/PointCloud2",
            "extrinsic": {"translation": T[:3, 3].tolist(), "rotation": q.tolist()},
            "fields": {"ring": None, "time": {"field": "timestamp", "unit": unit,
                                              "reference": ref}}})
    (d / "clip.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    lake = Lake(tmp_path / "lake")
    cid = run_ingest(lake, d).clip_id
    assert run_qa(lake, cid).metrics["errors"] == 0
    run_anonymize(lake, cid)
    assert run_deskew(lake, cid).metrics["n_frames"] == 3 * 6
    delta = int(lake.read_table("raw", "lidar_frames", clip_id=cid)["stamp_ns"].to_numpy().min()
                ) - int(lake.read_table("clean", "lidar_frames",
                                        clip_id=cid)["stamp_ns"].to_numpy().min())
    raw = lake.read_table("clean", "lidar_points", clip_id=cid)
    out = lake.read_table("clean", "lidar_points_deskewed", clip_id=cid)
    refs = {(d_["sensor"], d_["frame_idx"]): d_["deskew_ref_ns"] for d_ in
            lake.read_table("clean", "deskew_frames", clip_id=cid).to_pylist()}
    for name, T in (("LIDAR_TOP", T_EGO_LIDAR), *((n, v[1]) for n, v in EXTRA_LIDARS.items())):
        for k in (1, 4):
            sel = (raw["sensor"].to_numpy(zero_copy_only=False) == name) & \
                (raw["frame_idx"].to_numpy() == k)
            r = raw.filter(sel)
            o = out.filter((out["sensor"].to_numpy(zero_copy_only=False) == name)
                           & (out["frame_idx"].to_numpy() == k))
            xyz = np.stack([r[c].to_numpy() for c in "xyz"], 1)
            got = np.stack([o[c].to_numpy() for c in "xyz"], 1).astype(np.float64)
            scene = deskew_truth(xyz, r["t_ns"].to_numpy() + delta, refs[(name, k)] + delta, T)
            rms = float(np.sqrt(np.mean(np.sum((got - scene) ** 2, 1))))
            assert rms < 3e-4, f"{name} frame {k}: {rms * 1e3:.3f} mm"
