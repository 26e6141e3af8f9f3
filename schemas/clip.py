"""The ``clip.yaml`` input contract (DESIGN.md, "Input contract: a clip folder").

A clip folder holds one bag per agent plus this file, which says what the bags cannot: the
conditions, which agent is the reference, and per sensor the topic, message type, field
mapping and calibration source. Real recordings are ingested by writing one of these files,
never by changing code, so every driver-specific quirk (time field name, unit, reference)
must be expressible here.
"""

from __future__ import annotations

from enum import StrEnum
from pathlib import Path
from typing import Any, Literal, Self

import yaml
from pydantic import BaseModel, ConfigDict, Field, model_validator

from v2xlake.schemas.calibration import CameraIntrinsics
from v2xlake.schemas.geometry import Transform, Vec3

ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_\-]*$"


class Weather(StrEnum):
    CLEAR = "clear"
    OVERCAST = "overcast"
    RAIN = "rain"
    SNOW = "snow"
    FOG = "fog"


class Lighting(StrEnum):
    DAY = "day"
    DAWN = "dawn"
    DUSK = "dusk"
    DIRECT_SUN = "direct_sun"
    NIGHT = "night"


class RoadType(StrEnum):
    HIGHWAY = "highway"
    ARTERIAL = "arterial"
    COLLECTOR = "collector"
    LOCAL = "local"


class AgentKind(StrEnum):
    VEHICLE = "vehicle"
    ROADSIDE = "roadside"


class AgentRole(StrEnum):
    REFERENCE = "reference"
    COOPERATIVE = "cooperative"


class Modality(StrEnum):
    LIDAR = "lidar"
    CAMERA = "camera"
    INS = "ins"
    IMU = "imu"
    GNSS = "gnss"
    RADAR = "radar"


class TimeUnit(StrEnum):
    S = "s"
    MS = "ms"
    US = "us"
    NS = "ns"


class TimeReference(StrEnum):
    """What a per-point time field is measured from."""

    ABSOLUTE = "absolute"  # GNSS epoch time
    HEADER = "header"  # offset from the message header stamp (Ouster ``t``, Velodyne ``time``)


class PointTimeField(BaseModel):
    model_config = ConfigDict(frozen=True)

    field: str
    unit: TimeUnit
    reference: TimeReference


class LidarFields(BaseModel):
    """Which PointCloud2 fields carry what. ``None`` means the sensor does not provide it."""

    model_config = ConfigDict(frozen=True)

    x: str = "x"
    y: str = "y"
    z: str = "z"
    intensity: str | None = "intensity"
    ring: str | None = "ring"
    return_id: str | None = None
    time: PointTimeField


class SensorConfig(BaseModel):
    """One sensor of one agent.

    Calibration comes from ``extrinsic`` / ``intrinsics`` when given, else from the agent's
    ``tf_static_topic`` (looked up by ``frame_id``) and ``camera_info_topic``.
    """

    model_config = ConfigDict(frozen=True)

    name: str = Field(pattern=ID_PATTERN, description="channel name, e.g. LIDAR_TOP, CAM_FRONT")
    modality: Modality
    topic: str = Field(pattern=r"^/")
    msg_type: str = Field(description="ROS type name, e.g. sensor_msgs/msg/PointCloud2")
    frame_id: str | None = None
    fields: LidarFields | None = None
    extrinsic: Transform | None = Field(default=None, description="T_ego_sensor")
    intrinsics: CameraIntrinsics | None = None
    camera_info_topic: str | None = None
    rate_hz: float | None = Field(default=None, gt=0)

    @model_validator(mode="after")
    def _lidar_needs_fields(self) -> Self:
        if self.modality is Modality.LIDAR and self.fields is None:
            raise ValueError(
                f"lidar sensor {self.name!r} needs a 'fields' mapping with a time field"
            )
        return self


class InsFields(BaseModel):
    """Which field of a vendor INS message holds what (None: the usual names are tried)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    lat: str | None = None
    lon: str | None = None
    height: str | None = None
    roll: str | None = None
    pitch: str | None = None
    heading: str | None = None
    v_east: str | None = None
    v_north: str | None = None
    v_up: str | None = Field(default=None, description="or down, with velocity_axes ned")
    status: str | None = None


class Datum(BaseModel):
    """What turns a local map frame into the clip's world: the map is a local ENU frame
    whose origin is this geodetic point (``lat``/``lon`` degrees, ``alt`` metres), after
    subtracting ``offset`` (a map frame with a large false origin). Without ``lat``/``lon``
    the map is taken as already local ENU (its raw geodetic values are then nominal)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    lat: float | None = Field(default=None, ge=-90, le=90)
    lon: float | None = Field(default=None, ge=-180, le=180)
    alt: float = 0.0
    offset: Vec3 = Field(default_factory=lambda: [0.0, 0.0, 0.0])


