"""``v2xlake simulate --pose-format inspva|odometry|navsat-imu|tf`` and the roadside unit.

One INS solution, four encodings (``tasks.simulate.navformats``): each clip runs every stage,
and the raw pose track ingest makes of it is the vendor-INS one to nanometres (UTM round
trip) — the encoding of a pose is data, not something downstream can see. The roadside unit
is a fixed-pose agent (surveyed pose in clip.yaml, no navigation topics) with its own LiDAR
and camera, deskewed and registered like the vehicles."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from v2xlake.flows.pipeline import STAGES
from v2xlake.schemas.clip import ClipConfig
from v2xlake.storage.lake import Lake
from v2xlake.tasks.geodesy import attitude_to_matrix, geodetic_to_ecef
from v2xlake.tasks.simulate import SimConfig, simulate


def _sim(out: Path, fmt: str) -> Path:
    return simulate(out, SimConfig.preset(
        "small", seconds=0.3, seed=3, cameras=("CAM_FRONT",), camera_hz=10,
        agents="red,black,rsu", pose_format=fmt, write_lidar_truth=False))


def _track(lake: Lake, cid: str) -> tuple[np.ndarray, np.ndarray, list[str]]:
    ins = lake.read_table("raw", "ins", clip_id=cid).sort_by([("agent_id", "ascending"),
                                                              ("t_ns", "ascending")])
    p = geodetic_to_ecef(ins["lat"].to_numpy(), ins["lon"].to_numpy(), ins["alt"].to_numpy())
    R = attitude_to_matrix(ins["roll"].to_numpy(), ins["pitch"].to_numpy(),
                           ins["azimuth"].to_numpy())
    keys = [f"{a}@{t}" for a, t in zip(ins["agent_id"].to_pylist(), ins["t_ns"].to_pylist(),
                                       strict=True)]
    return p, R, keys


@pytest.fixture(scope="module")
def reference(tmp_path_factory: pytest.TempPathFactory) -> tuple[np.ndarray, np.ndarray,
                                                                  list[str]]:
    tmp = tmp_path_factory.mktemp("inspva")
    lake = Lake(tmp / "lake")
    cid = STAGES[0].run(lake, str(_sim(tmp / "clip", "inspva")), STAGES[0].config_model()
                        ).clip_id
    return _track(lake, cid)


@pytest.mark.parametrize("fmt", ["odometry", "navsat-imu", "tf"])
def test_every_pose_format_runs_every_stage_to_the_same_track(
        tmp_path: Path, fmt: str, reference: tuple[np.ndarray, np.ndarray, list[str]]) -> None:
    clip = _sim(tmp_path / "clip", fmt)
    cfg = ClipConfig.load(clip)
    kinds = {a.agent_id: a.effective_pose.kind for a in cfg.agents}
    assert kinds == {"red": {"navsat-imu": "split"}.get(fmt, fmt),
                     "black": {"navsat-imu": "split"}.get(fmt, fmt), "rsu": "fixed"}
    lake = Lake(tmp_path / "lake")
    cid = None
    for stage in STAGES:
        rep = stage.run(lake, str(clip) if stage.name == "ingest" else cid,
                        stage.config_model())
        cid = rep.clip_id
        assert rep.status == "done", (stage.name, rep.reason)
        if stage.name == "qa":
            assert rep.metrics["errors"] == 0 and rep.metrics["warnings"] == 0, rep.notes
    assert cid is not None
    p, R, keys = _track(lake, cid)
    p0, R0, keys0 = reference
    assert keys == keys0
    assert np.abs(p - p0).max() < 1e-6  # nanometres through UTM, exact otherwise
    assert np.abs(R - R0).max() < 1e-12
    # the roadside unit: constant pose over its recording, deskewed like the vehicles
    frames = lake.read_table("clean", "deskew_frames", clip_id=cid, agent_id="rsu")
    assert frames.num_rows == 3 and set(frames["n_uncovered"].to_pylist()) == {0}
    ego = lake.read_table("clean", "ego_poses", clip_id=cid, agent_id="rsu")
    assert np.ptp(ego["x"].to_numpy()) == 0.0 and np.ptp(ego["qz"].to_numpy()) == 0.0


def test_cli_pose_format_option(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from v2xlake.flows.cli import main

    out = tmp_path / "c"
    assert main(["simulate", str(out), "--seconds", "0.1", "--cameras", "1",
                 "--pose-format", "navsat-imu"]) == 0
    red = ClipConfig.load(out).agent("red")
    assert red.effective_pose.kind == "split"
    assert red.sensor("INS_FIX").msg_type == "sensor_msgs/msg/NavSatFix"
    assert main(["simulate", str(tmp_path / "d"), "--pose-format", "gps"]) == 2
    assert "gps" in capsys.readouterr().err


def test_simulated_radar_through_ingest(tmp_path: Path) -> None:
    """``SimConfig.radar``: a 20 Hz front radar per vehicle; its detections reach
    radar_points exactly as the bag carries them, and static targets (most of the street)
    close in at the sensor's own speed along the line of sight."""
    from v2xlake.tasks.simulate.truth import load_truth

    clip = simulate(tmp_path / "clip", SimConfig.preset(
        "small", seconds=0.3, seed=3, cameras=("CAM_FRONT",), camera_hz=10, radar=True,
        write_lidar_truth=False))
    assert ClipConfig.load(clip).agent("red").sensor("RADAR_FRONT").rate_hz == 20
    lake = Lake(tmp_path / "lake")
    cid = STAGES[0].run(lake, str(clip), STAGES[0].config_model()).clip_id
    assert STAGES[1].run(lake, cid, STAGES[1].config_model()).metrics["errors"] == 0
    frames = lake.read_table("raw", "radar_frames", clip_id=cid, agent_id="red")
    assert frames.num_rows == 6 and min(frames["n_points"].to_pylist()) > 50
    pts = lake.read_table("raw", "radar_points", clip_id=cid, agent_id="red")
    truth = load_truth(clip)
    T = truth.T_world_ego("red", frames["stamp_ns"].to_numpy())
    v_world = np.stack([truth.T_world_ego("red", frames["stamp_ns"].to_numpy() + d)[:, :3, 3]
                        for d in (1_000_000, -1_000_000)])
    v_ego = (v_world[0] - v_world[1]) / 2e-3
    fi = pts["frame_idx"].to_numpy()
    xyz = np.stack([pts[c].to_numpy() for c in "xyz"], 1).astype(np.float64)
    u = xyz / np.linalg.norm(xyz, axis=1, keepdims=True)
    v_sensor_radar = np.einsum("nji,nj->ni", T[fi, :3, :3], v_ego[fi])  # ego axes = radar axes
    resid = pts["velocity"].to_numpy() + np.einsum("ni,ni->n", v_sensor_radar, u)
    assert np.median(np.abs(resid)) < 0.3  # static targets; the rest are moving actors
    assert np.abs(v_ego).max() > 5  # the vehicle is moving: the test is not vacuous
    # the car ahead drives away at about our speed: it does not close in like the street
    assert np.mean(resid > 10.0) > 0.02
