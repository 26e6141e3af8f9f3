"""The register stage's parameters: nested sections that the numeric cores take as they are,
and parameter files of earlier versions (flat keys) still read, with the new key named."""

from __future__ import annotations

import warnings

import pytest

from v2xlake.tasks.register.config import RegisterConfig


def test_flat_keys_of_earlier_parameter_files_move_into_their_sections() -> None:
    old = {"voxel_m": 0.6, "clip_solve": False, "redeskew": False, "refined_require_all": True,
           "odometry_turn_deg": 2.0, "gicp_floor_m": 0.02, "static_only": False}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        cfg = RegisterConfig.model_validate(old)
    assert cfg.gicp.voxel_m == 0.6 and not cfg.solve.enabled and not cfg.redeskew.enabled
    assert cfg.calibration.require_all and cfg.solve.straight_deg == 2.0
    assert cfg.solve.floor_m == 0.02 and not cfg.static.enabled
    said = " ".join(str(w.message) for w in caught)
    assert "'voxel_m' is now 'gicp.voxel_m'" in said and "'redeskew' is now" in said


def test_a_section_named_like_an_old_flag_takes_the_new_form() -> None:
    cfg = RegisterConfig.model_validate({"redeskew": {"enabled": False, "min_shift_m": 0.05}})
    assert not cfg.redeskew.enabled and cfg.redeskew.min_shift_m == 0.05


def test_every_parameter_has_one_default() -> None:
    """The cores read the sections themselves: no second default to drift from these."""
    from v2xlake.tasks.register.backends import DEFAULT_GICP
    from v2xlake.tasks.register.solve import DEFAULT_SOLVE

    cfg = RegisterConfig()
    assert DEFAULT_GICP == cfg.gicp and DEFAULT_SOLVE == cfg.solve
    assert cfg.quality.gated(False).min_observability == 0.0
    assert cfg.quality.gated(True) == cfg.quality


def test_only_the_reference_scans_reach_farther() -> None:
    """gicp.reference_max_range_m (120 m by default) widens the reference agent's scans only
    (the target of the cross pairs); None, every agent keeps max_range_m."""
    cfg = RegisterConfig()
    assert cfg.gicp.range_m(True) == 120.0 and cfg.gicp.range_m(False) == 80.0
    cfg = RegisterConfig.model_validate({"gicp": {"reference_max_range_m": None}})
    assert cfg.gicp.range_m(True) == cfg.gicp.range_m(False) == cfg.gicp.max_range_m == 80.0


def test_unknown_keys_are_refused_inside_sections() -> None:
    with pytest.raises(ValueError, match="voxel"):
        RegisterConfig.model_validate({"gicp": {"voxel": 0.6}})
