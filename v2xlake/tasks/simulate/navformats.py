"""How a simulated agent's pose reaches its bag: one INS solution, four encodings.

The same INS solution (``ins.ins_samples``: true pose + the seeded INS error, 125 Hz) is
written in the convention ``SimConfig.pose_format`` names, with the matching ``clip.yaml``
``pose:`` block, so one recording exercises each pose source of the input contract and the
lake's poses do not depend on the encoding (``tests/test_simulate_pose_formats.py``):

- ``inspva``: the vendor-style ``v2xlake_msgs/msg/InsPva`` (WGS84, roll/pitch/azimuth);
- ``odometry``: ``nav_msgs/msg/Odometry`` in a UTM grid map frame with a false origin (the
  UTM coordinates of the clip origin rounded down to the kilometre, as Autoware-style maps
  do), orientation of ``base_link`` in grid axes, body-frame twist;
- ``navsat-imu``: the INS position as ``sensor_msgs/msg/NavSatFix`` at 125 Hz plus the
  attitude as the ``sensor_msgs/msg/Imu`` orientation (REP-103 ENU) the agent already has;
- ``tf``: ``tf2_msgs/msg/TFMessage`` on ``/tf``: ``map -> base_link`` with ``map`` the ENU
  frame of the clip origin (a geodetic datum).

A roadside unit has no navigation topics at all: its surveyed pose (the INS solution of the
static mast, error included) is written into ``clip.yaml`` as a fixed pose.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from v2xlake.schemas.clip import (
    AngleUnit,
    Datum,
    DatumKind,
    FixedAttitude,
    FixedPose,
    GeodeticPoint,
    InsFields,
    InsPose,
    Modality,
    OdometryPose,
    SensorConfig,
    SplitPose,
    TfPose,
    Vec3Paths,
)
from v2xlake.tasks.geodesy import LocalFrame, geodetic_to_utm, rot_z
from v2xlake.tasks.geometry import matrix_to_quat
from v2xlake.tasks.simulate.bagwrite import INS_MSG_TYPE, BagSink
from v2xlake.tasks.simulate.config import SimConfig
from v2xlake.tasks.simulate.ins import InsSamples

POSE_FORMATS = ("inspva", "odometry", "navsat-imu", "tf")
EGO_FRAME = "base_link"
MAP_FRAME = "map"
LAT_INS_NS = 1_000_000  # log time behind the header stamp


def utm_zone(lon: float) -> int:
    return int((lon + 180.0) // 6.0) % 60 + 1


def utm_offset(cfg: SimConfig) -> tuple[float, float, float]:
    """The map frame's false origin: the clip origin's UTM coordinates, rounded down to km."""
    e, n, _ = geodetic_to_utm(np.array([cfg.origin_lat]), np.array([cfg.origin_lon]),
                              utm_zone(cfg.origin_lon), cfg.origin_lat < 0)
    return float(e[0] // 1000 * 1000), float(n[0] // 1000 * 1000), 0.0


def pose_topic(agent: str, fmt: str) -> tuple[str, str]:
    """(topic, message type) of the agent's pose stream in ``fmt``."""
    return {"inspva": (f"/{agent}/ins", INS_MSG_TYPE),
            "odometry": (f"/{agent}/localization/odometry", "nav_msgs/msg/Odometry"),
            "navsat-imu": (f"/{agent}/ins/fix", "sensor_msgs/msg/NavSatFix"),
            "tf": ("/tf", "tf2_msgs/msg/TFMessage")}[fmt]


def declare(sink: BagSink, agent: str, fmt: str) -> None:
    topic, typ = pose_topic(agent, fmt)
    sink.topic(topic, typ)


