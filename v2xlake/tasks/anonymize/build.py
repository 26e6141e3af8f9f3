"""The stage's parameters (``config.py``, pydantic only) turned into what the numeric modules
take: the detector of the scan plan, the guide's, the blur's and the LiDAR clusters' settings.
Here, not on the config class, so that ``config.py`` imports no numeric code."""

from __future__ import annotations

from v2xlake.tasks.anonymize.blur import BlurConfig
from v2xlake.tasks.anonymize.clusters import ClusterConfig
from v2xlake.tasks.anonymize.config import AnonymizeConfig
from v2xlake.tasks.anonymize.detectors import (
    CenterFaceDetector,
    ClassicPlateConfig,
    ClassicPlateDetector,
    Detector,
    FaceConfig,
    HaarPlateDetector,
    ScanConfig,
)
from v2xlake.tasks.anonymize.guide import GuideConfig
from v2xlake.tasks.anonymize.guided import GuidedConfig, GuidedDetector, face_scan
from v2xlake.tasks.anonymize.plateread import PlateReadConfig
from v2xlake.tasks.anonymize.textplate import TextPlateConfig, TextPlateDetector


def full_face_scan(cfg: AnonymizeConfig) -> ScanConfig:
    """The full-frame plan's face scan (coarse pass, fine pass in tiles)."""
    return face_scan(cfg.faces)


def build_detector(cfg: AnonymizeConfig) -> GuidedDetector:
    """Faces and plates, guided when given regions, the full-frame plan otherwise."""
    f, p = cfg.faces, cfg.plates
    face = CenterFaceDetector(FaceConfig(threshold=min(f.threshold, f.full_threshold),
                                         scan=full_face_scan(cfg), quantized=f.int8))
    face_first = region_first = None
    if ((cfg.full_proposals and f.first_int8) or f.regions_first_int8) and not f.int8:
        int8 = CenterFaceDetector(FaceConfig(threshold=f.proposal_threshold, quantized=True))
        face_first = int8 if cfg.full_proposals and f.first_int8 else None
        region_first = int8 if f.regions_first_int8 else None
    plate = None
    if "text" in p.detector:
        plate = TextPlateDetector(TextPlateConfig(
            box_threshold=p.box_threshold, min_aspect=p.min_aspect, max_aspect=p.max_aspect,
            max_tilt_deg=p.max_tilt_deg,
            read=PlateReadConfig(min_conf=p.read_min_conf, min_digits=p.read_min_digits)
            if p.read else None))
    extra: list[Detector] = []
    if "classic" in p.detector:
        extra.append(ClassicPlateDetector(ClassicPlateConfig(upscale=p.upscale)))
    if "haar" in p.detector:
        extra.append(HaarPlateDetector())
    return GuidedDetector(face, plate, GuidedConfig.of(cfg), extra, face_first, region_first)


def guide_config(cfg: AnonymizeConfig) -> GuideConfig:
    r = cfg.regions
    return GuideConfig(margin_px=r.margin_px, margin_frac=r.margin_frac,
                       max_age_ns=int(r.box_max_age_ms * 1e6), windows=r.windows)


def blur_config(cfg: AnonymizeConfig) -> BlurConfig:
    b = cfg.blur
    return BlurConfig(method=b.method, margin=b.plate_margin, face_margin_x=b.face_margin_x,
                      face_margin_top=b.face_margin_top,
                      face_margin_bottom=b.face_margin_bottom)


def cluster_config(cfg: AnonymizeConfig) -> ClusterConfig:
    c = cfg.clusters
    return ClusterConfig(gap_deg=c.gap_deg, bridge_new_share=c.bridge_new_share,
                         bridge_max_m=c.bridge_max_m)
