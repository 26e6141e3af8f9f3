"""The parameter models (``PipelineParams``, ``ExportParams``): one section per registered
stage (``schemas.registry``), each the stage's own config model from its package's
``config.py``, and ``export``. ``flows.params`` imports this module only when a model is
needed (it imports every stage's config module and every exporter); see that module for the
rules.

WHY built from the registry: a new stage brings its section with its package; nothing here
names a stage.
"""

from __future__ import annotations

import warnings
from typing import TYPE_CHECKING, Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError, create_model

from v2xlake.flows.params import ParamsError, _short, config_model
from v2xlake.schemas.config import merge_params
from v2xlake.schemas.registry import stage_names
from v2xlake.schemas.stage import Stage
from v2xlake.tasks.export.bev import BevConfig
from v2xlake.tasks.export.eth3d import Eth3dConfig
from v2xlake.tasks.export.nuscenes import NuScenesExportConfig
from v2xlake.tasks.export.opencood import OpenCoodConfig
from v2xlake.tasks.export.rosbag import RosbagExportConfig
from v2xlake.tasks.export.scene_transfer import SceneTransferConfig


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


class _Sections(BaseModel):
    """Every user-settable parameter of a pipeline run: one section per stage, then
    ``export``."""

    model_config = ConfigDict(extra="forbid")

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


def _sections() -> dict[str, Any]:
    """(model, default) of every section, in pipeline order, ``export`` last."""
    out: dict[str, Any] = {}
    for name in stage_names():
        model = config_model(name)
        out[name] = (model, Field(default_factory=model))
    out["export"] = (ExportParams, Field(default_factory=ExportParams))
    return out


if TYPE_CHECKING:
    class PipelineParams(_Sections):
        """The static view of the model built below: a section is any attribute."""

        export: ExportParams = Field(default_factory=ExportParams)

        def __getattr__(self, name: str) -> Any: ...
else:
    PipelineParams = create_model("PipelineParams", __base__=_Sections, __module__=__name__,
                                  __doc__=_Sections.__doc__, **_sections())
