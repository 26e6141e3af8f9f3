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


class CameraIntrinsics(BaseModel):
    """Pinhole intrinsics plus distortion, checked against the image size they claim (and,
    at ingest, against the size of the images themselves)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    width: int = Field(gt=0)
    height: int = Field(gt=0)
    fx: float = Field(gt=0)
    fy: float = Field(gt=0)
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
