"""3D box annotations with the CATS-V2V taxonomy (main paper Sec. 3.4).

Boxes are given per LiDAR frame of one agent, in that LiDAR's frame at the scan start ``t0``
(the deskewed frame, which is what annotators label). ``t_ns`` is the time the box state
refers to: for a moving object, the moment the beam swept it. Instance ids are global: the
same car seen by both agents carries one id, which is what makes cross-agent re-identification
and the nuScenes ``instance`` table possible.
"""

from __future__ import annotations

from enum import StrEnum
from pathlib import Path
from typing import Annotated, Self

import yaml
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from v2xlake.schemas.config import ANNOTATED_LIDAR
from v2xlake.schemas.geometry import Quat, Vec3

Size3 = Annotated[list[float], Field(min_length=3, max_length=3)]


class ObjectClass(StrEnum):
    CAR = "Car"
    VAN = "Van"
    TRUCK = "Truck"
    TRAILER = "Trailer"
    BUS = "Bus"
    OTHERS = "Others"
    PEDESTRIAN = "Pedestrian"
    SCOOTER = "Scooter"
    BICYCLE = "Bicycle"
    MOTORCYCLE = "Motorcycle"

    @property
    def is_vru(self) -> bool:
        return self in _VRU


_VRU = {ObjectClass.PEDESTRIAN, ObjectClass.SCOOTER, ObjectClass.BICYCLE, ObjectClass.MOTORCYCLE}

# nuScenes category names for the detection benchmark (nuscenes-devkit's DETECTION_NAMES
# are derived from these by its own mapping).
NUSCENES_CATEGORY: dict[ObjectClass, str] = {
    ObjectClass.CAR: "vehicle.car",
    ObjectClass.VAN: "vehicle.car",
    ObjectClass.TRUCK: "vehicle.truck",
    ObjectClass.TRAILER: "vehicle.trailer",
    ObjectClass.BUS: "vehicle.bus.rigid",
    ObjectClass.OTHERS: "vehicle.construction",
    ObjectClass.PEDESTRIAN: "human.pedestrian.adult",
    ObjectClass.SCOOTER: "human.pedestrian.personal_mobility",
    ObjectClass.BICYCLE: "vehicle.bicycle",
    ObjectClass.MOTORCYCLE: "vehicle.motorcycle",
}


class Box3D(BaseModel):
    """Oriented box; ``size`` is (width, length, height) as in nuScenes."""

    model_config = ConfigDict(frozen=True)

    center: Vec3
    size: Size3
    rotation: Quat = Field(description="w, x, y, z; box x-axis is its length / heading")

    @field_validator("size")
    @classmethod
    def _positive(cls, v: list[float]) -> list[float]:
        if any(s <= 0 for s in v):
            raise ValueError(f"box size (w, l, h) must be positive, got {v}")
        return v

    @field_validator("rotation")
    @classmethod
    def _unit(cls, v: list[float]) -> list[float]:
        n = sum(c * c for c in v) ** 0.5
        if abs(n - 1.0) > 1e-6:
            raise ValueError(f"box rotation must be a unit quaternion, norm is {n:.9f}")
        return v


class BoxAnnotation(BaseModel):
    model_config = ConfigDict(frozen=True)

    agent_id: str
    sensor: str = ANNOTATED_LIDAR
    frame_idx: int = Field(ge=0)
    t_ns: int = Field(description="time the box state refers to (raw zone: GNSS epoch ns)")
    instance_id: str = Field(description="global id, shared across agents and frames")
    category: ObjectClass
    box: Box3D
    velocity: Vec3 | None = Field(
        default=None, description="m/s over ground (the object's own motion in the world, a "
        "parked car 0 whatever the sensor does), in the same frame's axes")
    links: list[str] = Field(default_factory=list, description="instance ids physically coupled")
    num_lidar_pts: int | None = Field(default=None, ge=0)


class AnnotationFile(BaseModel):
    """The optional annotation file named by ``clip.yaml``."""

    model_config = ConfigDict(frozen=True)

    clip_id: str
    coordinate_frame: str = Field(default="lidar_t0", pattern=r"^lidar_t0$")
    annotations: list[BoxAnnotation]

    @model_validator(mode="after")
    def _links_resolve(self) -> Self:
        ids = {a.instance_id for a in self.annotations}
        for a in self.annotations:
            missing = [link for link in a.links if link not in ids]
            if missing:
                raise ValueError(f"instance {a.instance_id!r} links to unknown instances {missing}")
        return self

    @classmethod
    def load(cls, path: str | Path) -> AnnotationFile:
        p = Path(path)
        text = p.read_text()
        data = yaml.safe_load(text)  # JSON is YAML
        return cls.model_validate(data)
