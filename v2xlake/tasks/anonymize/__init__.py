"""Anonymization stage: faces and plates blurred, time made relative, positions made local."""

from v2xlake.tasks.anonymize.blur import BlurConfig, blur_boxes
from v2xlake.tasks.anonymize.detectors import (
    CenterFaceDetector,
    ClassicPlateConfig,
    ClassicPlateDetector,
    Detection,
    Detector,
    FaceConfig,
    HaarPlateConfig,
    HaarPlateDetector,
    ScanConfig,
    UnionDetector,
)
from v2xlake.tasks.anonymize.images import anonymize_png, encode_png, png_chunks, strip_png_metadata
from v2xlake.tasks.anonymize.run import AnonymizeConfig, run_anonymize
from v2xlake.tasks.anonymize.textplate import TextPlateConfig, TextPlateDetector

__all__ = [
    "AnonymizeConfig",
    "BlurConfig",
    "CenterFaceDetector",
    "ClassicPlateConfig",
    "ClassicPlateDetector",
    "Detection",
    "Detector",
    "FaceConfig",
    "HaarPlateConfig",
    "HaarPlateDetector",
    "ScanConfig",
    "TextPlateConfig",
    "TextPlateDetector",
    "UnionDetector",
    "anonymize_png",
    "blur_boxes",
    "encode_png",
    "png_chunks",
    "run_anonymize",
    "strip_png_metadata",
]