def put_poses(sink: BagSink, cfg: SimConfig, agent: str, ins: InsSamples,
              frame: LocalFrame) -> None:
    """The agent's INS solution at every sample, in ``cfg.pose_format``."""
    fmt = cfg.pose_format
    topic, _ = pose_topic(agent, fmt)
    f, T = sink.f, sink.f.T
    n = len(ins.t_ns)
    R_enu = _enu_attitude(ins)
    if fmt == "odometry":
        zone = utm_zone(cfg.origin_lon)
        e, nn, gamma = geodetic_to_utm(ins.lat, ins.lon, zone, cfg.origin_lat < 0)
        off = utm_offset(cfg)
        q = matrix_to_quat(np.einsum("nij,njk->nik", rot_z(gamma), R_enu))  # grid <- body
        v_body = np.einsum("nji,nj->ni", R_enu, ins.vel_enu)
    elif fmt == "tf":
        xyz = frame.to_local(ins.lat, ins.lon, ins.alt).reshape(n, 3)
        q = matrix_to_quat(frame.R_local_enu(ins.lat, ins.lon) @ R_enu)
    for i, t in enumerate(ins.t_ns.tolist()):
        if fmt == "inspva":
            vals = {"latitude": float(ins.lat[i]), "longitude": float(ins.lon[i]),
                    "altitude": float(ins.alt[i]), "roll": float(ins.roll[i]),
                    "pitch": float(ins.pitch[i]), "azimuth": float(ins.azimuth[i]),
                    "east_velocity": float(ins.vel_enu[i, 0]),
                    "north_velocity": float(ins.vel_enu[i, 1]),
                    "up_velocity": float(ins.vel_enu[i, 2]), "rtk_status": 2}
            msg: Any = f.ins(t, EGO_FRAME, vals, topic)
        elif fmt == "odometry":
            pose = T["geometry_msgs/msg/Pose"](
                position=T["geometry_msgs/msg/Point"](x=float(e[i] - off[0]),
                                                      y=float(nn[i] - off[1]),
                                                      z=float(ins.alt[i] - off[2])),
                orientation=_quat(T, q[i]))
            twist = T["geometry_msgs/msg/Twist"](linear=_vec(T, v_body[i]),
                                                 angular=_vec(T, ins.gyro[i]))
            msg = T["nav_msgs/msg/Odometry"](
                header=f.header(t, MAP_FRAME, topic), child_frame_id=EGO_FRAME,
                pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose,
                                                               covariance=np.zeros(36)),
                twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=twist,
                                                                 covariance=np.zeros(36)))
        elif fmt == "navsat-imu":
            msg = f.navsatfix(t, EGO_FRAME, ins.lat[i], ins.lon[i], ins.alt[i], 0.01, topic)
        else:
            ts = T["geometry_msgs/msg/TransformStamped"](
                header=f.header(t, MAP_FRAME, topic), child_frame_id=EGO_FRAME,
                transform=T["geometry_msgs/msg/Transform"](translation=_vec(T, xyz[i]),
                                                           rotation=_quat(T, q[i])))
            msg = T["tf2_msgs/msg/TFMessage"](transforms=[ts])
        sink.put(topic, t + LAT_INS_NS, msg)


def _enu_attitude(ins: InsSamples) -> np.ndarray:
    from v2xlake.tasks.geodesy import attitude_to_matrix

    return attitude_to_matrix(ins.roll, ins.pitch, ins.azimuth)


def _vec(T: Any, v: np.ndarray) -> Any:
    return T["geometry_msgs/msg/Vector3"](x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _quat(T: Any, q_wxyz: np.ndarray) -> Any:
    return T["geometry_msgs/msg/Quaternion"](x=float(q_wxyz[1]), y=float(q_wxyz[2]),
                                             z=float(q_wxyz[3]), w=float(q_wxyz[0]))


def pose_config(cfg: SimConfig, agent: str
                ) -> tuple[list[SensorConfig], InsPose | OdometryPose | SplitPose | TfPose]:
    """The clip.yaml sensors of the pose stream (IMU and GNSS are declared elsewhere) and the
    agent's ``pose:`` block for ``cfg.pose_format``."""
    fmt = cfg.pose_format
    topic, typ = pose_topic(agent, fmt)
    if fmt == "navsat-imu":
        fix = SensorConfig(name="INS_FIX", modality=Modality.INS, topic=topic, msg_type=typ,
                           frame_id=EGO_FRAME, rate_hz=125.0)
        return [fix], SplitPose(position="INS_FIX", attitude="IMU", sample_at="position")
    sensor = SensorConfig(name="INS", modality=Modality.INS, topic=topic, msg_type=typ,
                          frame_id=EGO_FRAME, rate_hz=125.0)
    if fmt == "inspva":
        return [sensor], InsPose(sensor="INS", fields=InsFields(
            latitude="latitude", longitude="longitude", height="altitude", roll="roll",
            pitch="pitch", heading="azimuth", status="rtk_status", velocity=Vec3Paths(
                x="east_velocity", y="north_velocity", z="up_velocity")))
    if fmt == "odometry":
        return [sensor], OdometryPose(sensor="INS", map_frame=MAP_FRAME, datum=Datum(
            kind=DatumKind.UTM, utm_zone=utm_zone(cfg.origin_lon),
            hemisphere="south" if cfg.origin_lat < 0 else "north", offset=utm_offset(cfg)))
    return [sensor], TfPose(sensor="INS", parent_frame=MAP_FRAME, datum=Datum(
        kind=DatumKind.GEODETIC,
        origin=GeodeticPoint(latitude=cfg.origin_lat, longitude=cfg.origin_lon, height=0.0)))


def fixed_pose(ins: InsSamples) -> FixedPose:
    """A roadside unit's surveyed pose: its (static) INS solution's first sample."""
    return FixedPose(
        geodetic=GeodeticPoint(latitude=float(ins.lat[0]), longitude=float(ins.lon[0]),
                               height=float(ins.alt[0])),
        attitude=FixedAttitude(roll=float(ins.roll[0]), pitch=float(ins.pitch[0]),
                               heading=float(ins.azimuth[0])),
        angle_unit=AngleUnit.RAD)
