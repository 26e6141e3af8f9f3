"""Nested config sections: flat keys of earlier versions move into their section, with a
warning naming the new key; a clip's partial section keeps the run's other keys."""

from __future__ import annotations

from typing import ClassVar

import pytest
from pydantic import Field, ValidationError

from v2xlake.schemas.config import Section, StageConfig, merge_params


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
