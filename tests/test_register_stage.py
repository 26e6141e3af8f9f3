"""Deskew + register stages end to end on a hand-built clean zone of two moving agents.

Both agents drive the ray-cast street while their LiDARs sweep (points carry their firing
times, so the raw scans are skewed); the cooperative agent's INS carries a constant bias, so
eq. 1a is off by decimetres and GICP on the deskewed scans must recover the true transform.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest
from scipy.spatial.transform import Rotation

from tests.test_register import cast_scan, lidar_pose, make_street
from tests.test_stage_reads import handle
from v2xlake.schemas.arrow import columns_to_table
from v2xlake.schemas.errors import ClipError
from v2xlake.schemas.tables import (
    AgentRow,
    CalibratedSensorRow,
    ClipRow,
    EgoPoseRow,
    LidarFrameRow,
    LidarPointRow,
)
from v2xlake.storage.lake import Lake
from v2xlake.tasks.deskew.stage import run_deskew
from v2xlake.tasks.ingest.rows import table_of
from v2xlake.tasks.register.core import transform_delta
from v2xlake.tasks.register.stage import REGISTER, RegisterConfig, plot_registration, run_register

CLIP = "street1"
FRAMES = (200_000_000, 300_000_000, 400_000_000)
N_COLS, N_BEAMS, GROUP = 720, 32, 24  # 24 columns fire together: 30 firing times a sweep


def ego_motion(agent: str) -> Callable[[float], np.ndarray]:
    """True T_world_ego at time t (s)."""
    def red(t: float) -> np.ndarray:
        return lidar_pose(-30.0 + 10.0 * t, -1.75, 3.0 * t, height=0.0)

    def black(t: float) -> np.ndarray:  # oncoming, 12-16 m ahead, turning slightly
        return lidar_pose(-12.0 - 8.0 * t, 1.75, 180.0 - 5.0 * t, roll_deg=0.5, height=0.0)

    def mast(t: float) -> np.ndarray:  # a roadside unit on the kerb, 8-13 m ahead: stationary
        return lidar_pose(-17.0, -4.5, 150.0, height=0.0)
    return red if agent == "red" else mast if agent == "mast" else black


EXTR = {"red": lidar_pose(0.6, 0.0, 1.0, height=1.9),
        "black": lidar_pose(0.4, 0.1, -1.5, pitch_deg=0.5, height=1.8)}
BIAS = {"red": np.eye(4), "black": lidar_pose(0.12, -0.1, 0.4, height=0.05)}  # INS error


def write_clip(lake: Lake, agents: tuple[str, ...] = ("red", "black")) -> None:
    street = make_street(3)
    lake.write_table("clean", "clips", table_of(ClipRow, [ClipRow(
        clip_id=CLIP, location="synthetic", road_type="urban", weather="clear", lighting="day",
        work_zone=False, n_agents=len(agents), reference_agent="red", duration_s=0.5,
        source="simulated", status="ok")]), clip_id=CLIP)
    for agent in agents:
        motion, e = ego_motion(agent), EXTR[agent]
        lake.write_table("clean", "agents", table_of(AgentRow, [AgentRow(
            clip_id=CLIP, agent_id=agent, kind="vehicle",
            role="reference" if agent == "red" else "cooperative", has_ins=True)]),
            clip_id=CLIP, agent_id=agent)
        q = Rotation.from_matrix(e[:3, :3]).as_quat(scalar_first=True)
        lake.write_table("clean", "calibrated_sensors", table_of(CalibratedSensorRow, [
            CalibratedSensorRow(clip_id=CLIP, agent_id=agent, sensor="LIDAR_TOP",
                                modality="lidar", tx=e[0, 3], ty=e[1, 3], tz=e[2, 3], qw=q[0],
                                qx=q[1], qy=q[2], qz=q[3], source="tf_static")]),
            clip_id=CLIP, agent_id=agent)
        t = np.arange(100_000_000, 600_000_001, 8_000_000, dtype=np.int64)
        w = np.stack([BIAS[agent] @ motion(s) for s in t * 1e-9])
        qq = Rotation.from_matrix(w[:, :3, :3]).as_quat(scalar_first=True)
        z = np.zeros(len(t))
        lake.write_table("clean", "ego_poses", columns_to_table(EgoPoseRow, {
            "clip_id": [CLIP] * len(t), "agent_id": [agent] * len(t), "t_ns": t,
            "x": w[:, 0, 3], "y": w[:, 1, 3], "z": w[:, 2, 3], "qw": qq[:, 0], "qx": qq[:, 1],
            "qy": qq[:, 2], "qz": qq[:, 3], "vx": z, "vy": z, "vz": z,
            "rtk_status": np.full(len(t), 2)}), clip_id=CLIP, agent_id=agent)
        xyz: list[np.ndarray] = []
        tt: list[np.ndarray] = []
        ff: list[np.ndarray] = []
        frames: list[LidarFrameRow] = []
        for k, t0 in enumerate(FRAMES):
            for g in range(N_COLS // GROUP):  # skewed sweep: each group at its own pose
                tg = t0 + (g * GROUP * 100_000_000) // N_COLS
                pts = cast_scan(street, motion(tg * 1e-9) @ e, n_beams=N_BEAMS, n_cols=N_COLS,
                                seed=1000 * k + g, columns=slice(g * GROUP, (g + 1) * GROUP))
                xyz.append(pts)
                tt.append(np.full(len(pts), tg, np.int64))
                ff.append(np.full(len(pts), k, np.int32))
            n = sum(len(p) for p in xyz) - sum(r.n_points for r in frames)
            frames.append(LidarFrameRow(clip_id=CLIP, agent_id=agent, sensor="LIDAR_TOP",
                                        frame_idx=k, stamp_ns=t0, t_start_ns=t0,
                                        t_end_ns=t0 + 99_000_000, n_points=n, n_nan=0))
        p, n = np.concatenate(xyz), sum(len(a) for a in xyz)
        lake.write_table("clean", "lidar_points", columns_to_table(LidarPointRow, {
            "clip_id": [CLIP] * n, "agent_id": [agent] * n,
            "sensor": pa.array(["LIDAR_TOP"] * n).dictionary_encode(),
            "frame_idx": np.concatenate(ff), "t_ns": np.concatenate(tt), "x": p[:, 0],
            "y": p[:, 1], "z": p[:, 2], "intensity": np.ones(n, np.float32),
            "ring": np.zeros(n, np.uint16), "return_id": np.zeros(n, np.uint8)}),
            clip_id=CLIP, agent_id=agent, row_group_by="frame_idx")
        lake.write_table("clean", "lidar_frames", table_of(LidarFrameRow, frames),
                         clip_id=CLIP, agent_id=agent)


def true_T(t_ns: int) -> np.ndarray:
    s = t_ns * 1e-9
    w1, w2 = ego_motion("red")(s) @ EXTR["red"], ego_motion("black")(s) @ EXTR["black"]
    return np.linalg.inv(w1) @ w2


@pytest.fixture(scope="module")
def clip_lakes(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Ray casting is the slow part: build each clean zone once, tests work on copies."""
    root = tmp_path_factory.mktemp("register_stage")
    write_clip(Lake(root / "pair"))
    write_clip(Lake(root / "solo"), agents=("red",))
    return {"pair": root / "pair", "solo": root / "solo"}


