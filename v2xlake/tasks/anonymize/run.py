"""The names this package's entry point had before ``stage.py`` became the only module that
touches the lake (issue #24), kept for importers outside the package (the privacy audit,
``flows/params_model.py``, other stages' tests) until they import ``config.py`` /
``stage.py`` / ``build.py`` directly: nothing is defined here but the configuration's old
methods, which forward to ``build.py``."""

from __future__ import annotations

from typing import Any

from v2xlake.tasks.anonymize import build
from v2xlake.tasks.anonymize import config as _config
from v2xlake.tasks.anonymize.detectors import ScanConfig
from v2xlake.tasks.anonymize.guide import GuideConfig
from v2xlake.tasks.anonymize.guided import GuidedDetector
from v2xlake.tasks.anonymize.stage import (
    CLEAN_TABLES,
    STAGE,
    ProgressLog,
    lidar_clusters,
    run_anonymize,
)

__all__ = ["CLEAN_TABLES", "STAGE", "AnonymizeConfig", "ProgressLog", "lidar_clusters",
           "run_anonymize"]


class AnonymizeConfig(_config.AnonymizeConfig):
    """``config.AnonymizeConfig`` with its former methods (``cfg.build_detector()``...), which
    now live in ``build.py`` as functions of the config (``blur()`` is gone: ``blur`` is
    now the section; ``build.blur_config(cfg)``)."""

    def __init__(self, **data: Any) -> None:
        """Also the flat keys of earlier versions (``face_threshold=``...), which ``RENAMED``
        moves into their sections with a warning naming the new key."""
        super().__init__(**data)

    def build_detector(self) -> GuidedDetector:
        return build.build_detector(self)

    def full_face_scan(self) -> ScanConfig:
        return build.full_face_scan(self)

    def guide(self) -> GuideConfig:
        return build.guide_config(self)
