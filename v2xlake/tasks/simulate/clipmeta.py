"""The clip folder's ``clip.yaml`` and custom message definition, as the input contract says.

Calibration is NOT put into clip.yaml: it travels in the bags (``/tf_static`` with the
published, slightly wrong extrinsics and ``camera_info``), which is what ingest must read.
"""

from __future__ import annotations

from pathlib import Path

from v2xlake.schemas.clip import (
    AgentConfig,
    AgentDimensions,
    AgentKind,
    AgentRole,
    ClipConfig,
    FixedPose,
    LidarFields,
    Lighting,
    Modality,
    NoPose,
    PointTimeField,
    PoseConfig,
    RoadType,
    SensorConfig,
    TimeReference,
    TimeUnit,
    Weather,
)
from v2xlake.tasks.simulate import navformats
from v2xlake.tasks.simulate.bagwrite import INS_MSG_TEXT
from v2xlake.tasks.simulate.config import SimConfig
from v2xlake.tasks.simulate.rig import AgentRig, frame_name
from v2xlake.tasks.simulate.scene import AGENT_SIZE, EGO_HEIGHT

MSG_REL = "msgs/v2xlake_msgs/msg/InsPva.msg"
EGO_FRAME = "base_link"


def lidar_topic(agent: str) -> str:
    return f"/{agent}/lidar/points"


def side_lidar_topic(agent: str) -> str:
    """Topic of the optional second LiDAR (``SimConfig.side_lidar``, sensor LIDAR_LEFT)."""
    return f"/{agent}/lidar_left/points"


def radar_topic(agent: str) -> str:
    return f"/{agent}/radar/points"


def image_topic(agent: str, cam: str) -> str:
    return f"/{agent}/camera/{cam}/image"


def info_topic(agent: str, cam: str) -> str:
    return f"/{agent}/camera/{cam}/camera_info"


def bag_name(agent: str, storage: str) -> str:
    return f"{agent}.bag" if storage == "ros1" else agent


def build_clip_config(cfg: SimConfig, rigs: dict[str, AgentRig],
                      fixed: dict[str, FixedPose] | None = None) -> ClipConfig:
    """clip.yaml of a simulated clip: vehicles read their pose in ``cfg.pose_format``
    (``navformats``), a roadside unit has its surveyed pose in ``fixed``."""
    fixed = fixed or {}
    agents = []
    for agent in cfg.agents:
        rig = rigs[agent]
        sensors = [SensorConfig(
            name="LIDAR_TOP", modality=Modality.LIDAR, topic=lidar_topic(agent),
            msg_type="sensor_msgs/msg/PointCloud2", frame_id=frame_name(agent, "LIDAR_TOP"),
            fields=LidarFields(intensity="intensity", ring="ring", return_id="return_type",
                               time=PointTimeField(field="timestamp", unit=TimeUnit.S,
                                                   reference=TimeReference.ABSOLUTE)),
            rate_hz=cfg.lidar.rate_hz)]
        if rig.T_ego_side_true is not None:
            sensors.append(SensorConfig(
                name="LIDAR_LEFT", modality=Modality.LIDAR, topic=side_lidar_topic(agent),
                msg_type="sensor_msgs/msg/PointCloud2",
                frame_id=frame_name(agent, "LIDAR_LEFT"),
                fields=LidarFields(intensity="intensity", ring="ring", return_id="return_type",
                                   time=PointTimeField(field="timestamp", unit=TimeUnit.S,
                                                       reference=TimeReference.ABSOLUTE)),
                rate_hz=cfg.side_lidar_spec.rate_hz))
        if cfg.radar and agent != "rsu":
            sensors.append(SensorConfig(
                name="RADAR_FRONT", modality=Modality.RADAR, topic=radar_topic(agent),
                msg_type="sensor_msgs/msg/PointCloud2", frame_id=frame_name(agent, "RADAR_FRONT"),
                fields=LidarFields(intensity=None, ring=None, velocity="v_r", rcs="rcs"),
                rate_hz=20.0))
        for cam in rig.cameras:
            sensors.append(SensorConfig(
                name=cam, modality=Modality.CAMERA, topic=image_topic(agent, cam),
                msg_type="sensor_msgs/msg/CompressedImage", frame_id=frame_name(agent, cam),
                camera_info_topic=info_topic(agent, cam), rate_hz=cfg.camera_hz))
        pose: PoseConfig
        if agent == "rsu":
            pose = fixed.get(agent) or NoPose()
        else:
            pose_sensors, pose = navformats.pose_config(cfg, agent)
            sensors += [
                *pose_sensors,
                SensorConfig(name="IMU", modality=Modality.IMU, topic=f"/{agent}/imu",
                             msg_type="sensor_msgs/msg/Imu", frame_id=EGO_FRAME, rate_hz=125.0),
                SensorConfig(name="GNSS", modality=Modality.GNSS, topic=f"/{agent}/gnss",
                             msg_type="sensor_msgs/msg/NavSatFix", frame_id=EGO_FRAME,
                             rate_hz=10.0),
            ]
        dims = None if agent == "rsu" else AgentDimensions(
            length_m=AGENT_SIZE[0], width_m=AGENT_SIZE[1], height_m=AGENT_SIZE[2],
            center_in_ego=(0.0, 0.0, AGENT_SIZE[2] / 2 - EGO_HEIGHT))
        agents.append(AgentConfig(
            agent_id=agent, kind=AgentKind.ROADSIDE if agent == "rsu" else AgentKind.VEHICLE,
            role=AgentRole.REFERENCE if agent == "red" else AgentRole.COOPERATIVE,
            bag=bag_name(agent, cfg.storage), ego_frame=EGO_FRAME, tf_static_topic="/tf_static",
            sensors=sensors, pose=pose, dimensions=dims))
    return ClipConfig(clip_id=cfg.name, location="simtown", road_type=RoadType.ARTERIAL,
                      weather=Weather.CLEAR, lighting=Lighting.DAY, work_zone=False,
                      agents=agents, message_definitions=[MSG_REL],
                      annotations="annotations.json")


def write_msg_definition(out: Path) -> Path:
    p = out / MSG_REL
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(INS_MSG_TEXT)
    return p
