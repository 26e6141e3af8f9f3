"""The simulated world: agent trajectories, a road with buildings, poles, fences, parked and
moving vehicles (a truck, a pickup towing a trailer), pedestrians and a cyclist.

Everything is generated from the seed (``numpy.random.default_rng(seed)``) and the config, so
``build_world(cfg)`` called twice gives the same world (``tasks.simulate.truth`` relies on it).

``street="boulevard"`` has its own layout (a straight road fixed in the world, every vehicle on
its own profile): see ``tasks.simulate.boulevard``. Town and corridor:

Layout (lateral offsets ``d`` in metres, left of the red agent's path, which IS the road):
right sidewalk -8.0..-5.2, parking lane -5.2..-1.75 (parked cars at -3.3), red's lane
-1.75..1.75 (centre 0), black's lane (same direction) 1.75..5.25, oncoming lanes centred at 7.0
and 10.5, left sidewalk 14.0..17.0, buildings beyond -10 and +18. Poles at -5.0 / +14.3.

Agents: ``red`` (reference) drives the path at ~18 m/s (``speed_mps``, +-0.5 m/s slow
sinusoid) with a smooth left-or-right turn (0.15 rad/s, 0.5 s .. 5.5 s, logistic ramps) and
further gentle turns every 16 s; ``black`` follows the same path in the left lane, starting
~15 m ahead (profile time shift 0.8 s, rate 1.005, so 15..21 m ahead over a minute); ``rsu``
is a static mast 5.6 m right of the road ~70 m ahead, looking back along the road.

Objects:
* ground: the plane z = ``ground_z`` (ellipsoidal height ``ground_alt_m``), object id 1.
* static boxes (buildings, fence panels): yaw-only oriented boxes; fences are semi-transparent
  to the LiDAR (first weak return + the surface behind = dual return).
* cylinders: vertical poles (and the roadside unit's mast).
* actors: yaw-only boxes moving on a :class:`Trajectory` (parked cars have static ones); the
  box is (length, width, height) along the body x, y, z, bottom on the ground. The agents'
  own bodies are actors too (the other agent sees them); an agent never sees its own body.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from v2xlake.schemas.annotation import ObjectClass
from v2xlake.tasks.simulate.config import SimConfig
from v2xlake.tasks.simulate.trajectory import KinematicProfile, Trajectory, Turn

GROUND_ID = 1
EGO_HEIGHT = 0.40  # INS (base_link) above the ground, at the body's geometric centre
AGENT_SIZE = (4.92, 1.86, 1.48)  # Lincoln MKZ l, w, h


@dataclass(frozen=True)
class Actor:
    """A (possibly moving) yaw-only box with identity, looks and what is drawn on it."""

    instance_id: str
    category: ObjectClass
    size: tuple[float, float, float]  # length (x), width (y), height (z)
    traj: Trajectory
    color: tuple[int, int, int]  # BGR
    reflectivity: float
    links: tuple[str, ...] = ()
    plates: tuple[tuple[str, str, int], ...] = ()  # (front|rear, text, 0 white / 1 yellow)
    face: int | None = None  # face texture index (pedestrians, cyclist)
    agent: str | None = None  # the agent whose body this is

    @property
    def z_offset(self) -> float:
        """Box centre height above the trajectory point."""
        return self.size[2] / 2 - self.traj.height

    def box_pose(self, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(..., 3) box centre and (...,) yaw at times ``tau``."""
        p, yaw = self.traj.pose2d(tau)
        return p + np.array([0.0, 0.0, self.z_offset]), yaw


