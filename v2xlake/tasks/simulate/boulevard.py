"""The cooperative-registration boulevard of issue #21 (``SimConfig.street == "boulevard"``).

Unlike the town and the corridor, whose road IS the red agent's path, the boulevard is a
straight road fixed in the world and every vehicle has its own kinematic profile: the red
agent's turn does not bend the walls, and ``black`` really drives straight.

Road frame (``s`` along, ``d`` left of the centre line, both in metres): the centre line is
parallel to red's heading at clip time 0 (a seeded yaw), red's true INS position at tau = 0 is
(0, 0) in the world, at ``s = 0, d = red_lane``. Layout (default numbers, all config fields):

* walls: terraced blocks 18-36 m long, 6-16 m high, whose faces are exactly at
  ``d = +-wall_offset_m`` (14 m), covering 150 m before and after the stretch the agents drive
  (no gaps, no set-backs: only their top edges and the objects below fix the along-road axis);
* three lanes each way, 3.5 m wide: same direction at d = -1.75, -5.25, -8.75 (right), oncoming
  at +1.75, +5.25, +8.75; a parking strip at d = -11.5 (kerb side of the right lane),
  sidewalks from 12.5 m to the walls;
* ``n_poles`` (20) poles, 7 m tall, alternating left / right at d = +-12.8, evenly spread (with
  seeded jitter) over the stretch both agents see; ``n_parked_cars`` (6) parked cars at
  d = -11.5 on seeded, at least 6 m apart slots of the same stretch;
* an oncoming car (lane +5.25, 13-15 m/s) that meets red in the middle of the clip, a truck
  (8.5 m, lane -1.75, 13.5 m/s, 35-45 m ahead of red) and a pedestrian crossing the road
  (1.3 m/s, from the left sidewalk, at a seeded place red reaches 1.3-2.3 s after mid-clip).

Agents (``Trajectory`` on their own ``KinematicProfile``):

* ``red``: ``speed_mps`` (15 m/s, constant), one turn of ``turn_rate_radps`` (0.25 rad/s, + =
  left) for ``turn_duration_s`` (1 s) centred at ``turn_at_s`` (default 1.0 s: 0.5-1.5 s),
  logistic ramps of ``turn_ramp_s`` (0.05 s); and the turn back (the opposite rate, same
  duration) centred ``turn_back_after_s`` (2 s) later (2.5-3.5 s) if the clip holds all of it,
  ramp included (clips of 3.75 s and more with the defaults; a 3 s clip ends on the new
  heading). A turn and its turn back are a 7.4 m
  double lane change (15 m/s x 0.5 rad s): red starts in the lane right of black's
  (``red_lane_m`` default: ``coop_lane_m - 3.5`` for a left turn or none, ``+ 3.5`` for a
  right turn) and crosses black's lane into the one beyond it.
* ``black``: ``coop_speed_mps`` (16 m/s) straight along its lane ``coop_lane_m`` (-5.25),
  starting ``coop_gap_m`` (-20 m: behind; + ahead) along the road from red.
* ``rsu`` (optional): a static mast on the right sidewalk 70 m ahead, facing back.

Body roll / pitch follow the lateral / longitudinal acceleration as for the other streets (red's
turn rolls it by ~0.9 deg). The world is checked for collisions: an agent's footprint must
keep off every road user's and the other agent's (20 ms steps over the clip) and stay between
the sidewalks, otherwise ``build_boulevard`` raises ``ValueError`` naming what it hits (a
variation such as "5 m behind" with the turn puts red's lane change into black's bonnet:
pick a larger gap or no turn).
"""

from __future__ import annotations

import numpy as np

from v2xlake.schemas.annotation import ObjectClass
from v2xlake.tasks.simulate.config import SimConfig
from v2xlake.tasks.simulate.scene import (
    AGENT_SIZE,
    EGO_HEIGHT,
    Actor,
    Scene,
    World,
    _color,
    _plate_text,
)
from v2xlake.tasks.simulate.trajectory import KinematicProfile, Trajectory, Turn

LANE_W = 3.5
PARK_D = -11.5
SIDEWALK_IN = 12.5
POLE_INSET = 1.2
WALL_MARGIN_S = 150.0
CHECK_DT = 0.02


def red_turns(cfg: SimConfig) -> tuple[Turn, ...]:
    """Red's turn and, if the clip holds all of it, its turn back."""
    if cfg.turn_rate_radps == 0.0:
        return ()
    mid = 1.0 if cfg.turn_at_s is None else cfg.turn_at_s
    half = cfg.turn_duration_s / 2
    out = [Turn(mid - half, mid + half, cfg.turn_rate_radps, cfg.turn_ramp_s)]
    if cfg.turn_back_after_s is not None:
        mid2 = mid + cfg.turn_back_after_s
        # the whole turn back, ramp included (5 time constants: 99.3 % of the yaw)
        if mid2 + half + 5 * cfg.turn_ramp_s <= cfg.seconds + 1e-9:
            out.append(Turn(mid2 - half, mid2 + half, -cfg.turn_rate_radps, cfg.turn_ramp_s))
    return tuple(out)


