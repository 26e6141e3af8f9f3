"""Static scene only: remove what moves from a scan before GICP (issue #13).

GICP matches surfaces; a car that moved between the instants two LiDARs swept it, or the
other agent's own body (which only one of the two scans contains), pulls the solution along
the street exactly where a street gives no other hold (walls parallel to the motion). Three
sources say what moves, each per voxel centroid with the mean capture time of its points
(``voxel_downsample_t``), so boxes are moved to the time the points were taken:

* annotated boxes of the scan (centre, size, orientation, velocity at the box's time), grown
  by a margin: a point at time ``t`` is tested against the box centred at
  ``c + v (t - t_box)``;
* the other agents' bodies: their declared footprint placed by their INS pose and velocity
  (decimetres off before registration, hence a larger margin);
* with no annotations, consistency with the static scene over neighbouring scans of the same
  agent placed by its INS (exact over a few tenths of a second): a point with no point of
  the earlier scans within ``residual_m`` and none of the later scans either is moving.
  Front and back faces of moving vehicles (the surfaces that fix a scan along the street)
  fail both; surfaces parallel to the motion may survive, and they only fix the lateral
  direction the walls already fix.

Pure functions on arrays; the lake side (which boxes, which neighbours) is in ``stage.py``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numba import njit

from v2xlake.tasks.geometry import apply, quat_to_matrix


@dataclass(frozen=True, eq=False)
class MovingBoxes:
    """Oriented boxes moving at constant velocity, in one scan's frame.

    ``half`` is (length, width, height) / 2 along the box's own x, y, z; ``R`` the box
    orientation (box -> scan frame), ``velocity`` in the scan frame (m/s), ``t_s`` the time the
    centre is valid at (seconds, on the same clock as the points' times)."""

    center: np.ndarray  # (M, 3)
    half: np.ndarray  # (M, 3)
    R: np.ndarray  # (M, 3, 3)
    velocity: np.ndarray  # (M, 3)
    t_s: np.ndarray  # (M,)
    margin: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (M,) metres, every side
    # (M,) each annotated box's own speed (m/s) as annotated, NaN where not given; None:
    # not annotated boxes (bodies), never taken for still (``without_still``)
    speed: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.center)

    @staticmethod
    def empty() -> MovingBoxes:
        return MovingBoxes(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3, 3)),
                           np.zeros((0, 3)), np.zeros(0), np.zeros(0))

    @staticmethod
    def concat(parts: list[MovingBoxes]) -> MovingBoxes:
        parts = [p for p in parts if len(p)]
        if not parts:
            return MovingBoxes.empty()
        cat = {k: np.concatenate([getattr(p, k) for p in parts]) for k in
               ("center", "half", "R", "velocity", "t_s", "margin")}
        speeds = [p.speed for p in parts if p.speed is not None]
        return MovingBoxes(**cat, speed=np.concatenate(speeds) if len(speeds) == len(parts)
                           else None)

    def take(self, rows: np.ndarray) -> MovingBoxes:
        """The boxes at ``rows`` (a mask or indices), every per-box field alike."""
        return replace(self, center=self.center[rows], half=self.half[rows], R=self.R[rows],
                       velocity=self.velocity[rows], t_s=self.t_s[rows],
                       margin=self.margin[rows] if len(self.margin) else self.margin,
                       speed=None if self.speed is None else self.speed[rows])

    def grown(self, margin_m: float) -> MovingBoxes:
        """The same boxes, each grown by ``margin_m`` on every side."""
        return replace(self, margin=np.full(len(self), float(margin_m)))


