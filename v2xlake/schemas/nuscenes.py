"""The 13 nuScenes tables, as the official ``nuscenes-devkit`` reads them.

Field names and shapes follow the devkit's JSON exactly (tokens are 32-hex strings, times are
integer microseconds, quaternions w, x, y, z, box size is width, length, height). Export code
builds these models and dumps them; the catalog derives its Arrow schemas from them.
"""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field

Token = Annotated[str, Field(pattern=r"^[0-9a-f]{32}$")]
OptToken = Annotated[str, Field(pattern=r"^([0-9a-f]{32})?$")]  # "" ends a prev/next chain
Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]
Quat = Annotated[list[float], Field(min_length=4, max_length=4)]


class _Row(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


class Log(_Row):
    token: Token
    logfile: str
    vehicle: str
    date_captured: str
    location: str


class Map(_Row):
    token: Token
    log_tokens: list[Token]
    category: str = "semantic_prior"
    filename: str


class Scene(_Row):
    token: Token
    log_token: Token
    nbr_samples: int
    first_sample_token: Token
    last_sample_token: Token
    name: str
    description: str


class Sample(_Row):
    token: Token
    timestamp: int
    prev: OptToken
    next: OptToken
    scene_token: Token


class Sensor(_Row):
    token: Token
    channel: str
    modality: str  # lidar | camera | radar


class CalibratedSensor(_Row):
    token: Token
    sensor_token: Token
    translation: Vec3
    rotation: Quat
    camera_intrinsic: list[list[float]]  # 3x3, or [] for non-cameras


class EgoPose(_Row):
    token: Token
    timestamp: int
    rotation: Quat
    translation: Vec3


class SampleData(_Row):
    token: Token
    sample_token: Token
    ego_pose_token: Token
    calibrated_sensor_token: Token
    timestamp: int
    fileformat: str
    is_key_frame: bool
    height: int
    width: int
    filename: str
    prev: OptToken
    next: OptToken


class Category(_Row):
    token: Token
    name: str
    description: str
    index: int | None = None


class Attribute(_Row):
    token: Token
    name: str
    description: str


class Visibility(_Row):
    token: str  # "1".."4" in nuScenes
    level: str
    description: str


class Instance(_Row):
    token: Token
    category_token: Token
    nbr_annotations: int
    first_annotation_token: Token
    last_annotation_token: Token


class SampleAnnotation(_Row):
    token: Token
    sample_token: Token
    instance_token: Token
    visibility_token: str
    attribute_tokens: list[Token]
    translation: Vec3
    size: Vec3
    rotation: Quat
    prev: OptToken
    next: OptToken
    num_lidar_pts: int
    num_radar_pts: int


NUSCENES_TABLES: dict[str, type[_Row]] = {
    "attribute": Attribute,
    "calibrated_sensor": CalibratedSensor,
    "category": Category,
    "ego_pose": EgoPose,
    "instance": Instance,
    "log": Log,
    "map": Map,
    "sample": Sample,
    "sample_annotation": SampleAnnotation,
    "sample_data": SampleData,
    "scene": Scene,
    "sensor": Sensor,
    "visibility": Visibility,
}