@dataclass
class Scene:
    ground_z: float
    # static boxes
    sb_center: np.ndarray
    sb_half: np.ndarray
    sb_yaw: np.ndarray
    sb_refl: np.ndarray
    sb_transmit: np.ndarray  # bool: semi-transparent (fence)
    sb_color: np.ndarray  # (N, 3) uint8 BGR
    sb_name: list[str]
    # vertical cylinders
    cy_xy: np.ndarray
    cy_r: np.ndarray
    cy_z: np.ndarray  # (M, 2) bottom, top
    cy_refl: np.ndarray
    cy_color: np.ndarray
    cy_name: list[str]
    actors: list[Actor]
    decals: np.ndarray  # (K, 4, 3) ground polygons for cameras (road, sidewalks, markings)
    decal_color: np.ndarray  # (K, 3)
    ground_color: tuple[int, int, int] = (70, 110, 95)
    names: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.names = ["none", "ground", *self.sb_name, *self.cy_name,
                      *[a.instance_id for a in self.actors]]

    @property
    def sb_id0(self) -> int:
        return 2

    @property
    def cy_id0(self) -> int:
        return 2 + len(self.sb_name)

    @property
    def actor_id0(self) -> int:
        return 2 + len(self.sb_name) + len(self.cy_name)

    def actor_id(self, i: int) -> int:
        return self.actor_id0 + i

    def actor_poses(self, tau: float) -> tuple[np.ndarray, np.ndarray]:
        """Box centres (A, 3) and yaws (A,) of all actors at one instant."""
        c = np.empty((len(self.actors), 3))
        y = np.empty(len(self.actors))
        t = np.array([tau])
        for k, a in enumerate(self.actors):
            ck, yk = a.box_pose(t)
            c[k], y[k] = ck[0], yk[0]
        return c, y

    def is_static_id(self, ids: np.ndarray) -> np.ndarray:
        """Object ids that never move (ground, buildings, fences, poles, parked cars)."""
        static_actor = np.array([a.traj.static for a in self.actors], bool)
        lut = np.ones(len(self.names), bool)
        lut[0] = False
        lut[self.actor_id0:] = static_actor
        return lut[ids]


@dataclass
class World:
    cfg: SimConfig
    agents: dict[str, Trajectory]
    scene: Scene
    path_s: np.ndarray  # arc length samples of the red path
    path_t: np.ndarray  # profile time at those samples


def _red_profile(cfg: SimConfig, rng: np.random.Generator) -> KinematicProfile:
    sign = 1.0 if rng.random() < 0.5 else -1.0
    turns = [Turn(0.5, 5.5, 0.15 * sign, 0.3)]
    t = 14.0
    while t < cfg.seconds + 10:
        sign = -sign
        turns.append(Turn(t, t + 4.0, 0.12 * sign, 0.4))
        t += 16.0
    return KinematicProfile(
        x0=0.0, y0=0.0, yaw0=float(rng.uniform(-np.pi, np.pi)), v0=cfg.speed_mps, dv=0.5,
        v_period=9.0, v_phase=float(rng.uniform(0, 2 * np.pi)), turns=tuple(turns),
        t_min=-150.0, t_max=float(cfg.seconds) + 150.0,
    )


def _color(rng: np.random.Generator, lo: int, hi: int) -> tuple[int, int, int]:
    c = rng.integers(lo, hi, 3)
    return int(c[0]), int(c[1]), int(c[2])


def _plate_text(rng: np.random.Generator) -> str:
    letters = "ABCDEFGHJKLMNPRSTUVWXYZ"
    return "".join(rng.choice(list(letters), 3)) + " " + "".join(rng.choice(list("0123456789"), 4))



def _town_traffic(cfg: SimConfig, rng: np.random.Generator,
                  road: Callable[..., Actor]) -> list[Actor]:
    """The town street's road users: a car ahead and behind, an oncoming van and truck, a
    pickup towing a trailer (linked)."""
    actors: list[Actor] = []
    actors.append(road("car_ahead", ObjectClass.CAR, (4.6, 1.85, 1.5), 47.0, 0.0, 1.0))
    actors.append(road("car_behind", ObjectClass.CAR, (4.5, 1.8, 1.45), -24.0, 3.5, 1.0))
    actors.append(road("van_oncoming", ObjectClass.VAN, (5.2, 2.0, 2.1), 90.0, 7.0, -0.95))
    actors.append(road("truck_oncoming", ObjectClass.TRUCK, (8.5, 2.5, 3.4), 150.0, 10.5, -0.8))
    pick_l, trail_l = 5.5, 4.0
    pickup = road("pickup_towing", ObjectClass.CAR, (pick_l, 2.0, 1.9), 105.0, 7.0, -0.85,
                  links=("trailer_towed",))
    actors.append(pickup)
    gap_t = (pick_l / 2 + 1.2 + trail_l / 2) / cfg.speed_mps
    actors.append(road("trailer_towed", ObjectClass.TRAILER, (trail_l, 2.1, 1.9), 0.0, 7.0,
                       -0.85, links=("pickup_towing",), front=False,
                       shift=pickup.traj.shift + gap_t))

    return actors


