"""The deskew stage's parameters (pydantic only: ``v2xlake params show`` imports this module
without the stage's numeric code)."""

from __future__ import annotations

from typing import ClassVar, Literal

from pydantic import Field

from v2xlake.schemas.config import POSE_GAP_PERIODS, Section, StageConfig


class UncoveredPolicy(Section):
    """Scans whose points the pose track does not cover (it starts late, stops early, or
    has a gap inside the scan)."""

    max_fraction: float = Field(
        0.0, ge=0.0, le=1.0,
        description="a frame with more of its points outside INS coverage cannot be compensated")
    policy: Literal["error", "skip_edge", "skip"] = Field(
        "skip_edge",
        description="uncompensable frames: error always; skip those at the clip's edges "
                    "(INS starts late / stops early) and error in the middle; or skip all")


class PoseGaps(Section):
    """Pose samples too far apart to interpolate across."""

    max_ns: int | None = Field(
        None, gt=0,
        description="pose samples further apart than this are a gap, not something to "
                    "interpolate across; default: periods of the pose track's median "
                    "period, at least 50 ms (125 Hz INS: 50 ms; a 10 Hz localisation: "
                    "250 ms), as QA judges it")
    periods: float = Field(
        POSE_GAP_PERIODS, gt=1, description="with max_ns unset: a gap is longer than this "
                                            "many periods of the pose track")


class DeskewConfig(StageConfig):
    """Parameters of the deskew stage (hashed into the manifest)."""

    RENAMED: ClassVar[dict[str, str]] = {
        "max_uncovered_fraction": "uncovered.max_fraction", "on_uncovered": "uncovered.policy",
        "max_pose_gap_ns": "pose_gaps.max_ns", "pose_gap_periods": "pose_gaps.periods"}

    reference: Literal["scan_start", "first_point"] = Field(
        "scan_start", description="t_r of eq. 3: lidar_frames.t_start_ns, or the earliest point")
    uncovered: UncoveredPolicy = Field(default_factory=UncoveredPolicy)
    pose_gaps: PoseGaps = Field(default_factory=PoseGaps)
    frames_per_file: int = Field(
        100, ge=1, description="frames per output file and per chunk of work (bounds memory; "
                               "chunks are what a distributed run spreads over workers)")
