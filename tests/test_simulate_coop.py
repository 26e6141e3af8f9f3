"""The cooperative boulevard of issue #21 (``SimConfig.preset("coop")``), checked from truth.

One short low-resolution clip (4 s: the turn and the turn back, 16 x 180 LiDAR) is simulated
once; its ``truth/`` folder and its bags must show the scenario the issue describes: red at
15 m/s turning by 0.25 rad in 1 s and back, black straight at 16 m/s 20 m behind in the next
lane, black's published LiDAR extrinsic off by exactly the configured error (red's exact),
walls at +-14 m in the point cloud, and INS poses (nav_msgs/Odometry) equal to truth. The
variations are checked on the analytic world alone (no ray casting)."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq
import pytest
from scipy.spatial.transform import Rotation

from tests.fixtures.street import coop_config
from v2xlake.tasks.geodesy import LocalFrame, rot_z, utm_to_geodetic
from v2xlake.tasks.geometry import invert, rigid
from v2xlake.tasks.simulate import simulate
from v2xlake.tasks.simulate.bagwrite import make_typestore
from v2xlake.tasks.simulate.ins import ins_error
from v2xlake.tasks.simulate.navformats import utm_offset, utm_zone
from v2xlake.tasks.simulate.scene import build_world

SECONDS = 4.0


@pytest.fixture(scope="module")
def clip(tmp_path_factory: pytest.TempPathFactory) -> Path:
    cfg = coop_config("coop_test", seconds=SECONDS, seed=2, beams=16, columns=180)
    return simulate(tmp_path_factory.mktemp("coop") / "clip", cfg)


def _poses(clip: Path, agent: str) -> dict[str, np.ndarray]:
    t = pq.read_table(clip / "truth" / "poses.parquet").to_pydict()
    m = np.asarray(t["agent"]) == agent
    return {k: np.asarray(v)[m] for k, v in t.items() if k != "agent"}


def _matrix(d: dict[str, Any]) -> np.ndarray:
    q = np.array([d["rotation"][1], d["rotation"][2], d["rotation"][3], d["rotation"][0]])
    return rigid(Rotation.from_quat(q).as_matrix(), np.asarray(d["translation"]))


def _pose_matrices(p: dict[str, np.ndarray]) -> np.ndarray:
    r = Rotation.from_quat(np.column_stack([p["qx"], p["qy"], p["qz"], p["qw"]])).as_matrix()
    return rigid(r, np.column_stack([p["x"], p["y"], p["z"]]))


def _yaw(p: dict[str, np.ndarray]) -> np.ndarray:
    r = Rotation.from_quat(np.column_stack([p["qx"], p["qy"], p["qz"], p["qw"]]))
    return np.unwrap(r.as_euler("ZYX")[:, 0])


def test_red_turns_by_a_quarter_radian_in_one_second_and_back(clip: Path) -> None:
    p = _poses(clip, "red")
    tau = (p["t_ns"] - p["t_ns"][0]) / 1e9
    yaw = _yaw(p) - _yaw(p)[0]
    rate = np.gradient(yaw, tau)
    assert np.allclose(np.hypot(p["vx"], p["vy"]), 15.0, atol=1e-6)
    # turn 0.5-1.5 s, turn back 2.5-3.5 s; straight before, between and after
    assert abs(np.interp(2.0, tau, yaw) - 0.25) < 1e-4
    assert abs(yaw[-1]) < 1e-4
    first = (tau > 0.7) & (tau < 1.3)
    back = (tau > 2.7) & (tau < 3.3)
    assert rate[first].min() > 0.245 and rate[first].max() < 0.2501
    assert rate[back].max() < -0.245 and rate[back].min() > -0.2501
    quiet = (tau < 0.25) | ((tau > 1.75) & (tau < 2.25)) | (tau > 3.75)
    assert np.abs(rate[quiet]).max() < 0.01


def test_black_drives_straight_at_16_mps_20_m_behind_in_the_next_lane(clip: Path) -> None:
    red, black = _poses(clip, "red"), _poses(clip, "black")
    yaw_b = _yaw(black)
    assert np.ptp(yaw_b) < 1e-9
    assert np.allclose(np.hypot(black["vx"], black["vy"]), 16.0, atol=1e-6)
    # in red's frame at clip time 0 (= the road's axes: the road is parallel to it)
    y0 = _yaw(red)[0]
    assert abs(np.mod(yaw_b[0] - y0 + np.pi, 2 * np.pi) - np.pi) < 1e-9
    u, n = np.array([np.cos(y0), np.sin(y0)]), np.array([-np.sin(y0), np.cos(y0)])
    d = np.column_stack([black["x"] - red["x"][0], black["y"] - red["y"][0]])
    tau = (black["t_ns"] - black["t_ns"][0]) / 1e9
    assert np.allclose(d @ u, -20.0 + 16.0 * tau, atol=1e-6)
    assert np.allclose(d @ n, 3.5, atol=1e-6)
    # flat ground, no body roll / pitch on a straight line at constant speed
    assert np.allclose(black["z"], red["z"][0], atol=1e-9)


def test_black_published_extrinsic_is_off_by_exactly_the_configured_error(clip: Path) -> None:
    ext = json.loads((clip / "truth" / "extrinsics.json").read_text())["agents"]
    for agent in ("red", "black"):
        true = _matrix(ext[agent]["T_ego_lidar_true"])
        pub = _matrix(ext[agent]["T_ego_lidar_published"])
        dt = pub[:3, 3] - true[:3, 3]
        dr = Rotation.from_matrix(pub[:3, :3] @ true[:3, :3].T).as_euler("ZYX", degrees=True)
        want_t, want_ypr = ((0.12, -0.08, 0.05), (0.4, 0.0, 0.0)) if agent == "black" else (
            (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
        assert np.allclose(dt, want_t, atol=1e-9), agent
        assert np.allclose(dr, want_ypr, atol=1e-9), agent
        # LiDAR 1.9 m above the ground (base_link 0.40 m up), up to the seeded mount deviation
        assert abs(true[2, 3] + 0.40 - 1.9) < 0.08
    # eq. 1a with exact INS is off by the extrinsic error alone, on every pair
    rel = pq.read_table(clip / "truth" / "relative.parquet").to_pydict()
    assert len(rel["frame_idx"]) == round(SECONDS * 10)
    assert np.allclose(rel["init_err_trans_m"], np.linalg.norm([0.12, -0.08, 0.05]), atol=1e-6)
    assert np.allclose(rel["init_err_rot_deg"], 0.4, atol=1e-6)


def test_truth_relative_transform_matches_the_trajectories(clip: Path) -> None:
    ext = json.loads((clip / "truth" / "extrinsics.json").read_text())["agents"]
    rel = pq.read_table(clip / "truth" / "relative.parquet").to_pydict()
    red, black = _poses(clip, "red"), _poses(clip, "black")
    idx = np.searchsorted(red["t_ns"], np.asarray(rel["t_ns"]))
    assert np.array_equal(red["t_ns"][idx], rel["t_ns"])
    L1 = _pose_matrices(red)[idx] @ _matrix(ext["red"]["T_ego_lidar_true"])
    L2 = _pose_matrices(black)[idx] @ _matrix(ext["black"]["T_ego_lidar_true"])
    want = invert(L1) @ L2
    got = _pose_matrices({k: np.asarray(rel[k]) for k in ("x", "y", "z", "qw", "qx", "qy", "qz")})
    assert np.abs(got - want).max() < 1e-6
    # the pair's geometry moves: red's turn shows in the relative yaw, then it is undone
    yaw_rel = Rotation.from_matrix(want[:, :3, :3]).as_euler("ZYX")[:, 0]
    assert yaw_rel.min() < -0.24 and abs(yaw_rel[-1]) < 0.01


def test_walls_at_14_m_appear_in_both_point_clouds(clip: Path) -> None:
    red = _poses(clip, "red")
    y0 = _yaw(red)[0]
    n = np.array([-np.sin(y0), np.cos(y0)])
    lt = pq.read_table(clip / "truth" / "lidar_truth.parquet",
                       columns=["agent", "wx", "wy", "wz", "obj"]).to_pydict()
    obj = np.asarray(lt["obj"])
    # red starts 8.75 m right of the road centre line (lane right of black's at -5.25)
    d = (np.column_stack([lt["wx"], lt["wy"]]) - [red["x"][0], red["y"][0]]) @ n - 8.75
    agent = np.asarray(lt["agent"])
    for who in ("red", "black"):
        for side, pat in ((1, "wall_L"), (-1, "wall_R")):
            m = (agent == who) & np.char.startswith(obj.astype(str), pat)
            assert m.sum() > 1000, (who, pat)
            face = np.abs(d[m] - side * 14.0) < 1e-6
            # the rest: the end of a taller block above its lower neighbour (2 m deep)
            assert face.mean() > 0.9 and np.all((side * d[m] > 14.0 - 1e-6) & (side * d[m] < 16.0))
        # nothing but the walls stands beyond 14 m
        walls = np.char.startswith(obj.astype(str), "wall_")
        assert np.abs(d[(agent == who) & ~walls]).max() < 14.0
        # each agent's body is in the other's scan; the scene's objects all appear
        names = {re.sub(r"\d+$", "", o) for o in obj[agent == who]}
        other = "black" if who == "red" else "red"
        assert {f"agent_{other}", "pole_L", "pole_R", "parked_car_", "car_oncoming",
                "truck_ahead"} <= names, names


def test_exact_ins_is_the_truth(clip: Path) -> None:
    from rosbags.rosbag2 import Reader

    cfg = coop_config("coop_test", seconds=SECONDS, seed=2, beams=16, columns=180)
    ts = make_typestore(False)
    frame = LocalFrame(cfg.origin_lat, cfg.origin_lon)
    off = utm_offset(cfg)
    world = build_world(cfg)
    for agent in ("red", "black"):
        t_ns, pos, quat = [], [], []
        with Reader(clip / agent) as rd:
            conns = [c for c in rd.connections if c.topic == f"/{agent}/localization/odometry"]
            assert conns and conns[0].msgtype == "nav_msgs/msg/Odometry"
            for conn, _, raw in rd.messages(connections=conns):
                m = ts.deserialize_cdr(raw, conn.msgtype)
                t_ns.append(m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec)
                p, q = m.pose.pose.position, m.pose.pose.orientation
                pos.append((p.x + off[0], p.y + off[1], p.z + off[2]))
                quat.append((q.x, q.y, q.z, q.w))
        pos_a = np.asarray(pos)
        lat, lon, gamma = utm_to_geodetic(pos_a[:, 0], pos_a[:, 1], utm_zone(cfg.origin_lon))
        xyz = frame.to_local(lat, lon, pos_a[:, 2])
        R_grid = Rotation.from_quat(np.asarray(quat)).as_matrix()
        R_world = frame.R_local_enu(lat, lon) @ rot_z(-gamma) @ R_grid
        tau = (np.asarray(t_ns) - cfg.start_s * 1_000_000_000) / 1e9
        T = world.agents[agent].matrix(tau)
        assert len(tau) == 125 * SECONDS + 3  # 8 ms over the clip and its 20 ms tail
        assert np.abs(xyz - T[:, :3, 3]).max() < 1e-5  # UTM round trip: micrometres
        assert np.abs(R_world - T[:, :3, :3]).max() < 1e-9
    bias = _poses(clip, "black")
    assert max(np.abs(bias[k]).max() for k in ("bx", "by", "bz")) == 0.0


@pytest.mark.parametrize("gap", [-50.0, -9.0, 5.0, 20.0, 50.0])
def test_the_other_vehicle_ahead_or_behind(gap: float) -> None:
    w = build_world(coop_config("v", seconds=10.0, coop_gap_m=gap, beams=16, columns=180))
    pr, _ = w.agents["red"].pose2d(np.zeros(1))
    pb, yb = w.agents["black"].pose2d(np.zeros(1))
    u = np.array([np.cos(yb[0]), np.sin(yb[0])])
    assert abs((pb[0, :2] - pr[0, :2]) @ u - gap) < 1e-9


def test_red_cannot_change_lanes_into_a_close_follower() -> None:
    with pytest.raises(ValueError, match="collides with agent_black"):
        build_world(coop_config("v", seconds=10.0, coop_gap_m=-5.0))
    build_world(coop_config("v", seconds=10.0, coop_gap_m=-5.0, turn_rate_radps=0.0))


def test_no_turn_and_the_short_clip_variations() -> None:
    tau = np.linspace(0.0, 10.0, 1001)
    straight = build_world(coop_config("v", seconds=10.0, turn_rate_radps=0.0))
    _, yaw = straight.agents["red"].pose2d(tau)
    assert np.ptp(yaw) == 0.0
    long = build_world(coop_config("v", seconds=10.0))
    short = build_world(coop_config("v", seconds=3.0))
    assert [t.rate for t in long.agents["red"].profile.turns] == [0.25, -0.25]
    assert [t.rate for t in short.agents["red"].profile.turns] == [0.25]
    # a 3 s clip ends on the new heading
    _, yaw = short.agents["red"].pose2d(np.array([0.0, 3.0]))
    assert abs(yaw[1] - yaw[0] - 0.25) < 1e-6


def test_ins_noise_drift_and_step_variations() -> None:
    cfg = coop_config("v", seconds=10.0, ins_drift_mps=0.1, ins_step_m=(0.3, 0.0, 0.0),
                      ins_step_at_s=2.0)
    red, black = ins_error(cfg, "red"), ins_error(cfg, "black")
    assert abs(np.linalg.norm(red.drift) - 0.1) < 1e-12
    assert red.drift[2] == 0.0 and not np.allclose(red.drift, black.drift)
    jump = black.bias(np.array([2.0])) - black.bias(np.array([2.0 - 1e-9]))
    assert np.allclose(jump, [0.3, 0.0, 0.0], atol=1e-9)
    assert np.allclose(red.bias(np.array([1.0, 3.0])), [red.drift * 1.0, red.drift * 3.0])
    # drift on one agent only: the other keeps its (zero) bias
    one = coop_config("v", seconds=10.0, ins_drift_mps=0.1, ins_drift_agents=("black",))
    assert not ins_error(one, "red").drift.any()
    assert np.array_equal(ins_error(one, "black").drift, black.drift)
    # exact by default, the same world for the same seed
    base = coop_config("v", seconds=3.0)
    assert not np.any(ins_error(base, "black").bias(np.linspace(0, 3, 7)))
    a, b = build_world(base), build_world(base)
    assert np.array_equal(a.scene.sb_center, b.scene.sb_center)
    assert np.array_equal(a.scene.cy_xy, b.scene.cy_xy)
    assert len(a.scene.cy_name) == 20
    assert sum(x.instance_id.startswith("parked_car_") for x in a.scene.actors) == 6