def _corridor_profile(cfg: SimConfig, rng: np.random.Generator) -> KinematicProfile:
    """Straight, one 90 deg turn (0.4 rad/s, about 4 s) centred at ``turn_at_s``, straight."""
    sign = 1.0 if rng.random() < 0.5 else -1.0
    mid = cfg.turn_at_s if cfg.turn_at_s is not None else cfg.seconds / 2
    rate = 0.4
    dur = (np.pi / 2) / rate  # the logistic window integrates to exactly dur
    return KinematicProfile(
        x0=0.0, y0=0.0, yaw0=float(rng.uniform(-np.pi, np.pi)), v0=cfg.speed_mps, dv=0.3,
        v_period=9.0, v_phase=float(rng.uniform(0, 2 * np.pi)),
        turns=(Turn(mid - dur / 2, mid + dur / 2, rate * sign, 0.3),),
        t_min=-150.0, t_max=float(cfg.seconds) + 150.0)


def _corridor_facades(cfg: SimConfig, rng: np.random.Generator, prof: KinematicProfile,
                      s: np.ndarray, ts: np.ndarray, s_min: float, s_max: float,
                      building: Callable[..., None]) -> None:
    """Continuous terraced facades flush with both sidewalks (no gaps, setbacks under 0.1 m:
    nothing but the poles and the far ends fixes a scan along the street), a cross street
    every 150-250 m, shorter blocks around the turn (whose walls turn with it) and none on the
    inside of it where the curve is too tight for a block."""
    w = prof.yaw_rate(ts)
    in_turn = np.abs(w) > 0.05
    s_turn = (float(s[in_turn].min()), float(s[in_turn].max())) if in_turn.any() else None
    left_turn = bool(in_turn.any() and w[in_turn].mean() > 0)
    for side, base in ((-1, 9.0), (1, 17.5)):
        inner = (side > 0) == left_turn
        sk, i = s_min, 0
        next_cross = rng.uniform(120, 200)
        while sk < s_max:
            turning = s_turn is not None and s_turn[0] - 8 < sk < s_turn[1] + 8
            if turning and inner:
                sk += 2.0
                continue
            if sk > next_cross and not turning:  # a cross street: one 14 m gap
                sk += 14.0
                next_cross = sk + rng.uniform(150, 250)
                continue
            length = rng.uniform(3.0, 5.0) if turning else rng.uniform(14, 30)
            depth, height = rng.uniform(8, 14), rng.uniform(8, 22)
            d = side * (base + depth / 2 + rng.uniform(0, 0.1))
            building(sk, length, d, depth, height,
                     f"building_{'L' if side > 0 else 'R'}{i:03d}")
            sk += length  # terraced: block meets block
            i += 1


def _corridor_traffic(cfg: SimConfig, rng: np.random.Generator, prof: KinematicProfile,
                      gz: float, t_of_s: Callable[[float], float],
                      plates: Callable[..., tuple[tuple[str, str, int], ...]]) -> list[Actor]:
    """Dense traffic both ways: two oncoming lanes with a vehicle every 18-40 m (cars, vans,
    trucks) meeting the agents throughout the clip, a car ahead and behind in each
    same-direction lane, moving with them."""
    out: list[Actor] = []
    v = cfg.speed_mps
    kinds = ((ObjectClass.CAR, (4.6, 1.85, 1.5)), (ObjectClass.CAR, (4.4, 1.8, 1.45)),
             (ObjectClass.VAN, (5.2, 2.0, 2.1)), (ObjectClass.TRUCK, (8.5, 2.5, 3.4)))

    def vehicle(name: str, shift: float, rate: float, lateral: float) -> Actor:
        cat, size = kinds[int(rng.choice(len(kinds), p=[0.4, 0.3, 0.18, 0.12]))]
        tr = Trajectory(prof, gz, 0.0, shift, rate, lateral)
        return Actor(name, cat, size, tr, _color(rng, 30, 230), float(rng.uniform(0.2, 0.5)),
                     (), plates())

    k = 0
    for lateral in (7.0, 10.5):
        rate = -float(rng.uniform(0.8, 1.1))
        # meets red at tau_m when shift + rate tau_m = tau_m: shift = (1 - rate) tau_m
        tau_m = -8.0 + rng.uniform(0, 1.5)
        while tau_m < cfg.seconds + 8.0:
            out.append(vehicle(f"oncoming_{k:02d}", (1 - rate) * tau_m, rate, lateral))
            tau_m += rng.uniform(18, 40) / (v * (1 - rate))
            k += 1
    for j, (lateral, s0, rate) in enumerate(((0.0, 28.0, 1.0), (0.0, -14.0, 1.0),
                                             (3.5, -16.0, 1.0), (3.5, 60.0, 1.6))):
        out.append(vehicle(f"same_way_{j:02d}", t_of_s(s0), rate, lateral))
    return out


