"""What an audit returns (findings, counts), its error, and its thresholds."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class Finding:
    # absolute_time | latlon | image_metadata | unblurred_face | unblurred_plate | unreadable
    # (could not be read or parsed) | unscannable (no scanner for this kind of file)
    kind: str
    location: str
    detail: str


class AuditError(ValueError):
    """The audit could not look at anything (a missing or empty lake, release or folder):
    an error, never "0 findings"."""


@dataclass
class AuditReport:
    findings: list[Finding] = field(default_factory=list)
    n_files: int = 0
    n_tables: int = 0
    n_images_checked: int = 0
    # projected head / plate locations (from the clip's boxes) in the checked images: blurred,
    # or searched by the audit's own detector and found empty (back of a head, occluded)
    n_regions: int = 0
    n_regions_blurred: int = 0
    n_regions_not_visible: int = 0

    @property
    def ok(self) -> bool:
        return not self.findings

    def summary(self) -> str:
        head = (
            f"audit: {self.n_files} files, {self.n_tables} tables, "
            f"{self.n_images_checked} images re-checked ({self.n_regions} projected head/plate "
            f"locations: {self.n_regions_blurred} blurred, {self.n_regions_not_visible} with "
            f"nothing visible): {len(self.findings)} findings"
        )
        return "\n".join([head, *(f"  [{f.kind}] {f.location}: {f.detail}" for f in self.findings)])


@dataclass(frozen=True)
class AuditConfig:
    latlon_max_spread_deg: float = 0.05
    latlon_min_rows: int = 10
    stationary_span_m: float = 5.0
    span_factor_lo: float = 0.2
    span_factor_hi: float = 5.0
    face_min_score: float = 0.6
    plate_min_score: float = 0.5
    text_max_bytes: int = 4 << 20
    # which files of a release folder are camera images to re-check with the detector (in a
    # lake zone they are exactly the blobs its camera_frames name); plots, BEV rasters, maps,
    # depth previews and release-note figures are not dataset images
    camera_image_pattern: str = r"(^|/)(blobs|samples|sweeps|images|image_\d+)/|(^|/)CAM_[A-Z_]+/"
    not_camera_pattern: str = r"(^|/)(maps?|plots?|figures?|depth_preview|bev|preview)(/|_)"
    # the audit's own scan plan (a different one from the blur's): faces at 1.5x in tiles and
    # at native size, plates natively and at 2x; projected regions at larger targets
    audit_face_fine_scale: float = 1.5
    # plates: natively over the frame (an upscaled text detector reads foliage and facades
    # as text), and in the projected vehicle faces at their own scale
    audit_plate_fine_scale: float | None = None
    region_face_target_px: float = 56.0
    region_plate_target_px: float = 128.0
    region_min_face_px: float = 10.0  # projected locations checked from these sizes
    region_min_plate_px: float = 16.0
