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
    face_scan,
)
from v2xlake.tasks.anonymize.guide import GuideConfig
from v2xlake.tasks.anonymize.guided import GuidedConfig, GuidedDetector
from v2xlake.tasks.anonymize.textplate import TextPlateConfig, TextPlateDetector


def full_face_scan(cfg: AnonymizeConfig) -> ScanConfig:
    """The full-frame plan's face scan (coarse pass, fine pass in tiles)."""
    return face_scan(cfg.faces)


def build_detector(cfg: AnonymizeConfig) -> GuidedDetector:
    """Faces and plates, guided when given regions, the full-frame plan otherwise."""
    f, p = cfg.faces, cfg.plates
    face = CenterFaceDetector(FaceConfig.of(cfg))
    face_first = region_first = None
    if ((cfg.full_proposals and f.first_int8) or f.regions_first_int8) and not f.int8:
        # the proposing pass: only its heat maps are read (``maps`` / ``decode`` with the
        # plan's own thresholds), never its scan
        int8 = CenterFaceDetector(FaceConfig(threshold=f.proposal_threshold, quantized=True))
        face_first = int8 if cfg.full_proposals and f.first_int8 else None
        region_first = int8 if f.regions_first_int8 else None
    plate = None
    if "text" in p.detector:
        plate = TextPlateDetector(TextPlateConfig.of(cfg))
    extra: list[Detector] = []
    if "classic" in p.detector:
        extra.append(ClassicPlateDetector(ClassicPlateConfig.of(cfg)))
    if "haar" in p.detector:
        extra.append(HaarPlateDetector())
    return GuidedDetector(face, plate, GuidedConfig.of(cfg), extra, face_first, region_first)


def guide_config(cfg: AnonymizeConfig) -> GuideConfig:
    """The guide's settings (params.py: each field names its parameter)."""
    return GuideConfig.of(cfg)


def blur_config(cfg: AnonymizeConfig) -> BlurConfig:
    """The blur's settings (params.py: each field names its parameter)."""
    return BlurConfig.of(cfg)


def cluster_config(cfg: AnonymizeConfig) -> ClusterConfig:
    """The LiDAR clusters' settings (params.py: each field names its parameter)."""
    return ClusterConfig.of(cfg)
