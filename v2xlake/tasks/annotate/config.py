"""The annotate stage's parameters (pydantic only: ``v2xlake params show`` imports this
module without the stage's numeric code)."""

from __future__ import annotations

from typing import ClassVar, Literal

from pydantic import Field

from v2xlake.schemas.config import ANNOTATED_LIDAR, Section, StageConfig


class LinkConfig(Section):
    """Linked boxes (a trailer and the car towing it) annotated in the same scan."""

    # A far link is a plausibility finding on an annotation (a trailer a few decimetres
    # further than the limit), not bad input: by default it is reported, never quarantined.
    max_gap_m: float = Field(
        default=3.0, ge=0,
        description="linked boxes: centre distance <= (l_a + l_b) / 2 + this gap")
    policy: Literal["error", "warn"] = Field(
        default="warn", description="linked objects too far apart: report (warn) or error")


class CrossAgentConfig(Section):
    """Two agents' boxes of one global id, compared in the world frame."""

    max_dt_ms: float = Field(
        default=60.0, gt=0, description="pair two agents' boxes of one id at most this apart")
    registration_min_fitness: float = Field(
        default=0.0, ge=0, description="use only refined registrations at least this fit "
        "for the after-registration distances")


class AnnotateConfig(StageConfig):
    """Parameters of the annotate stage (hashed into the manifest)."""

    RENAMED: ClassVar[dict[str, str]] = {
        "max_link_gap_m": "links.max_gap_m", "link_policy": "links.policy",
        "cross_agent_max_dt_ms": "cross_agent.max_dt_ms",
        "registration_min_fitness": "cross_agent.registration_min_fitness"}

    lidar_sensor: str = Field(ANNOTATED_LIDAR, description="the LiDAR whose scans the boxes are "
                              "annotated in")
    # nuScenes' num_lidar_pts is what the devkit's points_in_box counts on the exported scan
    # (faces inclusive, no slack): the default counts exactly that, so the catalog, every
    # export and the devkit agree. A margin (metres, every side) is there for users who
    # want to count returns that calibration or deskew error pushed just outside a box.
    count_margin_m: float = Field(default=0.0, ge=0, description="grow boxes when counting")
    links: LinkConfig = Field(default_factory=LinkConfig)
    cross_agent: CrossAgentConfig = Field(default_factory=CrossAgentConfig)
