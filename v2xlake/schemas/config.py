"""The shape of every stage's parameters: nested sections, one definition per parameter.

A stage's config is a tree (kiss-icp's style): ``register.gicp.voxel_m``, not a flat bag of
prefixed names (``gicp_voxel_m``). Each section is a frozen pydantic model that the stage's
numeric core takes directly, so a parameter is written once, with its default and its
description, and no hand-copied dataclass can drift from it.

Earlier versions of the YAML used flat keys. A stage lists them in ``RENAMED`` (old flat key
-> dotted new path); they are moved into their section with a ``RenamedParameterWarning`` (a
``DeprecationWarning`` shown by default) that names the new key, so existing parameter files
keep working. Unknown keys are refused.

This module imports pydantic only: ``v2xlake params show`` builds the tree from the stages'
``config.py`` modules without importing their numeric code.
"""

from __future__ import annotations

import warnings
from typing import Any, ClassVar

from pydantic import BaseModel, ConfigDict, model_validator


class RenamedParameterWarning(DeprecationWarning):
    """A flat key of an earlier version was moved into its section. Shown by default, unlike
    a plain ``DeprecationWarning`` (hidden outside ``__main__``): the one who must act on it
    is the person who wrote the YAML, not a developer running tests."""


warnings.filterwarnings("default", category=RenamedParameterWarning)

#: A pose gap is longer than this many periods of its pose track: QA flags a LiDAR scan it
#: leaves uncovered, deskew does not interpolate across it (one default for both stages).
POSE_GAP_PERIODS = 2.5

#: The LiDAR boxes are annotated in unless an annotation names another (``BoxAnnotation``),
#: and so the one the stages and exports that work on boxes use by default.
ANNOTATED_LIDAR = "LIDAR_TOP"


class Section(BaseModel):
    """A group of parameters: frozen (a core may keep it), unknown keys refused."""

    model_config = ConfigDict(frozen=True, extra="forbid")


def _set_path(tree: dict[str, Any], path: str, value: Any) -> None:
    *parents, leaf = path.split(".")
    node = tree
    for name in parents:
        child = node.get(name)
        if isinstance(child, BaseModel):
            child = child.model_dump()
        elif not isinstance(child, dict):
            child = {}
        child = dict(child)
        node[name] = child
        node = child
    node[leaf] = value


class StageConfig(Section):
    """A stage's parameters: nested ``Section`` fields, plus ``RENAMED`` for flat old keys."""

    RENAMED: ClassVar[dict[str, str]] = {}

    @model_validator(mode="before")
    @classmethod
    def _move_renamed_keys(cls, data: Any) -> Any:
        if not isinstance(data, dict) or not cls.RENAMED:
            return data
        # an old flat key may share its name with the new section ("redeskew": true ->
        # "redeskew": {"enabled": true}); a mapping there is already the new form
        moved = {k: data[k] for k in data if k in cls.RENAMED
                 and not (k in cls.model_fields and isinstance(data[k], dict | BaseModel))}
        if not moved:
            return data
        out = {k: v for k, v in data.items() if k not in moved}
        for old, value in moved.items():
            new = cls.RENAMED[old]
            warnings.warn(f"{cls.__name__}: the parameter '{old}' is now '{new}' "
                          "(nested section); the flat key will be removed",
                          RenamedParameterWarning, stacklevel=2)
            _set_path(out, new, value)
        return out


def merge_params(base: dict[str, Any], override: dict[str, Any]) -> dict[str, Any]:
    """``override`` on top of ``base``, section by section (a clip that sets one key of a
    section keeps the run's other keys of that section)."""
    out = dict(base)
    for key, value in override.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = merge_params(out[key], value)
        else:
            out[key] = value
    return out
