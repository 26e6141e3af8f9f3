"""Deskew and registration on the project's simulator: simulate -> ingest -> anonymize ->
deskew -> register, checked against the simulator's ground truth (truth/, not an input).

Deskew is compared (a) with the per-point SciPy reference on the same inputs (exactness:
< 0.1 mm) and (b) with the true world hit points in the TRUE LiDAR frame at scan start: the
residual there is what the simulated INS attitude bias and LiDAR calibration error leave
(millimetres), against about a metre of raw skew. Registration: eq. 1a must equal the
simulator's own eq. 1a, and GICP must land within 3 cm / 0.1 deg of the true T_L1_L2.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow.compute as pc
import pyarrow.parquet as pq
import pytest
from scipy.spatial.transform import Rotation

from tests.test_deskew import scipy_reference
from v2xlake.storage.lake import Lake
from v2xlake.storage.reader import read_extrinsics
from v2xlake.tasks.deskew.stage import run_deskew
from v2xlake.tasks.reader import load_pose_track
from v2xlake.tasks.register.core import transform_delta
from v2xlake.tasks.register.stage import run_register

sim = pytest.importorskip("v2xlake.tasks.simulate")
CID = "sim_deskew_register"


@pytest.fixture(scope="module")
def processed(tmp_path_factory: pytest.TempPathFactory) -> tuple[Lake, Path]:
    from v2xlake.tasks.anonymize import run_anonymize
    from v2xlake.tasks.ingest import run_ingest

    root = tmp_path_factory.mktemp("simreg")
    cfg = sim.SimConfig.preset("small", seconds=0.4, seed=5, cameras=(), clip_id=CID)
    clip = sim.simulate(root / "clip", cfg)
    lake = Lake(root / "lake")
    run_ingest(lake, clip)
    run_anonymize(lake, CID)
    run_deskew(lake, CID)
    run_register(lake, CID)
    return lake, clip


def _m(r: dict, p: str, t: tuple[str, str, str]) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = Rotation.from_quat([r[f"{p}qw"], r[f"{p}qx"], r[f"{p}qy"], r[f"{p}qz"]],
                                   scalar_first=True).as_matrix()
    m[:3, 3] = [r[p + t[0]], r[p + t[1]], r[p + t[2]]]
    return m


def test_deskew_on_simulated_clip(processed: tuple[Lake, Path]) -> None:
    from v2xlake.tasks.simulate.truth import load_truth

    lake, clip = processed
    truth = load_truth(clip)
    hits = pq.read_table(clip / "truth" / "lidar_truth.parquet")
    rel0 = pq.read_table(clip / "truth" / "relative.parquet").column("t_ns")[0].as_py()
    checked = 0
    for agent in ("red", "black"):
        frames = {f["frame_idx"]: f for f in lake.read_table(
            "clean", "lidar_frames", clip_id=CID, agent_id=agent).to_pylist()}
        for d in lake.read_table("clean", "deskew_frames", clip_id=CID,
                                 agent_id=agent).to_pylist():
            frames[d["frame_idx"]]["deskew_ref_ns"] = d["deskew_ref_ns"]
        off = rel0 - frames[0]["stamp_ns"]  # clean (relative) -> simulator (absolute) time
        out = lake.read_table("clean", "lidar_points_deskewed", clip_id=CID, agent_id=agent)
        raw = lake.read_table("clean", "lidar_points", clip_id=CID, agent_id=agent)
        track = load_pose_track(lake, CID, agent)
        e_pub = read_extrinsics(lake, CID, agent)["LIDAR_TOP"]
        for k, fr in frames.items():
            if fr["deskew_ref_ns"] is None:  # an edge frame the INS does not cover
                continue
            d = out.filter(pc.equal(out.column("frame_idx"), k))
            r = raw.filter(pc.equal(raw.column("frame_idx"), k))
            h = hits.filter(pc.and_(pc.equal(hits.column("agent"), agent),
                                    pc.equal(hits.column("frame_idx"), k)))
            xyz = np.stack([d.column(c).to_numpy() for c in "xyz"], 1).astype(np.float64)
            rxyz = np.stack([r.column(c).to_numpy() for c in "xyz"], 1)
            assert len(xyz) == len(rxyz) == h.num_rows  # message order kept, nothing dropped
            ref = scipy_reference(rxyz, r.column("t_ns").to_numpy(), track, e_pub,
                                  fr["deskew_ref_ns"])
            assert np.abs(xyz - ref).max() < 1e-4
            t0 = np.array([fr["deskew_ref_ns"] + off])
            m = np.linalg.inv(truth.T_world_ego(agent, t0)[0] @ truth.T_ego_lidar(agent))
            w = np.stack([h.column(c).to_numpy() for c in ("wx", "wy", "wz")], 1)
            true_t0 = w @ m[:3, :3].T + m[:3, 3]
            static = h.column("is_static").to_numpy(zero_copy_only=False)
            err = np.linalg.norm(xyz - true_t0, axis=1)[static]
            skew = np.linalg.norm(rxyz - true_t0, axis=1)[static]
            rms, raw_rms = np.sqrt(np.mean(err**2)), np.sqrt(np.mean(skew**2))
            print(f"{agent} frame {k}: deskew RMS {rms * 1e3:.1f} mm vs raw skew "
                  f"{raw_rms * 1e3:.0f} mm")
            assert rms < 0.01 and raw_rms > 0.3
            checked += 1
    assert checked >= 4


def test_register_on_simulated_clip(processed: tuple[Lake, Path]) -> None:
    lake, clip = processed
    rel = {r["frame_idx"]: r for r in pq.read_table(clip / "truth" / "relative.parquet")
           .to_pylist()}
    regs = lake.read_table("clean", "registrations", clip_id=CID).to_pylist()
    assert len(regs) >= 2
    for r in regs:
        tr = rel[r["frame_idx"]]
        T_true, T_sim_init = _m(tr, "", ("x", "y", "z")), _m(tr, "init_", ("x", "y", "z"))
        T_init, T = _m(r, "init_", ("tx", "ty", "tz")), _m(r, "", ("tx", "ty", "tz"))
        # our eq. 1a = the simulator's eq. 1a (same reported poses, published extrinsics)
        dm, dd = transform_delta(T_sim_init, T_init)
        assert dm < 1e-3 and dd < 1e-3
        m0, d0 = transform_delta(T_true, T_init)
        m1, d1 = transform_delta(T_true, T)
        print(f"frame {r['frame_idx']}: eq. 1a off {m0 * 100:.1f} cm / {d0:.2f} deg -> GICP "
              f"{m1 * 100:.2f} cm / {d1:.3f} deg (fitness {r['fitness']:.2f})")
        assert m1 < 0.03 and d1 < 0.1
        # a 0.4 s clip is about one measurement (GICP errors of consecutive frames are
        # correlated, ``gicp_correlation_s``): its edge frames' honest 1-sigma sits at the
        # acceptance limit (2.0 cm); they may be held back as uncertain, never accepted wrong
        assert r["accepted"] or r["reason"].startswith("uncertain")
    assert sum(r["accepted"] for r in regs) >= len(regs) // 2
