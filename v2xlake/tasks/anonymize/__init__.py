"""The anonymize stage: faces and plates blurred, time made relative, positions made local.

``config.py`` its parameters (pydantic only), ``stage.py`` the lake I/O (the raw tables in,
the clean zone out, the guide built from the clip's tables) and the ``ANONYMIZE`` Stage
object; everything else is pure (arrays and images in, arrays out):

- ``build.py``: the parameters turned into the detector and the pure modules' settings,
  whose fields name the parameter each is (``params.py``: one definition, one default);
- ``guide.py`` (3D boxes -> image regions), ``context.py`` (one clip's poses, cameras and
  boxes -> regions per image), ``clusters.py`` (object boxes from a LiDAR scan);
- ``guided.py`` (the guided scan plan, its safety pass and the full-frame plan),
  ``detectors.py`` (CenterFace, the classic and Haar plate detectors, scans in tiles),
  ``textplate.py`` (PP-OCR text lines as plates), ``plateread.py`` (reading a candidate),
  ``plateprop.py`` (the scale to search a small plate's edge band at, dark frames lifted),
  ``bandplate.py`` (the far band's optional learned small-plate scorer, its weights in
  ``bandplate.npz``);
- ``carry.py`` (key frames, detections carried between them), ``temporal.py`` (gaps filled);
- ``blur.py`` (irreversible blur), ``images.py`` (decode, encode, metadata stripped),
  ``timespace.py`` (relative time, local ENU);
- ``evaluate.py`` (recall on simulated and real labelled images: tests and benchmarks),
  ``quantize.py`` (CenterFace's int8 copy, rebuilt deterministically).

Names are imported lazily (``v2xlake params show`` imports ``config.py`` without the
numeric code)."""

from __future__ import annotations

from importlib import import_module
from typing import Any

from v2xlake.schemas.stage import INGEST_TABLES, RAW_ONLY_TABLES, StageDeclaration, tables

# what the registry reads without importing the stage (schemas/registry.py)
DECLARATION = StageDeclaration(
    name="anonymize",
    owns=(*tables("clean", *(t for t in INGEST_TABLES if t not in RAW_ONLY_TABLES)),
          *tables("clean", "qa_checks", "anonymization_audit")))


_WHERE = {
    "AnonymizeConfig": "config",
    "run_anonymize": "stage",
    "BlurConfig": "blur",
    "blur_boxes": "blur",
    "CenterFaceDetector": "detectors",
    "ClassicPlateConfig": "detectors",
    "ClassicPlateDetector": "detectors",
    "Detection": "detectors",
    "Detector": "detectors",
    "FaceConfig": "detectors",
    "HaarPlateConfig": "detectors",
    "HaarPlateDetector": "detectors",
    "ScanConfig": "detectors",
    "UnionDetector": "detectors",
    "anonymize_png": "images",
    "encode_png": "images",
    "png_chunks": "images",
    "strip_png_metadata": "images",
    "TextPlateConfig": "textplate",
    "TextPlateDetector": "textplate",
}

__all__ = sorted(_WHERE)


def __getattr__(name: str) -> Any:
    """``from v2xlake.tasks.anonymize import run_anonymize`` imports its module on first use."""
    if name not in _WHERE:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(import_module(f"{__name__}.{_WHERE[name]}"), name)
