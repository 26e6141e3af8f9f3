"""QA's thresholds (pydantic only: ``v2xlake params show`` imports this module without the
stage's numeric code). Rates and sync models are the sensors' own (``clip.yaml``); these
are the tolerances applied to them, settable per clip in its ``params: qa:``."""

from __future__ import annotations

from typing import ClassVar

from pydantic import Field

from v2xlake.schemas.config import POSE_GAP_PERIODS, Section, StageConfig


class GridTolerance(Section):
    """How far a PPS-locked sensor's stamp may lie from its grid, per modality (ms)."""

    lidar: float = Field(1.0, gt=0, description="PPS grid tolerance, LiDAR")
    camera: float = Field(1.0, gt=0, description="PPS grid tolerance, cameras")
    ins: float = Field(0.5, gt=0, description="PPS grid tolerance, pose sources")
    imu: float = Field(0.5, gt=0, description="PPS grid tolerance, IMUs")
    gnss: float = Field(1.0, gt=0, description="PPS grid tolerance, GNSS fixes")
    radar: float = Field(1.0, gt=0, description="PPS grid tolerance, radars")


class StreamChecks(Section):
    """Every sensor's stream of stamps: its rate, jitter and dropped frames."""

    free_jitter_fraction: float = Field(
        0.25, gt=0, description="free-running sensors: largest deviation of an interval from "
        "a whole number of periods, as a fraction of the period (unless its sync gives "
        "tolerance_ms)")
    rate_mismatch_fraction: float = Field(
        0.1, gt=0, description="a declared rate_hz further than this (relative) from the "
        "measured median rate is an error")
    max_dropped_fraction: float = Field(0.05, ge=0, description="dropped frames: above this "
                                        "fraction an error, else a warning")


class ScanSpan(Section):
    """A LiDAR scan's per-point time span against its expected share of a revolution."""

    min: float = Field(0.5, description="min scan time span / expected span "
                       "(period x scan_fov_deg / 360)")
    max: float = Field(1.05, description="max scan time span / expected span")


class RtkChecks(Section):
    """The pose source's solution status."""

    min_fixed_fraction: float = Field(0.9, ge=0, le=1, description="a smaller fraction of "
                                      "RTK-fixed samples is a warning")
    fixed_status: int = Field(2, description="the status value that means RTK fixed")


class PoseCoverage(Section):
    """Whether the agent's pose track brackets every LiDAR scan densely (deskew needs it)."""

    max_gap_ms: float = Field(20.0, gt=0, description="largest pose gap inside a scan "
                              "(at least gap_periods of the pose source's period)")
    gap_periods: float = Field(POSE_GAP_PERIODS, gt=1, description="a pose gap longer than "
                               "this many periods of its source leaves a scan uncovered")
    edge_scans: int = Field(1, ge=0, description=(
        "scans at each end of the clip that may reach past the first/last pose sample "
        "(recording boundaries): a warning; more, or any gap inside, is an error"))


class QaConfig(StageConfig):
    """Thresholds of the QA stage (hashed into the manifest)."""

    RENAMED: ClassVar[dict[str, str]] = {
        **{f"{m}_tolerance_ms": f"tolerance_ms.{m}"
           for m in ("lidar", "camera", "ins", "imu", "gnss", "radar")},
        **{k: f"stream.{k}" for k in ("free_jitter_fraction", "rate_mismatch_fraction",
                                      "max_dropped_fraction")},
        "scan_span_min": "scan_span.min", "scan_span_max": "scan_span.max",
        "min_rtk_fixed_fraction": "rtk.min_fixed_fraction",
        "rtk_fixed_status": "rtk.fixed_status",
        "ins_max_gap_ms": "pose_coverage.max_gap_ms",
        "pose_gap_periods": "pose_coverage.gap_periods",
        "ins_edge_scans": "pose_coverage.edge_scans"}

    tolerance_ms: GridTolerance = Field(default_factory=GridTolerance)
    stream: StreamChecks = Field(default_factory=StreamChecks)
    scan_span: ScanSpan = Field(default_factory=ScanSpan)
    rtk: RtkChecks = Field(default_factory=RtkChecks)
    pose_coverage: PoseCoverage = Field(default_factory=PoseCoverage)
