"""Camera rendering by projection: flat-shaded painter's algorithm, real faces, real-looking plates.

A camera is a global-shutter pinhole with plumb_bob distortion (OpenCV 5-parameter model,
the one published in its CameraInfo) triggered at ``sec * 1e9 + round(k * 1e9 / 30)`` ns; the
image is rendered from the TRUE camera pose at that instant (``T_world_ego(t) @ T_ego_cam_true``)
with every object at that instant.

Pipeline per image: sky gradient, ground plane (a near-plane-clipped 6 km quad), ground decals
(road, sidewalks, lane markings), then all boxes / poles sorted far-to-near by the distance of
their closest point to the camera, each drawn with back-face culling (``cv2.fillConvexPoly``
on near-plane-clipped faces, subpixel shift 4) followed by its decals: licence plates on the
vehicles' rear/front faces and a camera-facing face sprite on pedestrians / the cyclist, both
warped by the true homography (``cv2.warpPerspective``). A distorted camera is rendered on a
larger pinhole canvas and remapped (map precomputed once on an 8 px grid, upsampled).

Truth: two label images are drawn alongside the colour with the SAME painter's order and
the same polygons (object id of whatever is on top, and part id of faces / plates); EVERY fill
writes both, so an occluder (vehicle body, building, pole) also erases the face / plate ids
below it (before this fix the part image was only ever written by faces / plates, so a plate or
face covered by a nearer car kept its ids and was reported visible). The visible 2D box of
every object, face and plate is the bounding box of its pixels in the final label image
(``x0 <= x < x1``, ``y0 <= y < y1`` in pixels of the distorted output image) with
``n_pixels`` its pixel count there, plus the amodal box (all projected, near-clipped vertices,
clipped to the image). ``visible_fraction`` = pixels still showing the item in the final canvas
/ pixels it covered right after it was drawn (its unoccluded footprint), both counted on the
part of the pinhole canvas that lands inside the output image; ``occluded`` is true when
``n_pixels < MIN_VISIBLE_PX`` or ``visible_fraction`` is below ``OCCLUDED_BELOW[kind]`` (0.5 for
faces / plates, 0.1 for objects). Items with no visible pixel at all get no row.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from v2xlake.tasks.geometry import compose, rigid
from v2xlake.tasks.simulate.rig import CameraRig
from v2xlake.tasks.simulate.scene import GROUND_ID, Actor, World
from v2xlake.tasks.simulate.textures import FACE_M, PLATE_MM, face_textures, plate_texture

NEAR = 0.1
MIN_VISIBLE_PX = 4
OCCLUDED_BELOW = {"face": 0.5, "plate": 0.5, "object": 0.1}
_SHIFT = 4
_LIGHT = np.array([0.35, 0.45, 0.82]) / np.linalg.norm([0.35, 0.45, 0.82])
# box faces as corner indices (corners ordered by the bits x: 1, y: 2, z: 4), outward normal
_FACES = (
    ((1, 3, 7, 5), (1, 0, 0)), ((0, 4, 6, 2), (-1, 0, 0)), ((2, 6, 7, 3), (0, 1, 0)),
    ((0, 1, 5, 4), (0, -1, 0)), ((4, 5, 7, 6), (0, 0, 1)), ((0, 2, 3, 1), (0, 0, -1)),
)
_UNIT = np.array([[(1 if i & 1 else -1), (1 if i & 2 else -1), (1 if i & 4 else -1)]
                  for i in range(8)], float)


@dataclass
class Rendered:
    image: np.ndarray  # (H, W, 3) uint8 BGR
    boxes: list[dict[str, Any]]


def _clip_near(pc: np.ndarray) -> np.ndarray:
    """Sutherland-Hodgman clip of a polygon (n, 3) in camera coords against z >= NEAR."""
    z = pc[:, 2]
    if np.all(z >= NEAR):
        return pc
    if np.all(z < NEAR):
        return pc[:0]
    out = []
    n = len(pc)
    for i in range(n):
        a, b = pc[i], pc[(i + 1) % n]
        ina, inb = a[2] >= NEAR, b[2] >= NEAR
        if ina:
            out.append(a)
        if ina != inb:
            t = (NEAR - a[2]) / (b[2] - a[2])
            out.append(a + t * (b - a))
    return np.asarray(out)


def _densify(poly: np.ndarray, n: int = 8) -> np.ndarray:
    """Points along the edges of a polygon (distortion bends straight edges)."""
    s = np.linspace(0.0, 1.0, n, endpoint=False)[:, None, None]
    nxt = np.roll(poly, -1, axis=0)
    return (poly[None] + s * (nxt - poly)[None]).reshape(-1, 3)


def _rotz(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


class CameraRenderer:
    """Renders one camera of one agent."""

    def __init__(self, world: World, agent: str, rig: CameraRig) -> None:
        self.world, self.agent, self.rig = world, agent, rig
        it = rig.intrinsics
        self.W, self.H = it.width, it.height
        self.fx, self.fy, self.cx, self.cy = it.fx, it.fy, it.cx, it.cy
        self.dist = np.asarray(it.distortion + [0.0] * (5 - len(it.distortion)), float)[:5]
        self.distorted = bool(np.any(self.dist != 0))
        self.ox = self.oy = 0.0
        self.cw, self.ch = self.W, self.H
        if self.distorted:
            step = 8
            us = np.arange(0, self.W + step, step, dtype=np.float64)
            vs = np.arange(0, self.H + step, step, dtype=np.float64)
            gu, gv = np.meshgrid(us, vs)
            pts = np.stack([gu.ravel(), gv.ravel()], -1).reshape(-1, 1, 2)
            k = np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])
            crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10)
            und = cv2.undistortPointsIter(pts, k, self.dist, None, None, crit)  # type: ignore[call-overload]
            xn = und[:, 0, 0].reshape(gu.shape)
            yn = und[:, 0, 1].reshape(gu.shape)
            cu = self.fx * xn + self.cx
            cv = self.fy * yn + self.cy
            self.ox = float(max(0.0, -np.floor(cu.min())) + 2)
            self.oy = float(max(0.0, -np.floor(cv.min())) + 2)
            self.cw = int(np.ceil(cu.max() + self.ox)) + 2
            self.ch = int(np.ceil(cv.max() + self.oy)) + 2
            mx, my = np.meshgrid(np.arange(self.W) / step, np.arange(self.H) / step)
            self.map_u = cv2.remap((cu + self.ox).astype(np.float32), mx.astype(np.float32),
                                   my.astype(np.float32), cv2.INTER_LINEAR)
            self.map_v = cv2.remap((cv + self.oy).astype(np.float32), mx.astype(np.float32),
                                   my.astype(np.float32), cv2.INTER_LINEAR)
        # canvas pixels that land inside the output image (visible-fraction denominators)
        self.valid = np.ones((self.ch, self.cw), bool)
        if self.distorted:
            gx, gy = np.meshgrid((np.arange(self.cw) + 0.5 - self.ox - self.cx) / self.fx,
                                 (np.arange(self.ch) + 0.5 - self.oy - self.cy) / self.fy)
            op = self._out_px(np.stack([gx.ravel(), gy.ravel(), np.ones(gx.size)], -1))
            self.valid = ((op[:, 0] >= 0) & (op[:, 0] < self.W) & (op[:, 1] >= 0)
                          & (op[:, 1] < self.H)).reshape(self.ch, self.cw)
        rows = np.linspace(0.0, 1.0, self.ch)[:, None]
        top, bot = np.array([200, 150, 110.0]), np.array([235, 220, 205.0])
        sky = (top * (1 - rows) + bot * rows).astype(np.uint8)
        self.sky = np.ascontiguousarray(np.broadcast_to(sky[:, None, :], (self.ch, self.cw, 3)))
        self.faces = face_textures()
        self.touched: list[int] = [self.cw, self.ch, 0, 0]
        self.foot: dict[str, tuple[tuple[slice, slice], int]] = {}

    # ---- projection helpers
    def _proj(self, pc: np.ndarray) -> np.ndarray:
        """Camera coords (n, 3), z > 0 -> canvas pixels (n, 2)."""
        return np.column_stack([self.fx * pc[:, 0] / pc[:, 2] + self.cx + self.ox,
                                self.fy * pc[:, 1] / pc[:, 2] + self.cy + self.oy])

    def _out_px(self, pc: np.ndarray) -> np.ndarray:
        """Camera coords -> pixels of the (distorted) output image."""
        x, y = pc[:, 0] / pc[:, 2], pc[:, 1] / pc[:, 2]
        k1, k2, p1, p2, k3 = self.dist
        r2 = x * x + y * y
        rad = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 ** 3
        xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return np.column_stack([self.fx * xd + self.cx, self.fy * yd + self.cy])

    def _fill(self, pts: np.ndarray, color: Any, obj: int) -> None:
        """Paint a polygon into the colour AND both label images: whatever it covers (a face,
        a plate) is no longer visible, so its part id is erased (0)."""
        p32 = np.clip(np.round(pts * (1 << _SHIFT)), -(2.0**30), 2.0**30).astype(np.int32)
        cv2.fillConvexPoly(self.img, p32, color, cv2.LINE_8, _SHIFT)
        cv2.fillConvexPoly(self.lab, p32, int(obj), cv2.LINE_8, _SHIFT)
        cv2.fillConvexPoly(self.part, p32, 0, cv2.LINE_8, _SHIFT)
        self._touch(pts)

    def _touch(self, pts: np.ndarray) -> None:
        """Grow the canvas bbox of what the current draw unit painted."""
        lo, hi = np.floor(pts.min(0)), np.ceil(pts.max(0)) + 2
        t = self.touched
        self.touched = [min(t[0], max(int(lo[0]), 0)), min(t[1], max(int(lo[1]), 0)),
                        max(t[2], min(int(hi[0]), self.cw)), max(t[3], min(int(hi[1]), self.ch))]

    def _footprint(self, key: str, src: np.ndarray, lid: int, roi: tuple[slice, slice]) -> None:
        """Record the unoccluded canvas footprint of an item right after drawing it."""
        m = (src[roi] == lid) & self.valid[roi]
        self.foot[key] = (roi, int(m.sum()))

    def _poly(self, pw: np.ndarray, color: Any, obj: int) -> np.ndarray | None:
        pc = _clip_near((pw - self.C) @ self.Rwc_T)
        if len(pc) < 3:
            return None
        self._fill(self._proj(pc), color, obj)
        return pc

    def _textured(self, pw: np.ndarray, tex: np.ndarray, obj: int, part_name: tuple[str, str]
                  ) -> list[float] | None:
        """Warp texture onto world quad (TL, TR, BR, BL). Returns amodal box or None."""
        pc = (pw - self.C) @ self.Rwc_T
        if np.any(pc[:, 2] < NEAR):
            return None
        dst = self._proj(pc)
        x0, y0 = np.floor(dst.min(0)).astype(int)
        x1, y1 = np.ceil(dst.max(0)).astype(int) + 1
        x0c, y0c, x1c, y1c = max(x0, 0), max(y0, 0), min(x1, self.cw), min(y1, self.ch)
        if x1c <= x0c or y1c <= y0c:
            return None
        th, tw = tex.shape[:2]
        src = np.array([[0, 0], [tw, 0], [tw, th], [0, th]], np.float32)
        hm = cv2.getPerspectiveTransform(src, (dst - [x0c, y0c]).astype(np.float32))
        size = (x1c - x0c, y1c - y0c)
        warped = cv2.warpPerspective(tex, hm, size, flags=cv2.INTER_AREA if
                                     (x1 - x0) < tw / 2 else cv2.INTER_LINEAR)
        mask = cv2.warpPerspective(np.full((th, tw), 255, np.uint8), hm, size,
                                   flags=cv2.INTER_NEAREST) > 127
        self.parts.append(part_name)
        pid = len(self.parts)
        roi = (slice(y0c, y1c), slice(x0c, x1c))
        self.img[roi][mask] = warped[mask]
        self.lab[roi][mask] = obj
        self.part[roi][mask] = pid
        self._touch(np.array([[x0c, y0c], [x1c - 1, y1c - 1]], float))
        self._footprint(f"{part_name[0]}:{part_name[1]}", self.part, pid, roi)
        op = self._out_px(_densify(pc) if self.distorted else pc)
        return [float(op[:, 0].min()), float(op[:, 1].min()), float(op[:, 0].max()),
                float(op[:, 1].max())]

    # ---- scene pieces
    def render(self, tau: float, actor_poses: tuple[np.ndarray, np.ndarray] | None = None
               ) -> Rendered:
        """Render at ``tau`` (s since the first PPS); ``actor_poses`` may be shared across
        cameras of the same instant (``scene.actor_poses(tau)``)."""
        w = self.world
        sc = w.scene
        p, r = w.agents[self.agent].pose(np.array([tau]))
        T = compose(rigid(r[0], p[0]), self.rig.T_ego_cam_true)
        self.C = T[:3, 3]
        self.Rwc_T = T[:3, :3]  # row vectors: pc = (pw - C) @ R_world_cam
        self.img = self.sky.copy()
        self.lab = np.zeros((self.ch, self.cw), np.uint16)
        self.part = np.zeros((self.ch, self.cw), np.uint16)
        self.parts: list[tuple[str, str]] = []
        self.foot = {}
        self.touched = [self.cw, self.ch, 0, 0]
        gz = sc.ground_z
        g = np.array([[-3000, -3000], [3000, -3000], [3000, 3000], [-3000, 3000]], float)
        self._poly(np.column_stack([g + self.C[:2], np.full(4, gz)]), sc.ground_color, GROUND_ID)
        dcent = sc.decals.mean(axis=1)
        near = np.flatnonzero(np.linalg.norm(dcent[:, :2] - self.C[:2], axis=1) < 160)
        dc = (sc.decals[near] - self.C) @ self.Rwc_T  # (K, 4, 3)
        dz = dc[..., 2]
        vis = np.any(dz > NEAR, axis=1)
        allin = np.all(dz >= NEAR, axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            du = self.fx * dc[..., 0] / dz + self.cx + self.ox
            dv = self.fy * dc[..., 1] / dz + self.cy + self.oy
        outside = allin & ((du.max(1) < 0) | (du.min(1) > self.cw) | (dv.max(1) < 0)
                           | (dv.min(1) > self.ch))
        dpix = np.stack([du, dv], -1)
        for j in np.flatnonzero(vis & ~outside):
            colr = tuple(int(c) for c in sc.decal_color[near[j]])
            if allin[j]:
                self._fill(dpix[j], colr, GROUND_ID)
            else:
                q = _clip_near(dc[j])
                if len(q) >= 3:
                    self._fill(self._proj(q), colr, GROUND_ID)

        ac, ay = actor_poses if actor_poses is not None else sc.actor_poses(tau)
        # every box to draw: center, yaw, half, color, object id, group (draw unit)
        cen: list[np.ndarray] = [sc.sb_center]
        yaw: list[np.ndarray] = [sc.sb_yaw]
        half: list[np.ndarray] = [sc.sb_half]
        col: list[np.ndarray] = [sc.sb_color.astype(float)]
        oid: list[np.ndarray] = [sc.sb_id0 + np.arange(len(sc.sb_name))]
        grp: list[np.ndarray] = [np.arange(len(sc.sb_name))]
        ng = len(sc.sb_name)
        # poles: square posts turned towards the camera
        n_cy = len(sc.cy_name)
        cz = sc.cy_z.mean(axis=1)
        cen.append(np.column_stack([sc.cy_xy, cz]))
        yaw.append(np.arctan2(self.C[1] - sc.cy_xy[:, 1], self.C[0] - sc.cy_xy[:, 0]))
        half.append(np.column_stack([sc.cy_r, sc.cy_r, 0.5 * (sc.cy_z[:, 1] - sc.cy_z[:, 0])]))
        col.append(sc.cy_color.astype(float))
        oid.append(sc.cy_id0 + np.arange(n_cy))
        grp.append(ng + np.arange(n_cy))
        ng += n_cy
        actor_group: dict[int, int] = {}
        for k, a in enumerate(sc.actors):
            if a.agent == self.agent:
                continue
            ln, wd, ht = a.size
            c = ac[k]
            actor_group[ng] = k
            if a.face is not None:
                body_h = ht - 0.26
                cen += [(c + np.array([0, 0, -ht / 2 + body_h / 2]))[None],
                        (c + np.array([0, 0, ht / 2 - 0.13]))[None]]
                yaw.append(np.full(2, ay[k]))
                half.append(np.array([[ln / 2, wd / 2, body_h / 2], [0.1, 0.1, 0.13]]))
                col.append(np.array([a.color, (120, 150, 190)], float))
                oid.append(np.full(2, sc.actor_id(k)))
                grp.append(np.full(2, ng))
            else:
                cen.append(c[None])
                yaw.append(np.array([ay[k]]))
                half.append(np.array([[ln / 2, wd / 2, ht / 2]]))
                col.append(np.array([a.color], float))
                oid.append(np.array([sc.actor_id(k)]))
                grp.append(np.array([ng]))
            ng += 1
        CEN, YAW, HALF = np.concatenate(cen), np.concatenate(yaw), np.concatenate(half)
        COL, OID, GRP = np.concatenate(col), np.concatenate(oid), np.concatenate(grp)
        cy, sy = np.cos(YAW), np.sin(YAW)
        rot = np.zeros((len(YAW), 3, 3))
        rot[:, 0, 0], rot[:, 0, 1], rot[:, 1, 0], rot[:, 1, 1], rot[:, 2, 2] = cy, -sy, sy, cy, 1
        local = _UNIT[None, :, :] * HALF[:, None, :]  # (N, 8, 3)
        corners = CEN[:, None, :] + np.einsum("nij,nkj->nki", rot, local)
        pc = (corners - self.C) @ self.Rwc_T  # (N, 8, 3)
        zc = pc[..., 2]
        loc = np.einsum("nji,nj->ni", rot, self.C - CEN)  # camera in box coords
        dist = np.linalg.norm(loc - np.clip(loc, -HALF, HALF), axis=1)
        keep = np.any(zc >= NEAR, axis=1) & (dist < 250)
        front = np.all(zc >= NEAR, axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            proj = np.stack([self.fx * pc[..., 0] / zc + self.cx + self.ox,
                             self.fy * pc[..., 1] / zc + self.cy + self.oy], -1)
        out = front & ((proj[..., 0].max(1) < 0) | (proj[..., 0].min(1) > self.cw)
                       | (proj[..., 1].max(1) < 0) | (proj[..., 1].min(1) > self.ch))
        keep &= ~out
        facing = np.stack([loc[:, 0] > HALF[:, 0], loc[:, 0] < -HALF[:, 0],
                           loc[:, 1] > HALF[:, 1], loc[:, 1] < -HALF[:, 1],
                           loc[:, 2] > HALF[:, 2], loc[:, 2] < -HALF[:, 2]], 1)
        nloc = np.array([n for _, n in _FACES], float)  # (6, 3)
        shade = 0.55 + 0.45 * np.clip(np.einsum("nij,fj->nfi", rot, nloc) @ _LIGHT, 0, None)
        # group distance = min over its boxes; draw far to near
        gdist = np.full(ng, np.inf)
        np.minimum.at(gdist, GRP[keep], dist[keep])
        order = np.argsort(-gdist[np.isfinite(gdist)], kind="stable")
        groups = np.flatnonzero(np.isfinite(gdist))[order]
        members: dict[int, list[int]] = {}
        for i_keep in np.flatnonzero(keep).tolist():
            members.setdefault(int(GRP[i_keep]), []).append(i_keep)
        amodal: dict[str, list[float]] = {}
        for g_ in (int(g) for g in groups):
            mem = members[g_]
            self.touched = [self.cw, self.ch, 0, 0]
            for i in mem:
                for f, (idx, _) in enumerate(_FACES):
                    if not facing[i, f]:
                        continue
                    colr = tuple(float(c) * shade[i, f] for c in COL[i])
                    ids = list(idx)
                    if np.all(zc[i, ids] >= NEAR):
                        self._fill(proj[i, ids], colr, int(OID[i]))
                    else:
                        q = _clip_near(pc[i, ids])
                        if len(q) >= 3:
                            self._fill(self._proj(q), colr, int(OID[i]))
            if g_ in actor_group:
                k = actor_group[g_]
                a = sc.actors[k]
                self._actor_decals(a, sc.actor_id(k), ac[k], float(ay[k]), amodal)
                tx0, ty0, tx1, ty1 = self.touched
                if tx1 > tx0 and ty1 > ty0:
                    self._footprint(f"object:{a.instance_id}", self.lab, sc.actor_id(k),
                                    (slice(ty0, ty1), slice(tx0, tx1)))
                if all(front[i] for i in mem) and not self.distorted:
                    pts = pc[mem].reshape(-1, 3)
                else:
                    pts_l = [_clip_near(pc[i, list(idx)]) for i in mem for idx, _ in _FACES]
                    pts_l = [_densify(q) if self.distorted else q for q in pts_l if len(q)]
                    pts = np.concatenate(pts_l) if pts_l else np.zeros((0, 3))
                if len(pts):
                    op = self._out_px(pts)
                    amodal[f"object:{a.instance_id}"] = [
                        float(op[:, 0].min()), float(op[:, 1].min()),
                        float(op[:, 0].max()), float(op[:, 1].max())]
        return self._finish(amodal)

    def _actor_decals(self, a: Actor, obj: int, c: np.ndarray, yaw: float,
                      amodal: dict[str, list[float]]) -> None:
        ln, _, ht = a.size
        r = _rotz(yaw)
        if a.face is not None:
            head = c + np.array([0, 0, ht / 2 - 0.13])
            to_cam = self.C[:2] - head[:2]
            dist = float(np.linalg.norm(to_cam))
            if dist > 0.3:
                u = to_cam / dist
                right = np.array([u[1], -u[0], 0.0])  # viewer's right
                fc = head + np.append(u * 0.11, 0.0)
                fw, fh = FACE_M
                up = np.array([0, 0, 1.0])
                rx, uy = right * fw / 2, up * fh / 2
                quad = np.array([fc - rx + uy, fc + rx + uy, fc + rx - uy, fc - rx - uy])
                box = self._textured(quad, self.faces[a.face], obj, ("face", a.instance_id))
                if box is not None:
                    amodal[f"face:{a.instance_id}"] = box
            return
        pw, ph = PLATE_MM[0] / 1000, PLATE_MM[1] / 1000
        zc = -ht / 2 + 0.5
        for where, text, style in a.plates:
            sx = -1.0 if where == "rear" else 1.0
            x = sx * (ln / 2 + 0.01)
            # texture left edge is on the viewer's left: +y seen from behind, -y from the front
            yl = pw / 2 * (1 if where == "rear" else -1)
            loc = np.array([[x, yl, zc + ph / 2], [x, -yl, zc + ph / 2], [x, -yl, zc - ph / 2],
                            [x, yl, zc - ph / 2]])
            quad = c + loc @ r.T
            nrm = r @ np.array([sx, 0.0, 0.0])
            if float(nrm @ (self.C - quad.mean(0))) <= 0:
                continue
            box = self._textured(quad, plate_texture(text, style), obj,
                                 ("plate", f"{a.instance_id}:{where}"))
            if box is not None:
                amodal[f"plate:{a.instance_id}:{where}"] = box

    def _finish(self, amodal: dict[str, list[float]]) -> Rendered:
        if self.distorted:
            img = cv2.remap(self.img, self.map_u, self.map_v, cv2.INTER_LINEAR)
            lab = cv2.remap(self.lab, self.map_u, self.map_v, cv2.INTER_NEAREST)
            part = cv2.remap(self.part, self.map_u, self.map_v, cv2.INTER_NEAREST)
        else:
            img, lab, part = self.img, self.lab, self.part
        sc = self.world.scene
        part_id = {f"{kind}:{inst}": i + 1 for i, (kind, inst) in enumerate(self.parts)}
        margin = 4 + (0.03 * max(self.W, self.H) if self.distorted else 0)
        boxes: list[dict[str, Any]] = []
        # visible box = pixels of the id inside its (margin-grown) amodal box: no full-image pass
        for key, am in amodal.items():
            kind, inst = key.split(":", 1)
            if kind == "object":
                src, lid, csrc = lab, sc.names.index(inst), self.lab
            else:
                src, lid, csrc = part, part_id[key], self.part
            x0 = max(int(np.floor(am[0] - margin)), 0)
            y0 = max(int(np.floor(am[1] - margin)), 0)
            x1 = min(int(np.ceil(am[2] + margin)) + 1, self.W)
            y1 = min(int(np.ceil(am[3] + margin)) + 1, self.H)
            if x1 <= x0 or y1 <= y0:
                continue
            m = src[y0:y1, x0:x1] == lid
            rows, cols = np.flatnonzero(m.any(axis=1)), np.flatnonzero(m.any(axis=0))
            if not len(rows):
                continue
            sl = (slice(y0 + int(rows[0]), y0 + int(rows[-1]) + 1),
                  slice(x0 + int(cols[0]), x0 + int(cols[-1]) + 1))
            npx = int(m.sum())
            frac = 0.0
            if key in self.foot:
                roi, full = self.foot[key]
                left = int(((csrc[roi] == lid) & self.valid[roi]).sum())
                frac = min(left / full, 1.0) if full else 0.0
            row = self._row(kind, inst, sl, npx, am)
            row["visible_fraction"] = frac
            row["occluded"] = bool(npx < MIN_VISIBLE_PX or frac < OCCLUDED_BELOW[kind])
            boxes.append(row)
        return Rendered(image=img, boxes=boxes)

    def _row(self, kind: str, inst: str, sl: tuple[slice, ...], npx: int,
             am: list[float] | None) -> dict[str, Any]:
        row: dict[str, Any] = {"kind": kind, "instance_id": inst, "x0": sl[1].start,
                               "y0": sl[0].start, "x1": sl[1].stop, "y1": sl[0].stop,
                               "n_pixels": npx}
        if am is None:
            am = [float("nan")] * 4
        row.update(ax0=max(am[0], 0.0), ay0=max(am[1], 0.0), ax1=min(am[2], float(self.W)),
                   ay1=min(am[3], float(self.H)))
        return row