def red_lane(cfg: SimConfig) -> float:
    if cfg.red_lane_m is not None:
        return cfg.red_lane_m
    return cfg.coop_lane_m + (LANE_W if cfg.turn_rate_radps < 0 else -LANE_W)


class RoadFrame:
    """(s, d) road coordinates <-> world xy; red's start (s = 0, d = red_lane) is the origin."""

    def __init__(self, yaw: float, d_red: float) -> None:
        self.yaw, self.d_red = yaw, d_red
        self.u = np.array([np.cos(yaw), np.sin(yaw)])
        self.n = np.array([-np.sin(yaw), np.cos(yaw)])

    def xy(self, s: float | np.ndarray, d: float | np.ndarray) -> np.ndarray:
        s_a, d_a = np.asarray(s, float), np.asarray(d, float)
        return s_a[..., None] * self.u + (d_a - self.d_red)[..., None] * self.n

    def sd(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        xy = np.asarray(xy, float)
        return xy[..., :2] @ self.u, xy[..., :2] @ self.n + self.d_red


def _straight(road: RoadFrame, s0: float, d: float, heading: float, v: float,
              t_max: float) -> KinematicProfile:
    p = road.xy(s0, d)
    return KinematicProfile(x0=float(p[0]), y0=float(p[1]), yaw0=float(heading), v0=v,
                            t_min=-60.0, t_max=t_max)


def _overlap(c1: np.ndarray, y1: np.ndarray, h1: np.ndarray, c2: np.ndarray, y2: np.ndarray,
             h2: np.ndarray) -> np.ndarray:
    """Do yaw-only rectangles (centres (N, 2), yaws (N,), half sizes (2,)) overlap? (SAT)"""
    ax = np.stack([np.stack([np.cos(y1), np.sin(y1)], -1), np.stack([-np.sin(y1), np.cos(y1)], -1),
                   np.stack([np.cos(y2), np.sin(y2)], -1), np.stack([-np.sin(y2), np.cos(y2)], -1)],
                  1)  # (N, 4, 2)
    e1 = np.stack([np.stack([np.cos(y1), np.sin(y1)], -1) * h1[0],
                   np.stack([-np.sin(y1), np.cos(y1)], -1) * h1[1]], 1)  # (N, 2, 2)
    e2 = np.stack([np.stack([np.cos(y2), np.sin(y2)], -1) * h2[0],
                   np.stack([-np.sin(y2), np.cos(y2)], -1) * h2[1]], 1)
    dist = np.abs(np.einsum("nk,nak->na", c2 - c1, ax))
    r1 = np.abs(np.einsum("nek,nak->nae", e1, ax)).sum(-1)
    r2 = np.abs(np.einsum("nek,nak->nae", e2, ax)).sum(-1)
    return np.all(dist <= r1 + r2, axis=1)


def check_collisions(cfg: SimConfig, agents: dict[str, Trajectory], actors: list[Actor],
                     road: RoadFrame, margin: float = 0.2) -> None:
    """Raise ValueError when an agent's footprint meets another road user's or leaves the
    carriageway during the clip (a scenario no recording can contain)."""
    tau = np.arange(0.0, cfg.seconds + CHECK_DT, CHECK_DT)
    half = np.array(AGENT_SIZE[:2]) / 2 + margin
    for name, traj in agents.items():
        if traj.static:
            continue
        p, yaw = traj.pose2d(tau)
        _, d = road.sd(p)
        reach = np.abs(np.sin(yaw - road.yaw)) * half[0] + np.abs(np.cos(yaw - road.yaw)) * half[1]
        off = (d + reach > SIDEWALK_IN) | (d - reach < -SIDEWALK_IN)
        if off.any():
            raise ValueError(f"boulevard: {name} leaves the carriageway at clip time "
                             f"{tau[np.argmax(off)]:.2f} s (lateral {d[np.argmax(off)]:.1f} m); "
                             "change turn_rate_radps / turn_back_after_s / red_lane_m")
        for act in actors:
            if act.agent == name:
                continue
            q, qy = act.traj.pose2d(tau)
            hit = _overlap(p[:, :2], yaw, half, q[:, :2], qy, np.array(act.size[:2]) / 2)
            if hit.any():
                raise ValueError(
                    f"boulevard: {name} collides with {act.instance_id} at clip time "
                    f"{tau[np.argmax(hit)]:.2f} s; change coop_gap_m, the turn "
                    "(turn_rate_radps = 0: no turn) or the seed")


def build_boulevard(cfg: SimConfig) -> World:
    """Deterministic boulevard world for ``cfg`` (seeded by ``cfg.seed``)."""
    rng = np.random.default_rng([cfg.seed, 20260121])
    gz = cfg.ground_alt_m
    yaw0 = float(rng.uniform(-np.pi, np.pi))
    d_red = red_lane(cfg)
    road = RoadFrame(yaw0, d_red)
    t_max = float(cfg.seconds) + 60.0
    rg, pg = 0.004, 0.003  # roll / pitch gains (rad per m/s^2), as the other streets
    prof = KinematicProfile(x0=0.0, y0=0.0, yaw0=yaw0, v0=cfg.speed_mps, turns=red_turns(cfg),
                            t_min=-60.0, t_max=t_max)
    agents: dict[str, Trajectory] = {
        "red": Trajectory(prof, gz, EGO_HEIGHT, roll_gain=rg, pitch_gain=pg)}
    if "black" in cfg.agents:
        bprof = _straight(road, cfg.coop_gap_m, cfg.coop_lane_m, yaw0, cfg.coop_speed_mps, t_max)
        agents["black"] = Trajectory(bprof, gz, EGO_HEIGHT, roll_gain=rg, pitch_gain=pg)

    # the stretch both agents drive during the clip, in s
    sec = float(cfg.seconds)
    s_red_end = float(road.sd(prof.position(np.array([sec])))[0][0])
    s_starts = [0.0]
    s_ends = [s_red_end]
    if "black" in agents:
        s_starts.append(cfg.coop_gap_m)
        s_ends.append(cfg.coop_gap_m + cfg.coop_speed_mps * sec)
    s_a, s_b = min(s_starts) - 20.0, max(s_ends) + 30.0
    w = cfg.wall_offset_m

    # ---- walls (static boxes), faces exactly at d = +-w
    c_l, h_l, yaw_l, refl_l, col_l, name_l = [], [], [], [], [], []
    for side in (-1, 1):
        sk, i = s_a - WALL_MARGIN_S, 0
        while sk < s_b + WALL_MARGIN_S:
            length, height, depth = rng.uniform(18, 36), rng.uniform(6, 16), 2.0
            p = road.xy(sk + length / 2, side * (w + depth / 2))
            c_l.append([p[0], p[1], gz + height / 2])
            h_l.append([length / 2, depth / 2, height / 2])
            yaw_l.append(yaw0)
            refl_l.append(rng.uniform(0.3, 0.7))
            col_l.append(rng.integers(80, 200, 3))
            name_l.append(f"wall_{'L' if side > 0 else 'R'}{i:03d}")
            sk += length
            i += 1

    # ---- poles, alternating sides, evenly spread with jitter
    cy_xy, cy_r, cy_z, cy_name = [], [], [], []
    if cfg.n_poles:
        step = (s_b - s_a) / cfg.n_poles
        for k in range(cfg.n_poles):
            side = 1 if k % 2 else -1
            sk = s_a + (k + 0.5) * step + rng.uniform(-0.3, 0.3) * step
            cy_xy.append(road.xy(sk, side * (w - POLE_INSET)))
            cy_r.append(float(rng.uniform(0.10, 0.15)))
            cy_z.append([gz, gz + 7.0])
            cy_name.append(f"pole_{'L' if side > 0 else 'R'}{k:02d}")
    if "rsu" in cfg.agents:
        p_rsu = road.xy(min(70.0, s_b), -(w - 1.0))
        agents["rsu"] = Trajectory(KinematicProfile(x0=float(p_rsu[0]), y0=float(p_rsu[1]),
                                                    yaw0=yaw0 + np.pi, v0=0.0),
                                   gz, 0.0, static=True)
        cy_xy.append(p_rsu)
        cy_r.append(0.15)
        cy_z.append([gz, gz + 5.2])
        cy_name.append("rsu_mast")

    # ---- actors: the agents' bodies, parked cars, oncoming car, truck, pedestrian
    def plates() -> tuple[tuple[str, str, int], ...]:
        style, text = int(rng.random() < 0.3), _plate_text(rng)
        return (("rear", text, style), ("front", text, style))

    actors: list[Actor] = []
    agent_colors = {"red": (40, 40, 200), "black": (30, 30, 30)}
    for name in ("red", "black"):
        if name in agents:
            actors.append(Actor(f"agent_{name}", ObjectClass.CAR, AGENT_SIZE, agents[name],
                                agent_colors[name], 0.3, plates=plates(), agent=name))
    # parked cars on distinct slots (>= 6 m apart) of the stretch
    slots = np.arange(s_a + 10.0, s_b - 10.0, 6.5)
    pick = np.sort(rng.choice(len(slots), size=min(cfg.n_parked_cars, len(slots)),
                              replace=False)) if len(slots) else np.zeros(0, int)
    for i, j in enumerate(pick):
        sk = float(slots[j] + rng.uniform(-0.5, 0.5))
        pr = _straight(road, sk, PARK_D, yaw0 + rng.uniform(-0.03, 0.03), 0.0, t_max)
        actors.append(Actor(f"parked_car_{i:02d}", ObjectClass.CAR, (4.5, 1.85, 1.5),
                            Trajectory(pr, gz, 0.0, static=True), _color(rng, 30, 230), 0.35,
                            plates=plates()))
    # an oncoming car meeting red mid-clip
    v_on = float(rng.uniform(13.0, 15.0))
    t_meet = sec * float(rng.uniform(0.4, 0.6))
    s_meet = float(road.sd(prof.position(np.array([t_meet])))[0][0])
    actors.append(Actor("car_oncoming", ObjectClass.CAR, (4.6, 1.85, 1.5),
                        Trajectory(_straight(road, s_meet + v_on * t_meet, LANE_W * 1.5,
                                             yaw0 + np.pi, v_on, t_max), gz, 0.0),
                        _color(rng, 30, 230), float(rng.uniform(0.2, 0.5)), plates=plates()))
    # a truck ahead in the inner same-direction lane
    actors.append(Actor("truck_ahead", ObjectClass.TRUCK, (8.5, 2.5, 3.4),
                        Trajectory(_straight(road, float(rng.uniform(35.0, 45.0)), -LANE_W / 2,
                                             yaw0, 13.5, t_max), gz, 0.0),
                        _color(rng, 30, 230), float(rng.uniform(0.2, 0.5)), plates=plates()))
    # a pedestrian crossing from the left sidewalk
    s_x = cfg.speed_mps * sec / 2 + float(rng.uniform(20.0, 35.0))
    actors.append(Actor("pedestrian_crossing", ObjectClass.PEDESTRIAN, (0.5, 0.6, 1.72),
                        Trajectory(_straight(road, s_x, SIDEWALK_IN, yaw0 - np.pi / 2, 1.3,
                                             t_max), gz, 0.0),
                        (60, 60, 160), 0.25, face=1))
    check_collisions(cfg, agents, actors, road)

    # ---- ground decals for the cameras (road surface, sidewalks, markings)
    dec, dcol = [], []

    def strip(d0: float, d1: float, color: tuple[int, int, int], on: float = 8.0,
              period: float = 8.0) -> None:
        for s0 in np.arange(s_a - 40.0, s_b + 40.0 - on, period):
            q = np.stack([road.xy(s0, d0), road.xy(s0 + on, d0), road.xy(s0 + on, d1),
                          road.xy(s0, d1)])
            dec.append(np.column_stack([q, np.full(4, gz)]))
            dcol.append(color)

    strip(-w, -SIDEWALK_IN, (150, 150, 150))
    strip(SIDEWALK_IN, w, (150, 150, 150))
    strip(-SIDEWALK_IN, SIDEWALK_IN, (62, 62, 62))
    for dm in (-2 * LANE_W, -LANE_W, LANE_W, 2 * LANE_W):  # dashed lane lines
        strip(dm - 0.07, dm + 0.07, (230, 230, 230), on=3.0, period=9.0)
    for dm in (-3 * LANE_W, 3 * LANE_W):  # edge lines
        strip(dm - 0.07, dm + 0.07, (200, 200, 200))
    strip(-0.1, 0.1, (40, 200, 230))  # the centre line

    # arc length samples of red's path (World API)
    ts = np.arange(-6.0, sec * 1.01 + 12.0, 0.01)
    xy = prof.position(ts)
    s_path = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    s_path -= np.interp(0.0, ts, s_path)

    def arr(x: list, dt: type = float) -> np.ndarray:
        return np.asarray(x, dtype=dt)

    scene = Scene(
        ground_z=gz,
        sb_center=arr(c_l).reshape(-1, 3), sb_half=arr(h_l).reshape(-1, 3), sb_yaw=arr(yaw_l),
        sb_refl=arr(refl_l), sb_transmit=np.zeros(len(c_l), bool),
        sb_color=np.asarray(col_l, np.uint8).reshape(-1, 3), sb_name=name_l,
        cy_xy=arr(cy_xy).reshape(-1, 2), cy_r=arr(cy_r), cy_z=arr(cy_z).reshape(-1, 2),
        cy_refl=np.full(len(cy_r), 0.5),
        cy_color=np.tile(np.array([120, 120, 120], np.uint8), (len(cy_r), 1)),
        cy_name=cy_name, actors=actors,
        decals=np.asarray(dec, float).reshape(-1, 4, 3), decal_color=np.asarray(dcol, np.uint8),
    )
    return World(cfg=cfg, agents=agents, scene=scene, path_s=s_path, path_t=ts)
