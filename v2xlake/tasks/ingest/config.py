"""Ingest's parameters (pydantic only: ``v2xlake params show`` imports this module without
the stage's decoding code). Few and unprefixed, so they stay one flat section."""

from __future__ import annotations

from typing import ClassVar

from pydantic import Field

from v2xlake.schemas.config import StageConfig


class IngestConfig(StageConfig):
    """Ingest parameters (hashed into the manifest)."""

    png_compression: int = Field(default=1, ge=0, le=9,
                                 description="zlib level for images re-encoded to PNG "
                                 "(tasks.pngcodec: with its RLE strategy the level "
                                 "hardly changes size or time)")
    recover_empty_storage_id: bool = Field(
        default=True, description="read a ROS 2 bag whose metadata.yaml has an empty "
        "storage_identifier as the storage its files are (sqlite3/MCAP by magic bytes)")
    copy_to_landing: bool = Field(
        default=True, description="copy (hard-link where it can) the clip as delivered into "
        "landing/<clip_id>/, where qa and re-runs read clip.yaml")
    allowed_bag_roots: tuple[str, ...] = Field(
        default=(), description="folders outside the clip folder that clip.yaml may name bags, "
        ".msg or annotation files in (after symlinks); by default a clip reads only its own "
        "folder. An operator setting: a clip's own params: block cannot set it")

    replace_existing: bool = Field(
        default=False, description="accept a delivery whose bags differ from those already "
        "ingested under the same clip id (it replaces that clip); otherwise it is refused")
    quat_tolerance: float = Field(
        default=1e-3, gt=0, description="largest |norm - 1| of a tf_static or pose "
        "quaternion; a larger one is an error (never silently normalised)")
    max_point_time_offset_s: float = Field(
        default=1.0, gt=0, description="per-point times declared absolute must lie within "
        "this of the header stamp, and header-relative ones be smaller than this: a time "
        "reference that contradicts the values is an error")
    min_range_m: float = Field(
        default=0.0, ge=0, description="points at or below this range are no-return points "
        "(drivers emit them at the origin): dropped and counted in lidar_frames.n_zero")
    min_agent_overlap_s: float = Field(
        default=0.0, ge=0, description="every agent's recording must overlap the reference "
        "agent's by more than this; agents that never recorded together are not a clip")

    # settings a clip.yaml's params: block may not change (the clip is untrusted input)
    OPERATOR_ONLY: ClassVar[frozenset[str]] = frozenset({"allowed_bag_roots",
                                                         "replace_existing"})
