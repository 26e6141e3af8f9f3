"""Vectorised spinning-LiDAR ray casting with per-column time, motion and dual return.

Timing (CATS-V2V supp. A.1): scan ``k`` starts at ``start_ns + k * 100 ms`` with the azimuth at
exactly 0 deg (phase lock). Column ``j`` (azimuth ``j * 360 / columns`` deg, clockwise from the
LiDAR +x axis seen from above) fires at ``t_j = scan_start_ns + round(j * period_ns / columns)``;
all beams of a column share that time. Each column is cast from the TRUE LiDAR pose at ``t_j``
(``T_world_ego(t_j) @ T_ego_lidar_true``) against the scene with every moving object at ``t_j``,
and the point is reported in the LiDAR frame at ``t_j`` (what a real sensor outputs), so a raw
scan is skewed by the ego motion (~1.8 m between the first and the last column at 18 m/s).

Geometry: ray-plane (ground), ray-slab (yaw-only boxes: buildings, fences, all actors), and
ray-cylinder (vertical poles, caps ignored), all as NumPy broadcasts over (columns, beams,
candidates) in blocks of columns; candidates per block are culled by an exact azimuth-wedge
test on bounding spheres, enlarged by the motion within the block.

Returns (field ``return_type``): dual-return mode reports the strongest and the last echo per
beam. 3 = single echo (strongest and last coincide, reported once), 1 = strongest (distinct
from last), 2 = last (distinct from strongest). A ray passing a semi-transparent fence panel
gives a weak fence echo plus the surface behind: two points. When the last echo is also the
strongest, the sensor reports the second-strongest (the fence) as type 1, so both are kept.
A beam on the silhouette of a nearer object (a neighbouring beam, or column of the same
block, hits something >= 0.5 m farther) is a mixed pixel: its footprint also reaches the
surface behind, which gives a weaker last echo (type 2) at the next opaque hit along the SAME
ray (so its true position is exact), and the near echo becomes type 1.
Single-return mode (``dual_return=False``) reports the strongest echo only, as type 1.

Intensity (float32, 0..255): ``255 * rho * |cos(incidence)| / (1 + (r / 80 m)^2)`` clipped to
[1, 255], ``rho`` = material reflectivity (fence echo: rho * 0.4, surface behind a fence: *0.6).
Output order within a scan: by column (time), then return (strongest first), then ring (beam
0 = lowest elevation).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from v2xlake.tasks.simulate.config import AGENT_NAMES, LidarSpec
from v2xlake.tasks.simulate.scene import GROUND_ID, Scene, World

GROUND_RHO = 0.15
EDGE_GAP_M = 0.5


@dataclass
class Scan:
    """One LiDAR message worth of points plus the truth behind each point."""

    frame_idx: int
    stamp_ns: int  # scan start, on the 100 ms PPS grid
    xyz: np.ndarray  # (N, 3) float32, LiDAR frame at each point's own time
    t_ns: np.ndarray  # (N,) int64 absolute GNSS ns (column time)
    ring: np.ndarray  # (N,) uint16
    return_type: np.ndarray  # (N,) uint8
    intensity: np.ndarray  # (N,) float32
    obj_id: np.ndarray  # (N,) int32 scene object id hit (scene.names)
    world: np.ndarray  # (N, 3) float64 true hit point in the world (before range noise)


@dataclass
class ColumnState:
    """Per-column state of the last cast scan (reused by the annotation of that scan)."""

    t_ns: np.ndarray  # (C,) column times
    origin: np.ndarray  # (C, 3) LiDAR origin in the world
    rot: np.ndarray  # (C, 3, 3) R_world_lidar
    actor_center: np.ndarray  # (C, A, 3) for ``LidarCaster.actors`` (own body excluded)
    actor_yaw: np.ndarray  # (C, A)


def beam_elevations(spec: LidarSpec) -> np.ndarray:
    return np.radians(np.linspace(spec.elev_min_deg, spec.elev_max_deg, spec.beams))


def column_times_ns(spec: LidarSpec, scan_start_ns: int) -> np.ndarray:
    period = round(1e9 / spec.rate_hz)
    j = np.arange(spec.columns, dtype=np.int64)
    return scan_start_ns + np.round(j * period / spec.columns).astype(np.int64)


def _wedge_hit(az_c: np.ndarray, half: np.ndarray, a0: float, a1: float) -> np.ndarray:
    """Does the circular interval [az_c - half, az_c + half] meet [a0, a1] (radians)?"""
    mid, hw = 0.5 * (a0 + a1), 0.5 * (a1 - a0)
    dist = np.abs(np.mod(az_c - mid + np.pi, 2 * np.pi) - np.pi)
    return dist <= hw + half


class LidarCaster:
    """Casts scans of one agent's LiDAR into a world."""

    def __init__(self, world: World, agent: str, T_ego_lidar: np.ndarray, spec: LidarSpec,
                 start_ns: int, seed: int) -> None:
        self.world, self.agent, self.spec, self.start_ns = world, agent, spec, start_ns
        self.T_el = T_ego_lidar
        self.seed = seed
        sc: Scene = world.scene
        self.scene = sc
        el = beam_elevations(spec)
        self.cos_el, self.sin_el = np.cos(el), np.sin(el)
        self.actors = [(i, a) for i, a in enumerate(sc.actors) if a.agent != agent]
        # bounding spheres of static things
        self.sb_r = np.linalg.norm(sc.sb_half, axis=1)
        self.cy_c = np.column_stack([sc.cy_xy, sc.cy_z.mean(axis=1)])
        self.cy_rad = np.hypot(sc.cy_r, 0.5 * (sc.cy_z[:, 1] - sc.cy_z[:, 0]))
        self.block = max(1, spec.columns // 36)

    def lidar_poses(self, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p, r = self.world.agents[self.agent].pose(tau)
        rl = r @ self.T_el[:3, :3]
        ol = p + np.einsum("nij,j->ni", r, self.T_el[:3, 3])
        return ol, rl

    def cast(self, frame_idx: int) -> Scan:
        spec, sc = self.spec, self.scene
        period = round(1e9 / spec.rate_hz)
        stamp = self.start_ns + frame_idx * period
        t_col = column_times_ns(spec, stamp)
        tau = (t_col - self.start_ns) / 1e9
        ncol, nb = spec.columns, spec.beams
        az = 2 * np.pi * np.arange(ncol) / ncol
        o, rl = self.lidar_poses(tau)
        # actor boxes at every column time
        na = len(self.actors)
        a_c = np.empty((ncol, na, 3))
        a_yaw = np.empty((ncol, na))
        a_half = np.empty((na, 3))
        for k, (_, act) in enumerate(self.actors):
            c, y = act.box_pose(tau)
            a_c[:, k], a_yaw[:, k] = c, y
            a_half[k] = np.asarray(act.size) / 2
        a_r = np.linalg.norm(a_half, axis=1)
        a_refl = np.array([a.reflectivity for _, a in self.actors])
        a_ids = np.array([sc.actor_id(i) for i, _ in self.actors], np.int32)
        self.last = ColumnState(t_col, o, rl, a_c, a_yaw)
        rng = np.random.default_rng([self.seed, 4242, frame_idx, AGENT_NAMES.index(self.agent)])
        noise = spec.range_noise_m

        out: dict[str, list[np.ndarray]] = {k: [] for k in
                                            ("t", "ring", "rt", "inten", "oid", "r", "col")}
        for j0 in range(0, ncol, self.block):
            j1 = min(ncol, j0 + self.block)
            sl = slice(j0, j1)
            jm = (j0 + j1 - 1) // 2
            om, rm = o[jm], rl[jm]
            move = float(np.linalg.norm(o[j1 - 1] - o[j0])) + 0.05
            a0, a1 = az[j0], az[j1 - 1]
            dang = 2 * np.pi / ncol + 0.01

            def cull(cent: np.ndarray, rad: np.ndarray, om: np.ndarray = om,
                     rm: np.ndarray = rm, move: float = move,
                     a0: float = a0, a1: float = a1, dang: float = dang) -> np.ndarray:
                d = (cent - om) @ rm
                rxy = np.hypot(d[:, 0], d[:, 1])
                rr = rad + move
                half = np.where(rxy > rr, np.arcsin(np.clip(rr / np.maximum(rxy, 1e-9), 0, 1)),
                                np.pi)
                azc = np.mod(np.arctan2(-d[:, 1], d[:, 0]), 2 * np.pi)
                near = np.linalg.norm(d, axis=1) - rr < spec.max_range_m
                return near & _wedge_hit(azc, half + dang, a0, a1)

            sb_k = np.flatnonzero(cull(sc.sb_center, self.sb_r))
            cy_k = np.flatnonzero(cull(self.cy_c, self.cy_rad))
            if na:
                amove = np.linalg.norm(a_c[j1 - 1] - a_c[j0], axis=1)
                ac_k = np.flatnonzero(cull(a_c[jm], a_r + amove))
            else:
                ac_k = np.zeros(0, np.int64)

            # rays of the block: (C, B, 3) world directions
            ca, sa = np.cos(az[sl]), np.sin(az[sl])
            dl = np.stack([ca[:, None] * self.cos_el[None, :], -sa[:, None] * self.cos_el[None, :],
                           np.broadcast_to(self.sin_el[None, :], (j1 - j0, nb))], -1)
            dw = np.einsum("cij,cbj->cbi", rl[sl], dl)
            ob = o[sl]
            C = j1 - j0
            ts_l, cos_l, rho_l, id_l, tr_l = [], [], [], [], []

            # ground plane
            dz = dw[..., 2]
            with np.errstate(divide="ignore", invalid="ignore"):
                tg = np.where(dz < -1e-9, (sc.ground_z - ob[:, 2:3]) / dz, np.inf)
            ts_l.append(tg[..., None])
            cos_l.append(np.abs(dz)[..., None])
            rho_l.append(np.full((1,), GROUND_RHO))
            id_l.append(np.array([GROUND_ID], np.int32))
            tr_l.append(np.array([False]))

            # boxes: static (broadcast over columns) + actors (per column)
            if len(sb_k) or len(ac_k):
                bc = np.concatenate([np.broadcast_to(sc.sb_center[sb_k], (C, len(sb_k), 3)),
                                     a_c[sl][:, ac_k]], axis=1)
                by = np.concatenate([np.broadcast_to(sc.sb_yaw[sb_k], (C, len(sb_k))),
                                     a_yaw[sl][:, ac_k]], axis=1)
                bh = np.concatenate([sc.sb_half[sb_k], a_half[ac_k]])
                t_box, cos_box = _ray_boxes(ob, dw, bc, by, bh)
                ts_l.append(t_box)
                cos_l.append(cos_box)
                rho_l.append(np.concatenate([sc.sb_refl[sb_k], a_refl[ac_k]]))
                id_l.append(np.concatenate([sc.sb_id0 + sb_k, a_ids[ac_k]]).astype(np.int32))
                tr_l.append(np.concatenate([sc.sb_transmit[sb_k], np.zeros(len(ac_k), bool)]))
            if len(cy_k):
                t_cy, cos_cy = _ray_cylinders(ob, dw, sc.cy_xy[cy_k], sc.cy_r[cy_k], sc.cy_z[cy_k])
                ts_l.append(t_cy)
                cos_l.append(cos_cy)
                rho_l.append(sc.cy_refl[cy_k])
                id_l.append((sc.cy_id0 + cy_k).astype(np.int32))
                tr_l.append(np.zeros(len(cy_k), bool))

            T = np.concatenate(ts_l, axis=-1)  # (C, B, K)
            COS = np.concatenate(cos_l, axis=-1)
            RHO = np.concatenate(rho_l)
            IDS = np.concatenate(id_l)
            TR = np.concatenate(tr_l)
            T = np.where((T >= spec.min_range_m) & (T <= spec.max_range_m), T, np.inf)
            t_op_all = np.where(TR, np.inf, T)
            k_op = np.argmin(t_op_all, axis=-1)
            t_op = np.take_along_axis(t_op_all, k_op[..., None], -1)[..., 0]
            t_st_all = np.where(TR & (T < t_op[..., None]), T, np.inf)
            k_st = np.argmin(t_st_all, axis=-1)
            t_st = np.take_along_axis(t_st_all, k_st[..., None], -1)[..., 0]
            has_op, has_st = np.isfinite(t_op), np.isfinite(t_st)

            i_op = _intensity(COS, RHO, k_op, t_op, np.where(has_st, 0.6, 1.0))
            i_st = _intensity(COS, RHO, k_st, t_st, 0.4)
            # echoes per ray: A = first slot, B = second slot
            if spec.dual_return:
                # mixed pixels: a beam on the silhouette of a nearer object (a neighbouring beam
                # or column hits something >= EDGE_GAP_M farther) also returns from the surface
                # behind it, found exactly as the next opaque hit along the same ray
                far = np.zeros(t_op.shape, bool)
                tn = np.where(has_op, t_op, np.inf)
                far[:-1] |= tn[1:] > tn[:-1] + EDGE_GAP_M
                far[1:] |= tn[:-1] > tn[1:] + EDGE_GAP_M
                far[:, :-1] |= tn[:, 1:] > tn[:, :-1] + EDGE_GAP_M
                far[:, 1:] |= tn[:, :-1] > tn[:, 1:] + EDGE_GAP_M
                t_bg_all = np.where(~TR & (T > t_op[..., None] + EDGE_GAP_M), T, np.inf)
                k_bg = np.argmin(t_bg_all, axis=-1)
                t_bg = np.take_along_axis(t_bg_all, k_bg[..., None], -1)[..., 0]
                edge = far & has_op & ~has_st & np.isfinite(t_bg)
                i_bg = _intensity(COS, RHO, k_bg, t_bg, 0.3)
                both = has_op & has_st
                two = both | edge
                slots = [
                    # strongest-type slot: the fence echo, or the near side of an edge
                    (has_op | has_st,
                     np.where(has_st, t_st, t_op),
                     np.where(has_st, k_st, k_op),
                     np.where(has_st, i_st, np.where(edge, 0.8 * i_op, i_op)),
                     np.where(two, 1, 3)),
                    # last slot: the surface behind the fence or behind the edge
                    (two, np.where(both, t_op, t_bg), np.where(both, k_op, k_bg),
                     np.where(both, i_op, i_bg), np.full(t_op.shape, 2)),
                ]
            else:
                st_wins = has_st & (~has_op | (i_st > i_op))
                slots = [(has_op | has_st, np.where(st_wins, t_st, t_op),
                          np.where(st_wins, k_st, k_op), np.where(st_wins, i_st, i_op),
                          np.full(t_op.shape, 1))]
            # order: column, slot, beam
            m_all = np.stack([s[0] for s in slots], axis=1)  # (C, S, B)
            sel = np.nonzero(m_all)
            cidx, sidx, bidx = sel
            tt = np.stack([s[1] for s in slots], axis=1)[sel]
            kk = np.stack([s[2] for s in slots], axis=1)[sel]
            ii = np.stack([s[3] for s in slots], axis=1)[sel]
            rt = np.stack([np.broadcast_to(s[4], t_op.shape) for s in slots], axis=1)[sel]
            out["t"].append(t_col[j0 + cidx])
            out["col"].append(j0 + cidx)
            out["ring"].append(bidx)
            out["rt"].append(rt)
            out["inten"].append(ii)
            out["oid"].append(IDS[kk])
            out["r"].append(tt)
            del sidx

        col = np.concatenate(out["col"]).astype(np.int64)
        ring = np.concatenate(out["ring"]).astype(np.int64)
        r_true = np.concatenate(out["r"])
        ce = self.cos_el[ring]
        dl_pts = np.stack([ce * np.cos(az[col]), -ce * np.sin(az[col]), self.sin_el[ring]], -1)
        world = o[col] + np.einsum("nij,nj->ni", rl[col], dl_pts) * r_true[:, None]
        r_meas = r_true + (rng.normal(0.0, noise, r_true.shape) if noise > 0 else 0.0)
        return Scan(
            frame_idx=frame_idx, stamp_ns=int(stamp),
            xyz=(dl_pts * r_meas[:, None]).astype(np.float32),
            t_ns=np.concatenate(out["t"]).astype(np.int64),
            ring=ring.astype(np.uint16), return_type=np.concatenate(out["rt"]).astype(np.uint8),
            intensity=np.concatenate(out["inten"]).astype(np.float32),
            obj_id=np.concatenate(out["oid"]).astype(np.int32), world=world,
        )


def _intensity(cos: np.ndarray, rho: np.ndarray, k: np.ndarray, t: np.ndarray,
               scale: float | np.ndarray) -> np.ndarray:
    cosv = np.take_along_axis(cos, k[..., None], -1)[..., 0]
    val = 255.0 * rho[k] * scale * cosv / (1.0 + (t / 80.0) ** 2)
    return np.clip(np.nan_to_num(val, posinf=0.0), 1.0, 255.0)


def _ray_boxes(o: np.ndarray, d: np.ndarray, c: np.ndarray, yaw: np.ndarray,
               half: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Slab test. o (C,3), d (C,B,3), c (C,K,3), yaw (C,K), half (K,3) -> t, |cos| (C,B,K)."""
    cy, sy = np.cos(yaw)[:, None, :], np.sin(yaw)[:, None, :]
    delta = o[:, None, :] - c  # (C, K, 3)
    lx = cy[:, 0] * delta[..., 0] + sy[:, 0] * delta[..., 1]
    ly = -sy[:, 0] * delta[..., 0] + cy[:, 0] * delta[..., 1]
    lz = delta[..., 2]
    dx, dy, dz = d[..., 0:1], d[..., 1:2], d[..., 2:3]
    ddx = cy * dx + sy * dy
    ddy = -sy * dx + cy * dy
    ddz = np.broadcast_to(dz, ddx.shape)
    t_near = np.full(ddx.shape, -np.inf)
    t_far = np.full(ddx.shape, np.inf)
    cos_n = np.zeros(ddx.shape)
    with np.errstate(divide="ignore", invalid="ignore"):
        for lo, dd, h in ((lx, ddx, half[:, 0]), (ly, ddy, half[:, 1]), (lz, ddz, half[:, 2])):
            inv = 1.0 / np.where(np.abs(dd) < 1e-12, 1e-12, dd)
            t1 = (-h - lo[:, None, :]) * inv
            t2 = (h - lo[:, None, :]) * inv
            tmin, tmax = np.minimum(t1, t2), np.maximum(t1, t2)
            upd = tmin > t_near
            t_near = np.where(upd, tmin, t_near)
            cos_n = np.where(upd, np.abs(dd), cos_n)
            t_far = np.minimum(t_far, tmax)
    hit = (t_near <= t_far) & (t_near > 0)
    return np.where(hit, t_near, np.inf), cos_n


def _ray_cylinders(o: np.ndarray, d: np.ndarray, xy: np.ndarray, r: np.ndarray,
                   z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertical cylinders, side surface only. -> t, |cos| (C, B, M)."""
    ox = o[:, None, None, 0] - xy[None, None, :, 0]  # (C,1,M)
    oy = o[:, None, None, 1] - xy[None, None, :, 1]
    dx, dy = d[..., 0:1], d[..., 1:2]
    a = dx * dx + dy * dy
    b = 2 * (ox * dx + oy * dy)
    cc = ox * ox + oy * oy - r * r
    disc = b * b - 4 * a * cc
    with np.errstate(invalid="ignore", divide="ignore"):
        t = (-b - np.sqrt(disc)) / (2 * a)
    zh = o[:, None, None, 2] + t * d[..., 2:3]
    ok = (disc >= 0) & (t > 0) & (zh >= z[:, 0]) & (zh <= z[:, 1])
    t = np.where(ok, t, np.inf)
    nx = (ox + t * dx) / r
    ny = (oy + t * dy) / r
    with np.errstate(invalid="ignore"):
        cosv = np.abs(nx * dx + ny * dy)
    return t, np.nan_to_num(cosv)
