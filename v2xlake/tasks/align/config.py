"""The align stage's parameters (pydantic only: ``v2xlake params show`` imports this module
without the stage's numeric code). ``association`` is what the three methods of
``methods.py`` take directly."""

from __future__ import annotations

from typing import ClassVar, Literal

from pydantic import Field

from v2xlake.schemas.config import ANNOTATED_LIDAR, Section, StageConfig

TimeStat = Literal["vote", "median", "mean"]


class AssociationConfig(Section):
    """How a LiDAR scan (or one object of it) is paired with a camera frame."""

    frame_time_stat: TimeStat = Field(
        "vote", description="frame-based: the statistic of the camera's points' times")
    target_time_stat: TimeStat = Field(
        "vote", description="target-based: the statistic of the object's points' times")
    unwrap_seam: bool = Field(
        True, description="median / mean: treat point times as phases of one revolution "
        "(a set straddling the scan start is cut at its largest gap)")
    # the paper aligns the camera whose view holds the scan seam with the scan start
    # (Sec. 5.2, Fig. 6, its forward cameras)
    seam_camera: Literal["start", "points"] = Field(
        "start", description="frame-based, a camera whose view holds the scan seam (points "
        "from the first and the last seam_window of the scan): align it with the scan start, "
        "or let the points decide")
    seam_window: float = Field(0.05, gt=0, lt=0.5, description="fraction of the scan period")
    fov_near_m: float = Field(0.5, gt=0, description="points nearer the camera are not in "
                              "its view")
    box_margin_m: float = Field(0.2, ge=0, description="grow boxes when collecting an "
                                "object's points")
    use_velocity: bool = Field(True, description="target-based: move objects to the camera "
                               "time with their velocity")
    velocity_from_track: bool = Field(
        True, description="estimate missing velocities from the instance's track")
    max_camera_dt_ms: float = Field(
        50.0, gt=0, description="no camera frame this close to the association time: skip")


class TruthConfig(Section):
    """The simulator's true 2D boxes the methods are scored against (when given)."""

    min_box_px: float = Field(4.0, ge=0, description="ignore smaller true boxes")
    min_pixels: int = Field(50, ge=0, description="ignore true objects with fewer visible "
                            "pixels")
    box: Literal["amodal", "visible"] = Field(
        "amodal", description="the whole object's extent clipped to the image, or its "
        "unoccluded pixels")


class AlignConfig(StageConfig):
    """Parameters of the align stage (hashed into the manifest)."""

    RENAMED: ClassVar[dict[str, str]] = {
        **{k: f"association.{k}" for k in (
            "frame_time_stat", "target_time_stat", "unwrap_seam", "seam_camera", "seam_window",
            "fov_near_m", "box_margin_m", "use_velocity", "velocity_from_track",
            "max_camera_dt_ms")},
        "min_truth_box_px": "truth.min_box_px", "min_truth_pixels": "truth.min_pixels",
        "truth_box": "truth.box"}

    lidar_sensor: str = Field(ANNOTATED_LIDAR, description="the LiDAR the boxes are annotated in")
    cameras: list[str] | None = Field(default=None, description="None: every camera")
    association: AssociationConfig = Field(default_factory=AssociationConfig)
    truth: TruthConfig = Field(default_factory=TruthConfig)
    overlay: bool = Field(True, description="draw one overlay picture per camera")