def build_world(cfg: SimConfig) -> World:
    """Deterministic world for ``cfg`` (seeded by ``cfg.seed``)."""
    if cfg.street == "boulevard":  # its own layout: a fixed straight road, own profiles
        from v2xlake.tasks.simulate.boulevard import build_boulevard

        return build_boulevard(cfg)
    rng = np.random.default_rng([cfg.seed, 20240601])
    gz = cfg.ground_alt_m
    corridor = cfg.street == "corridor"
    prof = _corridor_profile(cfg, rng) if corridor else _red_profile(cfg, rng)
    rg, pg = 0.004, 0.003  # roll / pitch gains (rad per m/s^2)
    agents: dict[str, Trajectory] = {
        "red": Trajectory(prof, gz, EGO_HEIGHT, 0.0, 1.0, 0.0, roll_gain=rg, pitch_gain=pg),
    }
    if "black" in cfg.agents:
        if corridor:  # next lane, 6 m ahead at the start, 24 m at the end (rate <= 1.5)
            gain = min(18.0 / (cfg.speed_mps * cfg.seconds), 0.5)
            agents["black"] = Trajectory(prof, gz, EGO_HEIGHT, 6.0 / cfg.speed_mps, 1.0 + gain,
                                         3.5, roll_gain=rg, pitch_gain=pg)
        else:
            agents["black"] = Trajectory(prof, gz, EGO_HEIGHT, 0.8, 1.005, 3.5, roll_gain=rg,
                                         pitch_gain=pg)

    # dense samples of the red path: arc length <-> profile time
    t_lo, t_hi = -6.0, cfg.seconds * 1.01 + 12.0
    ts = np.arange(t_lo, t_hi, 0.01)
    xy = prof.position(ts)
    yaw_s = prof.yaw(ts)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    s -= np.interp(0.0, ts, s)

    def at(s_q: np.ndarray | float, d: float) -> tuple[np.ndarray, np.ndarray]:
        sq = np.atleast_1d(np.asarray(s_q, float))
        x = np.interp(sq, s, xy[:, 0])
        y = np.interp(sq, s, xy[:, 1])
        yw = np.interp(sq, s, np.unwrap(yaw_s))
        return np.stack([x - d * np.sin(yw), y + d * np.cos(yw)], -1), yw

    def t_of_s(s_q: float) -> float:
        return float(np.interp(s_q, s, ts))

    s_min, s_max = float(s[0]) + 5, float(s[-1]) - 5

    if "rsu" in cfg.agents:
        s_rsu = min(70.0, s_max - 10)
        p_rsu, yw_rsu = at(s_rsu, -5.6)
        # the unit faces back along the road (towards the approaching vehicles)
        rsu_prof = KinematicProfile(x0=float(p_rsu[0, 0]), y0=float(p_rsu[0, 1]),
                                    yaw0=float(yw_rsu[0] + np.pi), v0=0.0)
        agents["rsu"] = Trajectory(rsu_prof, gz, 0.0, static=True)

    # ---- static boxes: buildings and fences
    c_l, h_l, yaw_l, refl_l, tr_l, col_l, name_l = [], [], [], [], [], [], []

    def building(sk: float, length: float, d: float, depth: float, height: float,
                 name: str) -> None:
        p, yw = at(sk + length / 2, d)
        c_l.append([p[0, 0], p[0, 1], gz + height / 2])
        h_l.append([length / 2, depth / 2, height / 2])
        yaw_l.append(yw[0])
        refl_l.append(rng.uniform(0.3, 0.7))
        tr_l.append(False)
        col_l.append(rng.integers(80, 200, 3))
        name_l.append(name)

    if corridor:
        _corridor_facades(cfg, rng, prof, s, ts, s_min, s_max, building)
    for side, base in (() if corridor else ((-1, 10.0), (1, 18.0))):
        sk = s_min + rng.uniform(0, 10)
        i = 0
        while sk < s_max:
            length, depth, height = rng.uniform(10, 24), rng.uniform(8, 15), rng.uniform(5, 22)
            d = side * (base + depth / 2 + rng.uniform(0, 4))
            building(sk, length, d, depth, height, f"building_{'L' if side > 0 else 'R'}{i:03d}")
            sk += length + rng.uniform(2, 8)
            i += 1
    sk, i = (s_max if corridor else s_min + rng.uniform(0, 20)), 0
    while sk < s_max:
        length = rng.uniform(8, 16)
        for side, d in ((-1, -7.9), (1, 16.9)):
            if rng.random() < 0.6:
                p, yw = at(sk + length / 2, d)
                c_l.append([p[0, 0], p[0, 1], gz + 0.65])
                h_l.append([length / 2, 0.03, 0.65])
                yaw_l.append(yw[0])
                refl_l.append(0.35)
                tr_l.append(True)
                col_l.append(np.array([60, 140, 60]))
                name_l.append(f"fence_{'L' if side > 0 else 'R'}{i:03d}")
        sk += length + rng.uniform(10, 30)
        i += 1

    # ---- poles
    cy_xy, cy_r, cy_z, cy_name = [], [], [], []
    for side, d in ((-1, -5.0), (1, 14.3)):
        sk, i = s_min + rng.uniform(0, 15), 0
        while sk < s_max:
            p, _ = at(sk, d)
            cy_xy.append(p[0])
            cy_r.append(0.12)
            cy_z.append([gz, gz + 7.0])
            cy_name.append(f"pole_{'L' if side > 0 else 'R'}{i:03d}")
            sk += rng.uniform(30, 45) if corridor else rng.uniform(25, 35)
            i += 1
    if "rsu" in cfg.agents:
        prsu = agents["rsu"].pose2d(np.zeros(1))[0][0]
        cy_xy.append(prsu[:2])
        cy_r.append(0.15)
        cy_z.append([gz, gz + 5.2])
        cy_name.append("rsu_mast")

    # ---- actors
    actors: list[Actor] = []
    agent_colors = {"red": (40, 40, 200), "black": (30, 30, 30)}

    def plates(front: bool = True) -> tuple[tuple[str, str, int], ...]:
        style = int(rng.random() < 0.3)
        text = _plate_text(rng)
        out = [("rear", text, style)]
        if front:
            out.append(("front", text, style))
        return tuple(out)

    for name in ("red", "black"):
        if name in agents:
            actors.append(Actor(f"agent_{name}", ObjectClass.CAR, AGENT_SIZE, agents[name],
                                agent_colors[name], 0.3, plates=plates(), agent=name))

    def road(inst: str, cat: ObjectClass, size: tuple[float, float, float], s0: float,
             lateral: float, rate: float, links: tuple[str, ...] = (), front: bool = True,
             shift: float | None = None) -> Actor:
        col = _color(rng, 30, 230)
        tr = Trajectory(prof, gz, 0.0, t_of_s(s0) if shift is None else shift, rate, lateral)
        return Actor(inst, cat, size, tr, col, float(rng.uniform(0.2, 0.5)), links,
                     plates(front))

    if corridor:
        actors += _corridor_traffic(cfg, rng, prof, gz, t_of_s, plates)
    else:
        actors += _town_traffic(cfg, rng, road)
    # parked cars (static)
    sk, i = (s_max if corridor else s_min + rng.uniform(5, 15)), 0
    while sk < s_max:
        if rng.random() < 0.55:
            p, yw = at(sk, -3.3)
            pr = KinematicProfile(x0=float(p[0, 0]), y0=float(p[0, 1]), yaw0=float(yw[0]), v0=0.0)
            col = _color(rng, 30, 230)
            actors.append(Actor(f"parked_car_{i:02d}", ObjectClass.CAR, (4.5, 1.85, 1.5),
                                Trajectory(pr, gz, 0.0, static=True), col, 0.35,
                                plates=plates()))
            i += 1
        sk += rng.uniform(7, 14)

    # pedestrians (faces) and a cyclist
    v = cfg.speed_mps
    ped_s = np.sort(rng.uniform(12.0, max(40.0, v * cfg.seconds + 40.0), size=6))
    for k, sp in enumerate(ped_s):
        left = k % 3 == 2
        d = 15.3 if left else -6.4
        rate = (1.3 if left else -1.4) / v
        col = _color(rng, 40, 220)
        tr = Trajectory(prof, gz, 0.0, t_of_s(float(sp)), rate, d)
        actors.append(Actor(f"pedestrian_{k:02d}", ObjectClass.PEDESTRIAN, (0.5, 0.6, 1.75),
                            tr, col, 0.25, face=k % 2))
    pc, ywc = at(35.0, -7.0)
    cross = KinematicProfile(x0=float(pc[0, 0]), y0=float(pc[0, 1]), yaw0=float(ywc[0] + np.pi / 2),
                             v0=1.3, t_min=-150.0, t_max=cfg.seconds + 150.0)
    actors.append(Actor("pedestrian_crossing", ObjectClass.PEDESTRIAN, (0.5, 0.6, 1.72),
                        Trajectory(cross, gz, 0.0), (60, 60, 160), 0.25, face=1))
    actors.append(Actor("cyclist_00", ObjectClass.BICYCLE, (1.8, 0.6, 1.75),
                        Trajectory(prof, gz, 0.0, t_of_s(29.0), 6.0 / v, -1.9),
                        (20, 160, 220), 0.3, face=0))

    # ---- ground decals for the cameras (road surface, sidewalks, markings)
    dec, dcol = [], []
    seg = 4.0
    sgrid = np.arange(s_min, s_max - seg, seg)

    def strip(d0: float, d1: float, color: tuple[int, int, int], on: float = seg,
              period: float = seg) -> None:
        for s0 in np.arange(s_min, s_max - on, period):
            a0, _ = at(s0, d0)
            a1, _ = at(s0 + on, d0)
            b1, _ = at(s0 + on, d1)
            b0, _ = at(s0, d1)
            q = np.stack([a0[0], a1[0], b1[0], b0[0]])
            dec.append(np.column_stack([q, np.full(4, gz)]))
            dcol.append(color)

    del sgrid
    strip(-8.0, -5.2, (150, 150, 150))
    strip(14.0, 17.0, (150, 150, 150))
    strip(-5.2, 12.25, (62, 62, 62))
    strip(-5.25, -5.1, (200, 200, 200))
    strip(1.68, 1.82, (230, 230, 230), on=3.0, period=9.0)
    strip(5.15, 5.35, (40, 200, 230))
    strip(8.68, 8.82, (230, 230, 230), on=3.0, period=9.0)
    strip(12.1, 12.25, (200, 200, 200))

    def arr(x: list, dt: type = float) -> np.ndarray:
        return np.asarray(x, dtype=dt)

    scene = Scene(
        ground_z=gz,
        sb_center=arr(c_l).reshape(-1, 3), sb_half=arr(h_l).reshape(-1, 3), sb_yaw=arr(yaw_l),
        sb_refl=arr(refl_l), sb_transmit=arr(tr_l, bool),
        sb_color=np.asarray(col_l, np.uint8).reshape(-1, 3), sb_name=name_l,
        cy_xy=arr(cy_xy).reshape(-1, 2), cy_r=arr(cy_r), cy_z=arr(cy_z).reshape(-1, 2),
        cy_refl=np.full(len(cy_r), 0.5),
        cy_color=np.tile(np.array([120, 120, 120], np.uint8), (len(cy_r), 1)),
        cy_name=cy_name, actors=actors,
        decals=np.asarray(dec, float).reshape(-1, 4, 3), decal_color=np.asarray(dcol, np.uint8),
    )
    return World(cfg=cfg, agents=agents, scene=scene, path_s=s, path_t=ts)
