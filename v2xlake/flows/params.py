"""Parameters as data: one ``PipelineParams`` with a section per stage and export format.

Each section is that stage's own config model (``DeskewConfig``...), so there is one
definition of every parameter, with its default and description. The same model is:

- the ``params`` parameter of the ``process-clip`` / ``process-clips`` Prefect flows (and so
  of the deployments in ``deploy/prefect.yaml``, whose ``parameters:`` block fills it);
- ``--params FILE.yaml`` on the command line (``v2xlake params show`` prints the result);
- a ``params:`` block in a clip's ``clip.yaml`` for what belongs to one recording (a rig's
  QA tolerances, its camera scan plan).

Precedence, most specific last: the class defaults, then the run's parameters, then the
clip's own block. The effective section of each stage is hashed into its manifest (a
changed parameter re-runs that stage and what reads its tables) and recorded in full.
"""

from __future__ import annotations

import copy
import functools
import warnings
from pathlib import Path
from typing import Any

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from v2xlake.schemas.clip import load_yaml
from v2xlake.schemas.stage import Stage
from v2xlake.tasks.align.stage import AlignConfig
from v2xlake.tasks.annotate.core import AnnotateConfig
from v2xlake.tasks.anonymize.run import AnonymizeConfig
from v2xlake.tasks.deskew.stage import DeskewConfig
from v2xlake.tasks.export.bev import BevConfig
from v2xlake.tasks.export.eth3d import Eth3dConfig
from v2xlake.tasks.export.nuscenes import NuScenesExportConfig
from v2xlake.tasks.export.opencood import OpenCoodConfig
from v2xlake.tasks.export.rosbag import RosbagExportConfig
from v2xlake.tasks.export.scene_transfer import SceneTransferConfig
from v2xlake.tasks.ingest.run import IngestConfig
from v2xlake.tasks.qa.core import QaConfig
from v2xlake.tasks.register.stage import RegisterConfig


class ParamsError(ValueError):
    """Parameters that do not validate (unknown key, wrong type, out of range)."""


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
            return stage.config({**values, **own})
        except ValidationError as e:
            raise ParamsError(f"params.{stage.name}: {_short(e)}") from e


def _short(e: ValidationError) -> str:
    return "; ".join(f"{'.'.join(str(x) for x in err['loc'])}: {err['msg']}"
                     for err in e.errors()[:5])


def parse_params(data: dict[str, Any] | PipelineParams | None) -> PipelineParams:
    """Validate user parameters (a mapping from YAML, a flow parameter, or a model)."""
    if isinstance(data, PipelineParams):
        return data
    try:
        return PipelineParams.model_validate(data or {})
    except ValidationError as e:
        raise ParamsError(f"invalid parameters: {_short(e)}") from e


def load_params(path: str | Path | None) -> PipelineParams:
    """``--params FILE.yaml``: a mapping with one optional section per stage / ``export``."""
    if path is None:
        return PipelineParams()
    try:
        data = load_yaml(Path(path).read_text())
    except OSError as e:
        raise ParamsError(f"cannot read parameters file {path}: {e.strerror}") from e
    except yaml.YAMLError as e:
        raise ParamsError(f"parameters file {path} is not valid YAML: {e}") from e
    if data is not None and not isinstance(data, dict):
        raise ParamsError(f"parameters file {path} must hold a mapping of sections")
    return parse_params(data)


def clip_params(clip_dir: str | Path) -> dict[str, Any]:
    """The ``params:`` block of a clip folder's clip.yaml ({} when absent or unreadable:
    reading the contract properly, with a clear error, is ingest's job)."""
    try:
        return copy.deepcopy(_params_block((Path(clip_dir) / "clip.yaml").read_text()))
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return {}


@functools.lru_cache(maxsize=64)
def _params_block(text: str) -> dict[str, Any]:
    """Once per distinct clip.yaml text: the flow asks before every stage of every clip."""
    data = load_yaml(text)
    block = data.get("params") if isinstance(data, dict) else None
    return dict(block) if isinstance(block, dict) else {}