def annotation_boxes(center: np.ndarray, size_wlh: np.ndarray, quat_wxyz: np.ndarray,
                     velocity: np.ndarray, t_s: np.ndarray, margin_m: float) -> MovingBoxes:
    """Boxes as the ``annotations`` table stores them (nuScenes size order w, l, h; box x
    carries the length). A missing velocity (NaN) does not move its box over the sweep, and
    its ``speed`` is NaN, so the box is never taken for still (``without_still``)."""
    n = len(center)
    size = np.asarray(size_wlh, np.float64).reshape(n, 3)
    half = np.stack([size[:, 1], size[:, 0], size[:, 2]], axis=1) / 2.0
    q = np.asarray(quat_wxyz, np.float64).reshape(n, 4)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    v = np.asarray(velocity, np.float64).reshape(n, 3)
    return MovingBoxes(np.asarray(center, np.float64).reshape(n, 3), half, quat_to_matrix(q),
                       np.nan_to_num(v), np.asarray(t_s, np.float64).reshape(n),
                       np.full(n, float(margin_m)), np.linalg.norm(v, axis=1))



def without_still(boxes: MovingBoxes, speed_mps: float | None) -> MovingBoxes:
    """``boxes`` less those whose own annotated speed over ground is below ``speed_mps`` (a
    parked car: static scene, kept in the scan; ``static.keep_still_boxes_mps``); None: all
    of them. A box without a velocity (NaN, or no ``speed`` at all: the agents' bodies) is
    never taken for still."""
    if speed_mps is None or not len(boxes) or boxes.speed is None:
        return boxes
    return boxes.take(~(boxes.speed < speed_mps))

def body_box(T_scan_ego: np.ndarray, velocity_scan: np.ndarray, t_s: float,
             length: float, width: float, height: float, center_ego: np.ndarray,
             margin_m: float) -> MovingBoxes:
    """An agent's body (its declared footprint, box centre ``center_ego`` in its ego frame)
    placed by ``T_scan_ego`` at time ``t_s``, moving at ``velocity_scan``."""
    c = apply(T_scan_ego, np.asarray(center_ego, np.float64).reshape(1, 3))
    return MovingBoxes(c, np.array([[length, width, height]]) / 2.0, T_scan_ego[None, :3, :3],
                       np.asarray(velocity_scan, np.float64).reshape(1, 3), np.array([t_s]),
                       np.array([float(margin_m)]))


@njit(cache=True, nogil=True)
def _in_boxes_kernel(pts: np.ndarray, t: np.ndarray, center: np.ndarray, half: np.ndarray,
                     R: np.ndarray, vel: np.ndarray, tb: np.ndarray, margin: np.ndarray,
                     reach2: np.ndarray) -> np.ndarray:
    n, m = pts.shape[0], center.shape[0]
    out = np.full(n, -1, np.int64)
    for i in range(n):
        x, y, z, ti = pts[i, 0], pts[i, 1], pts[i, 2], t[i]
        for k in range(m):
            dt = ti - tb[k]
            cx = center[k, 0] + vel[k, 0] * dt
            cy = center[k, 1] + vel[k, 1] * dt
            dx, dy = x - cx, y - cy
            if dx * dx + dy * dy > reach2[k]:
                continue
            dz = z - (center[k, 2] + vel[k, 2] * dt)
            mk = margin[k]
            lx = dx * R[k, 0, 0] + dy * R[k, 1, 0] + dz * R[k, 2, 0]
            if abs(lx) > half[k, 0] + mk:
                continue
            ly = dx * R[k, 0, 1] + dy * R[k, 1, 1] + dz * R[k, 2, 1]
            if abs(ly) > half[k, 1] + mk:
                continue
            lz = dx * R[k, 0, 2] + dy * R[k, 1, 2] + dz * R[k, 2, 2]
            if abs(lz) > half[k, 2] + mk:
                continue
            out[i] = k
            break
    return out


def box_of_point(pts: np.ndarray, t_s: np.ndarray, boxes: MovingBoxes) -> np.ndarray:
    """(N,) index of the (first) grown box containing each point at its own time, -1 if
    none. O(N M) with an xy-circle reject first: M is tens, N the voxel centroids."""
    n = len(pts)
    if n == 0 or len(boxes) == 0:
        return np.full(n, -1, np.int64)
    reach = np.linalg.norm(boxes.half + boxes.margin[:, None], axis=1)
    return _in_boxes_kernel(np.ascontiguousarray(pts, np.float64),
                            np.ascontiguousarray(t_s, np.float64), boxes.center, boxes.half,
                            np.ascontiguousarray(boxes.R), boxes.velocity, boxes.t_s,
                            boxes.margin, reach * reach)