def _copy(src: Path, dst: Path) -> Lake:
    shutil.copytree(src, dst)
    return Lake(dst)


@pytest.mark.parametrize("backend", ["sparse", "small_gicp", "open3d"])
def test_deskew_then_register_recovers_true_transform(tmp_path: Path, backend: str,
                                                      clip_lakes: dict[str, Path]) -> None:
    lake = _copy(clip_lakes["pair"], tmp_path / "lake")
    run_deskew(lake, CLIP)
    # through the handle the flow gives the stage: reading an undeclared table fails
    rep = run_register(handle(lake, REGISTER), CLIP,
                       RegisterConfig.model_validate({"gicp": {"backend": backend}}))
    regs = lake.read_table("clean", "registrations", clip_id=CLIP).to_pylist()
    assert len(regs) == 3 and rep.metrics["n_accepted"] == 3
    for r in regs:
        assert r["accepted"] and r["reason"] == "ok" and r["method"] == f"{backend}:GICP+clip"
        truth = true_T(r["t_ns"])
        T = np.eye(4)
        T[:3, :3] = Rotation.from_quat([r["qw"], r["qx"], r["qy"], r["qz"]],
                                       scalar_first=True).as_matrix()
        T[:3, 3] = [r["tx"], r["ty"], r["tz"]]
        Ti = np.eye(4)
        Ti[:3, :3] = Rotation.from_quat([r["init_qw"], r["init_qx"], r["init_qy"], r["init_qz"]],
                                        scalar_first=True).as_matrix()
        Ti[:3, 3] = [r["init_tx"], r["init_ty"], r["init_tz"]]
        m, d = transform_delta(truth, T)
        mi, di = transform_delta(truth, Ti)
        print(f"frame {r['frame_idx']}: init {mi * 100:.1f} cm {di:.2f} deg -> {m * 100:.2f} cm "
              f"{d:.3f} deg, fitness {r['fitness']:.2f}")
        assert mi > 0.1 and m < 0.03 and d < 0.1
        assert r["fitness"] > 0.5 and r["correction_m"] == pytest.approx(
            transform_delta(Ti, T)[0])
    assert rep.images and lake.read_bytes(rep.images[0])[:8] == b"\x89PNG\r\n\x1a\n"
    out = plot_registration(lake, CLIP, 1, tmp_path / "bev.png")
    assert out.read_bytes()[:4] == b"\x89PNG"


def test_register_needs_deskew_and_handles_single_agent(tmp_path: Path,
                                                        clip_lakes: dict[str, Path]) -> None:
    lake = _copy(clip_lakes["pair"], tmp_path / "lake")
    with pytest.raises(ClipError, match="run deskew first"):
        run_register(lake, CLIP)
    solo = _copy(clip_lakes["solo"], tmp_path / "solo")
    run_deskew(solo, CLIP)
    rep = run_register(solo, CLIP)
    assert rep.status == "not_applicable" and not rep.outputs
    assert "the clip has 1 agent(s)" in (rep.reason or "")
