"""The parameter models (``PipelineParams``, ``ExportParams``): each section is its stage's
own config model, so importing this module imports every stage's config module (and what
they import: NumPy, SciPy, Open3D, numba). ``flows.params`` imports it only when a model is
needed; see that module for the rules.
"""

from __future__ import annotations

import warnings
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from v2xlake.flows.params import ParamsError, _short
from v2xlake.schemas.config import merge_params
from v2xlake.schemas.stage import Stage
from v2xlake.tasks.align.config import AlignConfig
from v2xlake.tasks.annotate.config import AnnotateConfig
from v2xlake.tasks.anonymize.config import AnonymizeConfig
from v2xlake.tasks.deskew.stage import DeskewConfig
from v2xlake.tasks.export.bev import BevConfig
from v2xlake.tasks.export.eth3d import Eth3dConfig
from v2xlake.tasks.export.nuscenes import NuScenesExportConfig
from v2xlake.tasks.export.opencood import OpenCoodConfig
from v2xlake.tasks.export.rosbag import RosbagExportConfig
from v2xlake.tasks.export.scene_transfer import SceneTransferConfig
from v2xlake.tasks.ingest.config import IngestConfig
from v2xlake.tasks.qa.config import QaConfig
from v2xlake.tasks.register.stage import RegisterConfig


class ExportParams(BaseModel):
    """One section per export format (``scene-transfer`` is spelled ``scene_transfer``)."""

    model_config = ConfigDict(extra="forbid")

    nuscenes: NuScenesExportConfig = Field(default_factory=NuScenesExportConfig)
    eth3d: Eth3dConfig = Field(default_factory=Eth3dConfig)
    rosbag: RosbagExportConfig = Field(default_factory=RosbagExportConfig)
    opencood: OpenCoodConfig = Field(default_factory=OpenCoodConfig)
    bev: BevConfig = Field(default_factory=BevConfig)
    scene_transfer: SceneTransferConfig = Field(default_factory=SceneTransferConfig)

    def section(self, fmt: str) -> BaseModel:
        section: BaseModel = getattr(self, fmt.replace("-", "_"))
        return section


# The section is named after its stage; ``register`` is also the name of ABCMeta's class
# method, which pydantic warns a field shadows. Instances read the field as they should.
warnings.filterwarnings("ignore", message='Field name "register" in "PipelineParams"')


class PipelineParams(BaseModel):
    """Every user-settable parameter of a pipeline run."""

    model_config = ConfigDict(extra="forbid")

    ingest: IngestConfig = Field(default_factory=IngestConfig)
    qa: QaConfig = Field(default_factory=QaConfig)
    anonymize: AnonymizeConfig = Field(default_factory=AnonymizeConfig)
    deskew: DeskewConfig = Field(default_factory=DeskewConfig)
    register: RegisterConfig = Field(default_factory=RegisterConfig)
    annotate: AnnotateConfig = Field(default_factory=AnnotateConfig)
    align: AlignConfig = Field(default_factory=AlignConfig)
    export: ExportParams = Field(default_factory=ExportParams)

    def for_stage(self, stage: Stage[Any], clip_params: dict[str, Any] | None = None
                  ) -> BaseModel:
        """The effective config of one stage: this run's section, then the clip's block."""
        base: BaseModel | None = getattr(self, stage.name, None)
        # a stage outside the standard pipeline (a plugin, a test double) has its own model
        values = base.model_dump() if isinstance(base, stage.config_model) else {}
        own = (clip_params or {}).get(stage.name) or {}
        if not isinstance(own, dict):
            raise ParamsError(f"params.{stage.name} must be a mapping, got {type(own).__name__}")
        forbidden = sorted(set(own) & getattr(stage.config_model, "OPERATOR_ONLY", frozenset()))
        if forbidden:  # a clip is untrusted input: it may not widen what it may read
            raise ParamsError(f"params.{stage.name}: {forbidden} can only be set by the "
                              "operator (--params, a deployment), not by a clip's clip.yaml")
        try:
            return stage.config(merge_params(values, own))
        except ValidationError as e:
            raise ParamsError(f"params.{stage.name}: {_short(e)}") from e
