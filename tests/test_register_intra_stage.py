"""Several LiDARs on one agent end to end (issue #27): the simulator's side-LiDAR option
(``SimConfig.side_lidar``: LIDAR_LEFT, rolled 40 deg down, published 30 deg / 9 cm off) ->
ingest -> anonymize -> deskew (each LiDAR with its own per-point time) -> the intra-agent
refinement on deskewed frames (re-deskewed with a first pass's rotation, several frames
pooled) -> ``calibration_refined`` -> what ``v2xlake calibration`` and every consumer read.
Checked against the simulator's true mounting (truth/, not an input)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tests.fixtures.rigs import deskewed_side_lidar_clip
from v2xlake.schemas.arrow import rows_to_table
from v2xlake.schemas.tables import CalibrationRefinedRow
from v2xlake.storage.lake import Lake
from v2xlake.storage.reader import read_clip, read_extrinsics
from v2xlake.tasks.reader import compare_calibration
from v2xlake.tasks.register.calibration import format_calibration
from v2xlake.tasks.register.intra import pose_distance
from v2xlake.tasks.register.intra_stage import IntraStageSettings, frame_pairs, split_lidars
from v2xlake.tasks.register.stage import refine_agent_lidars

sim = pytest.importorskip("v2xlake.tasks.simulate")
CID = "sim_intra"


@pytest.fixture(scope="module")
def side_clip(tmp_path_factory: pytest.TempPathFactory) -> tuple[Lake, Path]:
    return deskewed_side_lidar_clip(tmp_path_factory.mktemp("intra"), CID, beams=64,
                                    columns=1024, max_range_m=120.0)


def test_side_lidar_option_is_off_by_default() -> None:
    from v2xlake.tasks.simulate.rig import build_rigs

    cfg = sim.SimConfig.preset("small", seconds=0.3, cameras=())
    assert not cfg.side_lidar
    assert all(r.T_ego_side_true is None for r in build_rigs(cfg).values())
    with_side = build_rigs(cfg.model_copy(update={"side_lidar": True}))
    without = build_rigs(cfg)
    for a, r in without.items():  # the option draws nothing: the rest of the rig is the same
        assert np.array_equal(r.T_ego_lidar_pub, with_side[a].T_ego_lidar_pub)


def test_split_and_pairs() -> None:
    assert split_lidars(["LIDAR_LEFT", "LIDAR_TOP", "LIDAR_RIGHT"]) == (
        "LIDAR_TOP", ["LIDAR_LEFT", "LIDAR_RIGHT"])
    assert split_lidars(["B", "A"]) == ("A", ["B"])
    p = {k: (k * 100, k * 100) for k in range(10)}
    s = {k: (k * 100 + 3, k * 100 + 3) for k in range(1, 10)}
    got = frame_pairs(p, s, 10, 3)
    assert got == [(1, 1), (5, 5), (9, 9)]
    assert frame_pairs(p, s, 1, 3) == []  # starts too far apart: no pair


def test_side_lidar_refined_end_to_end(side_clip: tuple[Lake, Path]) -> None:
    from v2xlake.tasks.simulate.truth import load_truth

    lake, clip = side_clip
    assert set(read_extrinsics(lake, CID, "red")) == {"LIDAR_TOP", "LIDAR_LEFT"}
    # the stage's own setting (intra.frames, 3 frame pairs pooled), not fewer: which single
    # frame finds a second minimum scoring within ambiguity_ratio of the best depends on the
    # CPU's floating point path (an AVX2-less AMD EPYC refused one of the first two frames
    # as ambiguous, where earlier machines accepted both); that frame is refused, the
    # other two agree and are pooled, as a user's run pools them
    rows, notes = refine_agent_lidars(lake, CID, "red", IntraStageSettings())
    assert IntraStageSettings().frames >= 3
    assert [r.sensor for r in rows] == ["LIDAR_LEFT"], notes
    row = rows[0]
    assert row.usable, row.reason
    rig = load_truth(clip).rigs["red"]
    # T_ego_S = T_ego_top (published, itself ~0.4 deg / 15 cm off the truth in this preset)
    # x T_top_S: compare the relation to the true top LiDAR, which is what the data measures
    from v2xlake.tasks.geometry import invert, transform

    T = transform(np.array([row.tx, row.ty, row.tz]), np.array([row.qw, row.qx, row.qy,
                                                                 row.qz]))
    T_top_pub = read_extrinsics(lake, CID, "red")["LIDAR_TOP"]
    got = invert(T_top_pub) @ T
    true = invert(rig.T_ego_lidar_true) @ rig.T_ego_side_true
    deg, m = pose_distance(true, got)
    # measured: 0.08 deg / 4.1 cm with a reported 1-sigma of 0.11 deg / 1.9 cm (16-beam side
    # LiDAR on a moving vehicle, town street): within 3 sigma, not within the real rig's 2 cm
    assert deg < 0.3 and m < 0.05, (deg, m)
    assert deg < 3 * row.std_deg and m < 3 * row.std_m, (deg, m, row.std_deg, row.std_m)
    start = pose_distance(true, invert(T_top_pub) @ rig.T_ego_side_pub)
    assert start[0] > 20.0  # it really started far off
    assert row.std_deg < 0.5 and row.std_m < 0.05
    assert "rx ry rz tx ty tz" == row.refined_components

    # the consumers: written as the register stage writes its table, read back as every
    # consumer reads calibration, and printed as `v2xlake calibration` prints it
    lake.write_table("clean", "calibration_refined", rows_to_table(CalibrationRefinedRow, rows),
                     clip_id=CID, name="calibration_refined")
    rec = read_clip(lake, CID).agents["red"]  # what annotate, align and the exports read
    assert np.allclose(rec.sensors["LIDAR_LEFT"].T_ego_sensor, T)
    assert np.allclose(rec.sensors["LIDAR_TOP"].T_ego_sensor, T_top_pub)
    table = format_calibration(compare_calibration(lake, CID))
    line = next(ln for ln in table.splitlines() if "LIDAR_LEFT" in ln)
    assert "refined" in line and "rx ry rz tx ty tz" in line

    # and the Python API's view of the same table: published vs refined per LiDAR
    import v2xlake

    cal = v2xlake.open(lake.uri).clip(CID).calibration().to_pylist()
    left = next(r for r in cal if r["agent_id"] == "red" and r["sensor"] == "LIDAR_LEFT")
    assert left["effective"] == "refined" and left["usable"]
    assert np.allclose([left["ref_tx"], left["ref_ty"], left["ref_tz"]], T[:3, 3])
    assert np.allclose([left["pub_tx"], left["pub_ty"], left["pub_tz"]],
                       rig.T_ego_side_pub[:3, 3])
    top = next(r for r in cal if r["agent_id"] == "red" and r["sensor"] == "LIDAR_TOP")
    assert top["ref_tx"] is None and top["effective"] == "published"
