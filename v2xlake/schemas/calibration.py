"""Camera intrinsics and per-sensor calibration records."""

from __future__ import annotations

from enum import StrEnum
from typing import Self

from pydantic import BaseModel, ConfigDict, Field, model_validator

from v2xlake.schemas.geometry import Transform


class DistortionModel(StrEnum):
    """ROS ``CameraInfo.distortion_model`` names.

    plumb_bob is OpenCV's 5-parameter radial-tangential model.
    """

    NONE = "none"
    PLUMB_BOB = "plumb_bob"
    RATIONAL_POLYNOMIAL = "rational_polynomial"
    EQUIDISTANT = "equidistant"


_N_COEFFS = {
    DistortionModel.NONE: (0,),
    DistortionModel.PLUMB_BOB: (5,),
    DistortionModel.RATIONAL_POLYNOMIAL: (8, 12, 14),
    DistortionModel.EQUIDISTANT: (4,),
}


#: Bounds of a focal length in pixels. Below one pixel the whole image would span more than
#: a radian per pixel (no pinhole or fisheye camera does); above 10^6 pixels a 10,000-pixel
#: image would see less than 0.6 degrees (a telescope, not a driving camera). Outside, the
#: number is a unit mistake or an attack, and projections with it are meaningless.
MIN_FOCAL_PX = 1.0
MAX_FOCAL_PX = 1e6
#: Largest image side accepted, pixels (beyond any automotive sensor).
MAX_IMAGE_SIDE = 100_000


class CameraIntrinsics(BaseModel):
    """Pinhole intrinsics plus distortion, checked against the image size they claim (and,
    at ingest, against the size of the images themselves)."""

    # Every number finite (``allow_inf_nan=False``): a NaN distortion coefficient or an
    # infinite focal length validated here used to reach anonymize, whose projection of
    # faces and plates then silently covered nothing (or crashed there, far from the cause).
    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    width: int = Field(gt=0, le=MAX_IMAGE_SIDE)
    height: int = Field(gt=0, le=MAX_IMAGE_SIDE)
    fx: float = Field(ge=MIN_FOCAL_PX, le=MAX_FOCAL_PX, description="pixels")
    fy: float = Field(ge=MIN_FOCAL_PX, le=MAX_FOCAL_PX, description="pixels")
    cx: float
    cy: float
    distortion_model: DistortionModel = DistortionModel.NONE
    distortion: list[float] = Field(default_factory=list)

    @model_validator(mode="after")
    def _consistent(self) -> Self:
        if not (0 <= self.cx <= self.width and 0 <= self.cy <= self.height):
            raise ValueError(
                f"principal point ({self.cx}, {self.cy}) lies outside the "
                f"{self.width}x{self.height} image"
            )
        allowed = _N_COEFFS[self.distortion_model]
        n = len(self.distortion)
        if self.distortion_model is DistortionModel.NONE and n and any(self.distortion):
            raise ValueError("distortion coefficients given but distortion_model is 'none'")
        if self.distortion_model is not DistortionModel.NONE and n not in allowed:
            raise ValueError(
                f"distortion_model {self.distortion_model.value} needs {allowed} "
                f"coefficients, got {n}"
            )
        return self

    def k_matrix(self) -> list[list[float]]:
        return [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]]


class SensorCalibration(BaseModel):
    """Where a sensor sits on its agent (``T_ego_sensor``) and, for cameras, how it projects."""

    model_config = ConfigDict(frozen=True)

    T_ego_sensor: Transform
    intrinsics: CameraIntrinsics | None = None
