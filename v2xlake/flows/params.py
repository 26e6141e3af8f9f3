"""Parameters as data: one ``PipelineParams`` with a section per registered stage
(``schemas.registry``) and one per export format.

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
import importlib
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml
from pydantic import BaseModel, ValidationError

from v2xlake.schemas.clip import load_yaml

if TYPE_CHECKING:
    from v2xlake.flows.params_model import ExportParams, PipelineParams

__all__ = ["ExportParams", "ParamsError", "PipelineParams", "clip_params", "config_model",
           "describe_params", "load_params", "load_params_data", "parse_params"]


def __getattr__(name: str) -> Any:
    """``PipelineParams`` / ``ExportParams`` on first use: their module imports every
    stage's config module (seconds), which ``params show --stage X``, the no-op check and
    ``--help`` must not pay."""
    if name in ("PipelineParams", "ExportParams"):
        from v2xlake.flows import params_model

        return getattr(params_model, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


class ParamsError(ValueError):
    """Parameters that do not validate (unknown key, wrong type, out of range)."""


def _short(e: ValidationError) -> str:
    return "; ".join(f"{'.'.join(str(x) for x in err['loc'])}: {err['msg']}"
                     for err in e.errors()[:5])


def parse_params(data: dict[str, Any] | PipelineParams | None) -> PipelineParams:
    """Validate user parameters (a mapping from YAML, a flow parameter, or a model)."""
    from v2xlake.flows.params_model import PipelineParams

    if isinstance(data, PipelineParams):
        return data
    try:
        return PipelineParams.model_validate(data or {})
    except ValidationError as e:
        raise ParamsError(f"invalid parameters: {_short(e)}") from e


def load_params(path: str | Path | None) -> PipelineParams:
    """``--params FILE.yaml``: a mapping with one optional section per stage / ``export``."""
    return parse_params(load_params_data(path))


def load_params_data(path: str | Path | None) -> dict[str, Any] | None:
    """``--params FILE.yaml`` read but not validated (the mapping ``parse_params`` takes)."""
    if path is None:
        return None
    try:
        data = load_yaml(Path(path).read_text())
    except OSError as e:
        raise ParamsError(f"cannot read parameters file {path}: {e.strerror}") from e
    except yaml.YAMLError as e:
        raise ParamsError(f"parameters file {path} is not valid YAML: {e}") from e
    if data is not None and not isinstance(data, dict):
        raise ParamsError(f"parameters file {path} must hold a mapping of sections")
    return data


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
    from v2xlake.flows.stage_names import parse_clip_yaml

    data = parse_clip_yaml(text)
    block = data.get("params") if isinstance(data, dict) else None
    return dict(block) if isinstance(block, dict) else {}


def config_model(section: str) -> type[BaseModel]:
    """The model of one section of ``PipelineParams``: a stage's ``StageConfig`` from its
    package's ``config.py`` (pydantic only: milliseconds; the package from
    ``schemas.registry``); ``export``: ``ExportParams``."""
    from v2xlake.schemas.config import StageConfig
    from v2xlake.schemas.registry import package

    if section == "export":
        from v2xlake.flows.params_model import ExportParams

        return ExportParams
    name = f"{package(section)}.config"
    module = importlib.import_module(name)
    found = [v for v in vars(module).values() if isinstance(v, type)
             and issubclass(v, StageConfig) and v.__module__ == name]
    if len(found) != 1:
        raise TypeError(f"{name} must define one StageConfig, found {found}")
    return found[0]


def describe_params(data: Mapping[str, Any]) -> str:
    """``v2xlake params show``: the effective parameters as YAML, nested sections as they
    are, each parameter and section followed by its description as a comment (the text a
    user otherwise finds only in the source). ``data`` maps section names (``qa``,
    ``export``...) to their values; the result loads back to ``data``."""
    lines: list[str] = []
    for name, values in data.items():
        _describe(config_model(name), name, values, 0, lines)
    return "\n".join(lines) + "\n"


def _scalar(value: Any) -> str:
    text: str = yaml.safe_dump(value, default_flow_style=True, width=10_000)
    return text.removesuffix("\n").removesuffix("\n...")


def _describe(model: type[BaseModel], key: str, values: Any, depth: int,
              lines: list[str]) -> None:
    pad = "  " * depth
    doc = " ".join((model.__doc__ or "").strip().split("\n\n")[0].split())
    if not isinstance(values, dict) or not values:
        lines.append(f"{pad}{key}: {_scalar(values)}" + (f"  # {doc}" if doc else ""))
        return
    lines.append(f"{pad}{key}:" + (f"  # {doc}" if doc else ""))
    for name, value in values.items():
        field = model.model_fields.get(name)
        sub = field.annotation if field is not None else None
        if isinstance(sub, type) and issubclass(sub, BaseModel) and isinstance(value, dict):
            _describe(sub, name, value, depth + 1, lines)
            continue
        text = field.description if field is not None and field.description else ""
        lines.append(f"{pad}  {name}: {_scalar(value)}"
                     + (f"  # {' '.join(text.split())}" if text else ""))