def dynamic_mask(nearest_earlier: np.ndarray | None, nearest_later: np.ndarray | None,
                 residual_m: float) -> np.ndarray:
    """Moving = farther than ``residual_m`` from every point of the earlier scans AND of the
    later scans (squared distances in, one array per side; a missing side, at the clip's
    ends, decides alone). A static surface occluded in one side's scans survives through
    the other; a moving front or back face fails both."""
    sides = [d for d in (nearest_earlier, nearest_later) if d is not None]
    if not sides:
        raise ValueError("dynamic_mask needs the neighbours of at least one side")
    r2 = residual_m * residual_m
    out = sides[0] > r2
    for d in sides[1:]:
        out &= d > r2
    return np.asarray(out)


@njit(cache=True, nogil=True)
def _above_kernel(pts: np.ndarray, cell_m: float, clearance_m: float) -> np.ndarray:
    n = pts.shape[0]
    gx = np.empty(n, np.int64)
    gy = np.empty(n, np.int64)
    for i in range(n):
        gx[i] = np.int64(np.floor(pts[i, 0] / cell_m))
        gy[i] = np.int64(np.floor(pts[i, 1] / cell_m))
    x0, y0 = gx.min(), gy.min()
    ny = gy.max() - y0 + 1
    zmin = np.full((gx.max() - x0 + 1) * ny, np.inf)
    for i in range(n):
        k = (gx[i] - x0) * ny + gy[i] - y0
        gx[i] = k
        if pts[i, 2] < zmin[k]:
            zmin[k] = pts[i, 2]
    out = np.empty(n, np.bool_)
    for i in range(n):
        out[i] = pts[i, 2] > zmin[gx[i]] + clearance_m
    return out


def above_ground(pts: np.ndarray, ground_cell_m: float = 4.0,
                 clearance_m: float = 0.3) -> np.ndarray:
    """Points more than ``clearance_m`` above the lowest point of their ``ground_cell_m``
    bird's-eye-view cell. The ground never moves, and its sparse far rings shift between
    scans by more than any residual threshold: it is left out of the moving test. (One numba
    pass: with ``np.minimum.at`` it took 3.4 ms per 25k-point scan, twice per frame pair.)"""
    if len(pts) == 0:
        return np.zeros(0, bool)
    if not np.isfinite(pts[:, :3]).all():  # the kernel's cell indices would run off its grid
        raise ValueError("above_ground: points must be finite")
    return np.asarray(_above_kernel(np.ascontiguousarray(pts, np.float64),
                                    float(ground_cell_m), float(clearance_m)))


def grow_to_objects(pts: np.ndarray, moving: np.ndarray, above: np.ndarray, cell_m: float,
                    min_fraction: float) -> np.ndarray:
    """Extend a per-point moving mask to whole objects: above-ground points are grouped into
    objects (8-connected cells of ``cell_m`` in bird's-eye view) and an object with at least
    ``min_fraction`` of its points moving moves as a whole. The per-point test alone keeps
    the surfaces of a moving car that slide along themselves (roof, sides); a whole car
    goes. Walls are one long object, mostly static, and keep the per-point decision."""
    from scipy import ndimage

    if len(pts) == 0 or not moving.any() or not above.any():
        return moving.copy()
    c = np.floor(pts[above, :2] / cell_m).astype(np.int64)
    c -= c.min(axis=0)
    shape = (int(c[:, 0].max()) + 1, int(c[:, 1].max()) + 1)
    occ = np.zeros(shape, bool)
    occ[c[:, 0], c[:, 1]] = True
    labels, nlab = ndimage.label(occ, structure=np.ones((3, 3), bool))
    lab = labels[c[:, 0], c[:, 1]]
    tot = np.bincount(lab, minlength=nlab + 1)
    mov = np.bincount(lab, weights=moving[above].astype(np.float64), minlength=nlab + 1)
    whole = mov >= min_fraction * np.maximum(tot, 1)
    whole[0] = False
    out = moving.copy()
    out[np.flatnonzero(above)[whole[lab]]] = True
    return out


