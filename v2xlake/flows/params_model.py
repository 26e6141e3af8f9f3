"""The parameter models (``PipelineParams``, ``ExportParams``): one section per registered
stage (``schemas.registry``), each the stage's own config model from its package's
``config.py``, and ``export``. ``flows.params`` imports this module only when a model is
needed (it imports every stage's config module and every exporter); see that module for the
rules.

WHY built from the registries: a new stage brings its section with its package, a new
export format with its ``EXPORTERS`` entry; nothing here names either.
"""

from __future__ import annotations

import warnings
from typing import TYPE_CHECKING, Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError, create_model

from v2xlake.flows.params import ParamsError, _short, config_model
from v2xlake.schemas.config import merge_params
from v2xlake.schemas.registry import stage_names
from v2xlake.schemas.stage import Stage
from v2xlake.tasks.export.exporters import EXPORTERS


def _section(model: type[BaseModel]) -> Any:
    """(model, default) of one section: its model's defaults."""
    return model, Field(default_factory=model)


class _ExportSections(BaseModel):
    """One section per export format (``scene-transfer`` is spelled ``scene_transfer``)."""

    model_config = ConfigDict(extra="forbid")

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


if TYPE_CHECKING:  # the static view of the models built below: a section is any attribute
    class ExportParams(_ExportSections):
        def __getattr__(self, name: str) -> Any: ...

    class PipelineParams(_Sections):
        export: ExportParams = Field(default_factory=ExportParams)

        def __getattr__(self, name: str) -> Any: ...
else:  # a section per exporter (tasks/export/exporters.py), then per stage, and ``export``
    ExportParams = create_model(
        "ExportParams", __base__=_ExportSections, __module__=__name__,
        __doc__=_ExportSections.__doc__,
        **{name.replace("-", "_"): _section(e.config_model) for name, e in EXPORTERS.items()})
    PipelineParams = create_model(
        "PipelineParams", __base__=_Sections, __module__=__name__, __doc__=_Sections.__doc__,
        **{name: _section(config_model(name)) for name in stage_names()},
        export=_section(ExportParams))