class PoseSource(BaseModel):
    """Where an agent's pose comes from (one pose track comes out of every kind):

    - ``ins``: a vendor INS message on ``topic`` (WGS84 position, attitude, velocities), with
      ``fields``, ``angle_unit`` (deg / rad), ``heading`` (azimuth from north clockwise, or
      yaw from east counter-clockwise) and ``velocity_axes`` (ENU or NED);
    - ``odometry``: ``nav_msgs/msg/Odometry``, ``geometry_msgs/msg/PoseStamped`` or
      ``PoseWithCovarianceStamped`` on ``topic``, in a local map frame given by ``datum``;
    - ``navsat_imu``: position from ``sensor_msgs/msg/NavSatFix`` on ``topic`` and attitude
      from the orientation of ``sensor_msgs/msg/Imu`` on ``attitude_topic`` (ENU, REP 103),
      interpolated (SLERP) to the fix times;
    - ``fixed``: a surveyed pose (a roadside unit): ``position`` lat/lon/alt (degrees, m)
      and ``attitude`` roll/pitch/heading (degrees, heading from north clockwise);
    - ``none``: the agent has no pose; pose-dependent stages say "not applicable".
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    kind: Literal["ins", "odometry", "navsat_imu", "fixed", "none"]
    topic: str | None = Field(default=None, pattern=r"^/")
    msg_type: str | None = None
    attitude_topic: str | None = Field(default=None, pattern=r"^/")
    fields: InsFields | None = None
    angle_unit: Literal["rad", "deg"] = "rad"
    heading: Literal["north_cw", "east_ccw"] = "north_cw"
    velocity_axes: Literal["enu", "ned"] = "enu"
    datum: Datum | None = None
    position: Vec3 | None = None
    attitude: Vec3 | None = None
    rate_hz: float | None = Field(default=None, gt=0)

    @model_validator(mode="after")
    def _complete(self) -> Self:
        need = {"ins": ("topic",), "odometry": ("topic", "msg_type"),
                "navsat_imu": ("topic", "attitude_topic"), "fixed": ("position", "attitude"),
                "none": ()}[self.kind]
        missing = [n for n in need if getattr(self, n) is None]
        if missing:
            raise ValueError(f"pose kind {self.kind!r} needs {missing}")
        if self.kind == "odometry" and self.msg_type not in ODOMETRY_TYPES:
            raise ValueError(f"pose kind 'odometry' reads {list(ODOMETRY_TYPES)}, "
                             f"not {self.msg_type!r}")
        return self


ODOMETRY_TYPES = ("nav_msgs/msg/Odometry", "geometry_msgs/msg/PoseStamped",
                  "geometry_msgs/msg/PoseWithCovarianceStamped")


class AgentConfig(BaseModel):
    model_config = ConfigDict(frozen=True)

    agent_id: str = Field(pattern=ID_PATTERN)
    kind: AgentKind
    role: AgentRole
    bag: str = Field(description="bag path relative to the clip folder")
    ego_frame: str = Field(default="base_link", description="the INS/IMU frame in tf_static")
    tf_static_topic: str | None = "/tf_static"
    pose: PoseSource | None = Field(
        default=None, description="where the pose comes from; without it, the sensor of "
        "modality 'ins' (the simulator's layout)")
    sensors: list[SensorConfig]

    @model_validator(mode="after")
    def _unique_sensors(self) -> Self:
        names = [s.name for s in self.sensors]
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise ValueError(f"agent {self.agent_id!r}: duplicate sensor names {sorted(dup)}")
        return self

    def sensor(self, name: str) -> SensorConfig:
        for s in self.sensors:
            if s.name == name:
                return s
        raise KeyError(f"agent {self.agent_id!r} has no sensor {name!r}")

    def sensors_of(self, modality: Modality) -> list[SensorConfig]:
        return [s for s in self.sensors if s.modality is modality]


class ClipConfig(BaseModel):
    """The whole ``clip.yaml``."""

    model_config = ConfigDict(frozen=True)

    clip_id: str = Field(pattern=ID_PATTERN)
    location: str
    road_type: RoadType
    weather: Weather
    lighting: Lighting
    work_zone: bool = False
    agents: list[AgentConfig] = Field(min_length=1)
    message_definitions: list[str] = Field(
        default_factory=list,
        description=".msg files (relative to the clip folder) for custom types, e.g. a vendor INS",
    )
    annotations: str | None = Field(default=None, description="annotation file, relative path")
    params: dict[str, dict[str, Any]] = Field(
        default_factory=dict,
        description="pipeline parameters that belong to this recording, one section per stage "
                    "(e.g. qa tolerances of its rig); they override the run's parameters")

    @model_validator(mode="after")
    def _one_reference(self) -> Self:
        refs = [a.agent_id for a in self.agents if a.role is AgentRole.REFERENCE]
        if len(refs) != 1:
            raise ValueError(f"exactly one agent must have role 'reference', got {refs}")
        ids = [a.agent_id for a in self.agents]
        if len(set(ids)) != len(ids):
            raise ValueError(f"agent ids must be unique, got {ids}")
        return self

    @property
    def reference_agent(self) -> AgentConfig:
        return next(a for a in self.agents if a.role is AgentRole.REFERENCE)

    def agent(self, agent_id: str) -> AgentConfig:
        for a in self.agents:
            if a.agent_id == agent_id:
                return a
        raise KeyError(f"clip {self.clip_id!r} has no agent {agent_id!r}")

    @classmethod
    def load(cls, clip_dir: str | Path) -> ClipConfig:
        path = Path(clip_dir) / "clip.yaml"
        with path.open() as f:
            return cls.model_validate(yaml.safe_load(f))

    def dump(self, clip_dir: str | Path) -> Path:
        path = Path(clip_dir) / "clip.yaml"
        data = self.model_dump(mode="json", exclude_none=True)
        path.write_text(yaml.safe_dump(data, sort_keys=False))
        return path
