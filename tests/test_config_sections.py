"""Nested config sections: flat keys of earlier versions move into their section, with a
warning naming the new key; a clip's partial section keeps the run's other keys."""

from __future__ import annotations

import subprocess
import sys
from typing import Any, ClassVar

import pytest
import yaml
from pydantic import BaseModel, Field, ValidationError

from v2xlake.flows.params import config_model, describe_params
from v2xlake.schemas.config import Section, StageConfig, merge_params

# the stages whose parameters are nested sections (tests/test_layers.py, SHAPED)
CONVERTED = ("ingest", "qa", "deskew", "annotate", "align")


class _Gicp(Section):
    voxel_m: float = Field(0.3, gt=0)
    max_iterations: int = 30


class _Toy(StageConfig):
    RENAMED: ClassVar[dict[str, str]] = {"voxel_m": "gicp.voxel_m",
                                         "max_iterations": "gicp.max_iterations"}
    gicp: _Gicp = Field(default_factory=_Gicp)
    enabled: bool = True


def test_a_flat_key_moves_into_its_section_and_names_the_new_key() -> None:
    with pytest.warns(DeprecationWarning, match="'voxel_m' is now 'gicp.voxel_m'"):
        cfg = _Toy.model_validate({"voxel_m": 0.5, "gicp": {"max_iterations": 5}})
    assert cfg.gicp.voxel_m == 0.5 and cfg.gicp.max_iterations == 5


def test_unknown_keys_are_refused_at_every_level() -> None:
    with pytest.raises(ValidationError):
        _Toy.model_validate({"gicp": {"voxel": 0.5}})
    with pytest.raises(ValidationError):
        _Toy.model_validate({"voxl_m": 0.5})


def test_a_partial_section_keeps_the_other_keys() -> None:
    run = _Toy.model_validate({"gicp": {"voxel_m": 0.6, "max_iterations": 7}}).model_dump()
    clip = {"gicp": {"max_iterations": 3}}
    cfg = _Toy.model_validate(merge_params(run, clip))
    assert cfg.gicp.voxel_m == 0.6 and cfg.gicp.max_iterations == 3
    assert run["gicp"]["max_iterations"] == 7  # the run's values are not modified


def _leaves(model: type[BaseModel], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for name, f in model.model_fields.items():
        t = f.annotation
        if isinstance(t, type) and issubclass(t, Section):
            out.update(_leaves(t, f"{prefix}{name}."))
        else:
            out[f"{prefix}{name}"] = f
    return out


@pytest.mark.parametrize("stage", CONVERTED)
def test_every_parameter_is_described_and_every_old_key_lands(stage: str) -> None:
    model = config_model(stage)
    assert issubclass(model, StageConfig)
    leaves = _leaves(model)
    assert [k for k, f in leaves.items() if not f.description] == []
    assert set(model.RENAMED.values()) <= set(leaves), "a RENAMED key points nowhere"
    assert not set(model.RENAMED) & set(model.model_fields), "an old key is still a field"
    default = model().model_dump()
    for old, new in model.RENAMED.items():
        with pytest.warns(DeprecationWarning, match=f"'{old}' is now '{new}'"):
            cfg = model.model_validate({old: _get(default, new)})
        assert cfg.model_dump() == default  # the same value, in its new place


def _get(tree: dict[str, Any], path: str) -> Any:
    for name in path.split("."):
        tree = tree[name]
    return tree


def test_params_show_text_is_the_tree_with_descriptions() -> None:
    """What ``v2xlake params show`` prints: YAML that loads back to the values, with each
    section's and parameter's description beside it."""
    data = {s: config_model(s)().model_dump(mode="json") for s in CONVERTED}
    data["deskew"]["pose_gaps"]["max_ns"] = 30_000_000
    text = describe_params(data)
    assert yaml.safe_load(text) == data
    assert "    max_ns: 30000000  # pose samples further apart than this are a gap" in text
    assert "  pose_gaps:  # Pose samples too far apart to interpolate across." in text


def test_a_user_sees_the_renamed_key_warning() -> None:
    """Python hides a DeprecationWarning outside ``__main__``: the renamed-key warning is
    shown by default, so the one who wrote the YAML learns the new key."""
    code = ("from v2xlake.tasks.qa.config import QaConfig\n"
            "QaConfig.model_validate({'lidar_tolerance_ms': 2.0})\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    assert "'lidar_tolerance_ms' is now 'tolerance_ms.lidar'" in out.stderr