@njit(cache=True, nogil=True)
def _ground_fit(pts: np.ndarray, above: np.ndarray, r_min2: float, r_max2: float,
                trim_m: float, min_points: int) -> float:
    """:func:`ground_distance`'s plane fit in one pass per refit: the 3x3 normal equations
    accumulated over the kept points (NumPy's masks, stacks and products over the scan took
    1.6 ms of the static filter's ~5 ms per scan)."""
    # the kept points' rows, in scan order: each refit sums over them alone, in the same
    # order as a pass over the whole scan would (the same sums; a fifth of the scan is ground
    # within 3-15 m)
    n = pts.shape[0]
    use = np.empty(n, np.int64)
    m = 0
    for i in range(n):
        r2 = pts[i, 0] * pts[i, 0] + pts[i, 1] * pts[i, 1]
        if not above[i] and r2 >= r_min2 and r2 <= r_max2:
            use[m] = i
            m += 1
    a = b = c = 0.0
    for _ in range(3):
        sxx = sxy = sx = syy = sy = sxz = syz = sz = 0.0
        for j in range(m):
            i = use[j]
            x, y, z = pts[i, 0], pts[i, 1], pts[i, 2]
            sxx += x * x
            sxy += x * y
            sx += x
            syy += y * y
            sy += y
            sxz += x * z
            syz += y * z
            sz += z
        if m < min_points:
            return np.nan
        # the points on one line (a wall's foot, no ground) fix no plane: their centred x-y
        # scatter is singular (to rounding: a line along an axis makes the solve raise, one
        # at any other angle solves to an arbitrary plane)
        cxx, cyy, cxy = sxx - sx * sx / m, syy - sy * sy / m, sxy - sx * sy / m
        if cxx * cyy - cxy * cxy <= 1e-9 * (cxx + cyy) ** 2:
            return np.nan
        M = np.array([[sxx, sxy, sx], [sxy, syy, sy], [sx, sy, float(m)]])
        coef = np.linalg.solve(M, np.array([sxz, syz, sz]))
        a, b, c = coef[0], coef[1], coef[2]
        k = 0
        for j in range(m):  # drop the rows farther than trim_m (NaN stays, as before)
            i = use[j]
            if not abs(pts[i, 2] - (a * pts[i, 0] + b * pts[i, 1] + c)) > trim_m:
                use[k] = i
                k += 1
        m = k
    return abs(c) / np.sqrt(a * a + b * b + 1.0)


def ground_distance(pts: np.ndarray, min_range_m: float = 3.0, max_range_m: float = 15.0,
                    trim_m: float = 0.05, min_points: int = 30) -> float:
    """Distance (m) from the sensor origin to the ground plane around it: a least-squares
    plane through the ground points (``above_ground`` false) between ``min_range_m`` and
    ``max_range_m`` horizontally, refitted twice without points farther than ``trim_m``.
    NaN when there are fewer than ``min_points`` or they fix no plane (all on one line,
    where the normal equations are singular: a wall's foot with no ground). With the
    agent's declared body (ground to roof) this is the LiDAR's height in its ego frame: the
    extrinsic's z, which driving on a plane never shows otherwise. (Normal equations, a 3x3
    solve: x and y span metres to 15 m, so they stay well conditioned where they span a
    plane at all.)"""
    if len(pts) == 0:
        return float("nan")
    p = np.ascontiguousarray(pts, np.float64)
    return float(_ground_fit(p, above_ground(p), float(min_range_m) ** 2,
                             float(max_range_m) ** 2, float(trim_m), int(min_points)))


@dataclass
class RemovalCounts:
    """What static-scene filtering took out of one scan (voxel centroids)."""

    n_in: int = 0
    boxes: int = 0
    bodies: int = 0
    dynamic: int = 0

    @property
    def removed(self) -> int:
        return self.boxes + self.bodies + self.dynamic
