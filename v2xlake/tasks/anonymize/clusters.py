"""Object boxes from a LiDAR scan when a clip has no annotations: where vehicles and people
stand, for the guided scan plan (not a detector for any other use).

Why so simple: the anonymizer only needs to know where to look and at what scale, with a
margin; a box that is too large costs a little time, a missed object falls back on the
safety pass. So: the ground is the lowest points of each 2 m cell; what stands 0.2-4 m above
it is rasterised on a 0.2 m grid; 8-connected cells form objects; an object's footprint is
the rectangle around its points. A spinning LiDAR's points on a distant object are further apart
than the grid (at 20 m a 1° azimuth step is 0.35 m): there a car falls apart into slivers
that are too small or person-sized, and its plate gets no region (on the simulated 1080p clip
without annotations most missed plates were missed that way). So cells are also bridged
when their gap, seen from the sensor, is at most ``gap_deg`` (``_bridged``): every object of
the 0.2 m grid is kept, and every bridged group that joins several of them is an object too.
Sizes decide the class: a person is at most 1.2 m across and 1-2.2 m tall (a head on top); a
vehicle 1.2-20 m across and 0.8-4.5 m tall. A footprint's orientation is fitted to the L a
LiDAR sees of a vehicle (its near faces, ``_footprint``), not the minimum-area rectangle,
which turns an L diagonally. Far away (beyond ``dense_range_m``) a sparse LiDAR puts a few
returns on a car (4-6 on the simulator's at 25 m): fewer returns make an object there (by
range²), and an object that may be one point spacing larger on each side than its returns,
person-sized or a vehicle's face, is searched as both. A LiDAR sees a car from behind as its
rear face only (a 1.7 m x 0.5 m footprint at 40 m on the real PJLab scan), so an object
shorter than a car's length may be seen end-on: it is returned in both orientations, and the
camera-facing faces of both are searched for plates. Walls longer than 20 m are dropped. A
row of parked cars touching each other is one cluster: a long, car-high footprint is also
cut into car-length pieces (and a thin one, the rear faces of cars parked side by side, into
car widths, each seen end-on), so the plates between the row's ends are searched too. Pure
function of the points.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from v2xlake.tasks.anonymize.params import FromParams, param


@dataclass(frozen=True)
class ClusterConfig(FromParams):
    """The clustering's measured constants, and (made with ``param``) the user parameters of
    bridging gaps (params.py: ``ClusterConfig.of``)."""

    ground_cell_m: float = 2.0
    ground_percentile: float = 5.0
    min_above_m: float = 0.2
    max_above_m: float = 4.0
    grid_m: float = 0.2
    max_range_m: float = 80.0
    min_points: int = 8
    # a cell's ground no higher than its neighbours' median (``_ground_below_neighbours``)
    ground_neighbours: bool = True
    # a cell with fewer than two occupied neighbours (a lone object's own returns, the road
    # around it unseen) takes the lower quartile of the cells' ground within this (m); 0: off
    ground_isolated_m: float = param("clusters.ground_isolated_m")
    # fewer returns suffice beyond ``dense_range_m`` (by range², down to ``min_points_far``):
    # the simulator's 1.1° LiDAR puts 4-6 returns on a car's rear face at 25 m
    dense_range_m: float = param("clusters.dense_range_m")
    min_points_far: int = param("clusters.min_points_far")
    # a group's extent grown by its point spacing decides whether it can be a vehicle (a far
    # car's face is 2-3 columns wide); one that could be a person or a vehicle is both
    sparse_extent: bool = param("clusters.sparse_extent")
    # beyond ``dense_range_m`` a person whose top return is under this (m) is also given a box
    # one point spacing taller (at most ``person_h[1]``): the rings above it may have passed
    # over its head; 0: off
    sparse_person_top_m: float = param("clusters.sparse_person_top_m")
    # the footprint's orientation: L-shape fit in steps of this (0: minimum-area rectangle)
    lshape_step_deg: float = 1.0
    lshape_d0_m: float = 0.02
    lshape_max_points: int = 256
    vehicle_l: tuple[float, float] = (1.2, 20.0)  # the footprint's long side
    vehicle_w_max: float = 3.5
    vehicle_h: tuple[float, float] = (0.8, 4.5)
    full_length_m: float = 3.0  # a shorter vehicle footprint may be a car seen end-on
    person_max_wl: float = 1.2
    person_h: tuple[float, float] = (1.0, 2.2)
    # a row of touching parked cars is one cluster: a vehicle footprint longer than
    # ``row_min_m`` and no taller than ``row_max_h`` (a bus or a truck is taller) is also
    # cut into car-length pieces along its axis (``car_length_m``), each a car whose front
    # and rear faces get searched; a thin row (``row_max_w`` wide at most: the rear faces of
    # cars parked side by side, seen end-on) is cut into car widths (``car_width_m``), each
    # a car seen end-on. 0: rows are not cut
    row_min_m: float = 6.0
    row_max_h: float = 2.4
    row_max_w: float = 1.2
    car_length_m: float = 4.5
    car_width_m: float = 1.9
    # cells further apart than the grid are one object when the gap, seen from the sensor,
    # is at most this angle (a spinning LiDAR's azimuth step, with room to spare: 1024-column
    # heads 0.35°, the simulator's 1.1°); the 0.2 m grid's objects are kept too. 0: off
    gap_deg: float = param("clusters.gap_deg")
    # a bridged group is an object of its own only when no single grid object holds this
    # share of its points (else it is that object plus stragglers: searched already), and
    # when it is car-high or at most ``bridge_max_m`` long (taller and longer: facades)
    bridge_new_share: float = param("clusters.bridge_new_share")
    bridge_max_m: float = param("clusters.bridge_max_m")


def cluster_boxes(xyz: np.ndarray, cfg: ClusterConfig | None = None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Points (N, 3) in a frame with z up (the ego frame) -> boxes: centres (M, 3), sizes
    (M, 3) as (w, l, h), yaw (M,) of the length axis, category (M,) "Car" | "Pedestrian"."""
    c = cfg or ClusterConfig()
    p = np.asarray(xyz, np.float64).reshape(-1, 3)
    p = p[np.isfinite(p).all(1) & (np.hypot(p[:, 0], p[:, 1]) <= c.max_range_m)]
    empty = (np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0, "<U10"))
    if len(p) < min(c.min_points, c.min_points_far):
        return empty
    # ground: a low percentile of z per coarse cell
    gc = np.floor(p[:, :2] / c.ground_cell_m).astype(np.int64)
    key = gc[:, 0] * 1_000_003 + gc[:, 1]
    order = np.argsort(key, kind="stable")
    ks, start = np.unique(key[order], return_index=True)
    ground_of = np.empty(len(ks))
    for i, (a, b) in enumerate(zip(start, [*start[1:], len(order)], strict=True)):
        ground_of[i] = np.percentile(p[order[a:b], 2], c.ground_percentile)
    if c.ground_neighbours:
        ground_of = _ground_below_neighbours(ks, ground_of, c.ground_cell_m,
                                             c.ground_isolated_m)
    ground = ground_of[np.searchsorted(ks, key)]
    above = p[:, 2] - ground
    keep = (above >= c.min_above_m) & (above <= c.max_above_m)
    q, qg = p[keep], ground[keep]
    if len(q) < min(c.min_points, c.min_points_far):
        return empty
    cell = np.floor(q[:, :2] / c.grid_m).astype(np.int64)
    lo = cell.min(0)
    cell -= lo
    shape = cell.max(0) + 1
    occ = np.zeros(shape, bool)
    occ[cell[:, 0], cell[:, 1]] = True
    labels, n = ndimage.label(occ, structure=np.ones((3, 3), bool))
    lab = labels[cell[:, 0], cell[:, 1]]
    centres: list[tuple[float, float, float]] = []
    sizes: list[tuple[float, float, float]] = []
    yaws: list[float] = []
    cats: list[str] = []
    order = np.argsort(lab, kind="stable")
    bounds = np.searchsorted(lab[order], np.arange(1, n + 2))
    groups = [order[bounds[k] : bounds[k + 1]] for k in range(n)]
    if c.gap_deg > 0:
        groups += _bridged(cell, lab, -lo, c)
    for j, idx in enumerate(groups):
        if len(idx) < c.min_points_far or len(idx) < _min_points(q[idx], c):
            continue
        _object(q[idx], qg[idx], c, centres, sizes, yaws, cats, bridged=j >= n)
    if not centres:
        return empty
    return np.array(centres), np.array(sizes), np.array(yaws), np.array(cats)


def _object(pts: np.ndarray, qg: np.ndarray, c: ClusterConfig,
            centres: list[tuple[float, float, float]], sizes: list[tuple[float, float, float]],
            yaws: list[float], cats: list[str], bridged: bool = False) -> None:
    """One object's points (and the ground under each) -> its box(es), appended: none when
    its size fits neither a person nor a vehicle (nor, for a ``bridged`` group, when it is
    taller than a car and longer than ``bridge_max_m``); a row of touching cars also as its
    cars, a short vehicle also end-on."""
    (cx, cy), length, width, yaw = _footprint(pts[:, :2], c)
    length, width = max(length, 0.3), max(width, 0.3)
    own_length = length  # a person's, before a vehicle reading may grow it
    g = float(np.median(qg))
    h = float(pts[:, 2].max() - g)
    top_return = h  # before a class's smallest height may raise it
    # beyond ``dense_range_m`` an object is larger than its points by up to one point spacing
    # on each side and above its top return (a car's rear face at 27 m: 3 columns 0.45 m
    # apart on a 1.8 m face, its top return 1 m up, the next row over its roof)
    far = c.dense_range_m > 0 and float(np.median(np.hypot(pts[:, 0], pts[:, 1]))) \
        > c.dense_range_m
    could = length <= c.person_max_wl or (length >= c.vehicle_l[0] and h < c.vehicle_h[0])
    sp = _spacing(pts) if c.sparse_extent and far and could else 0.0
    person = (length <= c.person_max_wl and h <= c.person_h[1]
              and h + sp >= c.person_h[0])
    vehicle = (c.vehicle_l[0] <= length + (2.0 * sp if person else 0.0)
               and length <= c.vehicle_l[1] and width <= c.vehicle_w_max
               and h <= c.vehicle_h[1] and h + sp >= c.vehicle_h[0])
    if person and vehicle and (length < c.vehicle_l[0] or h < c.person_h[0]):
        # too few returns to tell: both
        hp = max(h, c.person_h[0])
        _append((cx, cy, g + hp / 2), (width, length, hp), yaw, "Pedestrian",
                centres, sizes, yaws, cats)
        length = max(length, c.vehicle_l[0])  # the smallest vehicle face, centred there
        h = max(h, c.vehicle_h[0])
        cat = "Car"
    elif person:
        h = max(h, c.person_h[0])
        cat = "Pedestrian"
    elif vehicle:
        cat = "Car"
    else:
        return
    if bridged and h > c.row_max_h and length > c.bridge_max_m:
        return
    if person and sp > 0 and top_return < c.sparse_person_top_m:
        # the measured box's head region is the top 0.5 m of its returns; at 30-50 m a
        # 32-beam head's rings are 0.6-0.8 m apart, so the face may be a ring spacing higher
        # (a walker 32 m away: top return 1.1 m up, head region 0.2-0.9 m, face at 1.5 m)
        hp = max(top_return, c.person_h[0])
        top = min(hp + sp, c.person_h[1])
        if top > hp + 0.05:
            _append((cx, cy, g + top / 2), (width, own_length, top), yaw, "Pedestrian",
                    centres, sizes, yaws, cats)
    _append((cx, cy, g + h / 2), (width, length, h), yaw, cat, centres, sizes, yaws, cats)
    if cat == "Car" and c.row_min_m > 0 and length >= c.row_min_m and h <= c.row_max_h:
        thin = width <= c.row_max_w
        piece = c.car_width_m if thin else c.car_length_m
        n_cut = max(2, round(length / piece))
        seg = length / n_cut
        axis = np.array([np.cos(yaw), np.sin(yaw)])
        normal = np.array([-axis[1], axis[0]])
        if float(normal @ (cx, cy)) < 0:
            normal = -normal  # away from the sensor (the ego frame's origin)
        for j in range(n_cut):
            ox, oy = (cx, cy) + axis * (-length / 2 + (j + 0.5) * seg)
            if thin:  # an end-on car: the row is its near face, its body behind
                depth = max(width, c.car_length_m)
                ox, oy = (ox, oy) + normal * (depth - width) / 2
                _append((ox, oy, g + h / 2), (seg, depth, h), yaw + np.pi / 2, cat,
                        centres, sizes, yaws, cats)
            else:
                _append((ox, oy, g + h / 2), (width, seg, h), yaw, cat,
                        centres, sizes, yaws, cats)
    if cat == "Car" and length < c.full_length_m:  # maybe seen end-on: both ways
        _append((cx, cy, g + h / 2), (length, width, h), yaw + np.pi / 2, cat,
                centres, sizes, yaws, cats)


def _ground_below_neighbours(ks: np.ndarray, ground: np.ndarray, cell_m: float = 2.0,
                             isolated_m: float = 0.0) -> np.ndarray:
    """Each ground cell's height, never above the median of its neighbour cells' (with two
    of them at least). Why: far away a sparse LiDAR may hit no road in a car's 2 m cell, so
    the cell's lowest returns are the car's own (a parked car 27 m away got its bumper as
    ground, and with it most of its 6-8 returns below ``min_above_m``); the road around it
    is the ground there. A slope keeps its height: its neighbours' median is its own.

    A cell with fewer than two occupied neighbours, never above the lower quartile of the
    cells' ground within ``isolated_m`` (two of them at least): a walker 32-35 m from the
    simulated LiDAR got 4 returns in two rings, alone in its cell and with no return in the
    eight around it (the road there hidden), so its lower ring was its 'ground' and it was no
    object. The quartile, not the median: within 4-5 m parked cars and walls are ground
    cells too (their lowest returns 0.5-0.7 m up)."""
    cx, cy = np.divmod(ks + 500_001, 1_000_003)  # undo key = gx * 1_000_003 + gy
    cy = cy - 500_001
    nb = np.full((len(ks), 8), np.nan)
    j = 0
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            if dx == dy == 0:
                continue
            k = (cx + dx) * 1_000_003 + (cy + dy)
            pos = np.clip(np.searchsorted(ks, k), 0, len(ks) - 1)
            hit = ks[pos] == k
            nb[hit, j] = ground[pos[hit]]
            j += 1
    n = np.isfinite(nb).sum(1)
    out = ground.copy()
    ok = n >= 2
    if ok.any():
        med = np.nanmedian(nb[ok], axis=1)
        out[ok] = np.minimum(ground[ok], med)
    lone = np.flatnonzero(~ok)
    if isolated_m > 0 and len(lone) and len(ks) > 2:
        centres = np.stack([cx, cy], 1).astype(np.float64) * cell_m
        tree = cKDTree(centres)
        for i, near in zip(lone, tree.query_ball_point(centres[lone], isolated_m), strict=True):
            others = [j for j in near if j != i]
            if len(others) >= 2:
                out[i] = min(out[i], float(np.percentile(ground[others], 25)))
    return out


def _append(centre: tuple[float, float, float], size: tuple[float, float, float], yaw: float,
            cat: str, centres: list[tuple[float, float, float]],
            sizes: list[tuple[float, float, float]], yaws: list[float], cats: list[str]) -> None:
    """One box into the four parallel lists :func:`cluster_boxes` returns as arrays."""
    centres.append(centre)
    sizes.append(size)
    yaws.append(yaw)
    cats.append(cat)


def _footprint(xy: np.ndarray, c: ClusterConfig
               ) -> tuple[tuple[float, float], float, float, float]:
    """Centre, length, width and yaw (of the length axis) of the rectangle around ``xy``.

    Why not the minimum-area rectangle: a LiDAR sees a vehicle's near faces, an L of points
    (rear and side), and the diagonal rectangle around an L has the same area as the
    upright one (a*b either way), so ``minAreaRect`` often picks the diagonal (a parked car
    seen from behind-left at 12 m: a 3.2 x 1.3 m box turned 36°, whose rear face missed the
    plate). The orientation is the one whose rectangle edges the points hug (the closeness
    criterion of L-shape fitting: the sum of 1 / distance to the nearest edge), searched in
    ``lshape_step_deg`` steps; the rectangle is then the points' extent along those axes."""
    if len(xy) > c.lshape_max_points:  # the angle search on an even subset (walls: 1000s)
        xy_fit = xy[np.linspace(0, len(xy) - 1, c.lshape_max_points).astype(np.int64)]
    else:
        xy_fit = xy
    p = xy_fit - xy_fit.mean(0)
    if len(p) < 3 or c.lshape_step_deg <= 0:
        (cx, cy), (a, b), ang = cv2.minAreaRect(xy.astype(np.float32))
        return ((cx, cy), a, b, np.radians(ang)) if a >= b else ((cx, cy), b, a,
                                                                np.radians(ang + 90))
    def best(th: np.ndarray) -> float:
        e1 = p @ np.stack([np.cos(th), np.sin(th)])  # (n, k): coordinate along each axis
        e2 = p @ np.stack([-np.sin(th), np.cos(th)])
        d1 = np.minimum(e1 - e1.min(0), e1.max(0) - e1)
        d2 = np.minimum(e2 - e2.min(0), e2.max(0) - e2)
        score = (1.0 / np.maximum(np.minimum(d1, d2), c.lshape_d0_m)).sum(0)
        return float(th[int(np.argmax(score))])

    coarse = 5.0 * c.lshape_step_deg  # coarse steps, then fine ones around the best
    t = best(np.radians(np.arange(0.0, 90.0, coarse)))
    t = best(t + np.radians(np.arange(-coarse, coarse + 1e-9, c.lshape_step_deg)))
    a1 = xy @ np.array([np.cos(t), np.sin(t)])  # every point's extent along the axes found
    a2 = xy @ np.array([-np.sin(t), np.cos(t)])
    m1, m2 = (a1.min() + a1.max()) / 2, (a2.min() + a2.max()) / 2
    centre = m1 * np.array([np.cos(t), np.sin(t)]) + m2 * np.array([-np.sin(t), np.cos(t)])
    ext1, ext2 = float(np.ptp(a1)), float(np.ptp(a2))
    if ext1 >= ext2:
        return (float(centre[0]), float(centre[1])), ext1, ext2, float(t)
    return (float(centre[0]), float(centre[1])), ext2, ext1, float(t + np.pi / 2)


def _spacing(pts: np.ndarray) -> float:
    """The median distance from each point to its nearest neighbour (the scan's spacing on
    this object); 0 for a single point."""
    if len(pts) < 2:
        return 0.0
    d, _ = cKDTree(pts).query(pts, k=2)
    return float(np.median(d[:, 1]))


def _min_points(pts: np.ndarray, c: ClusterConfig) -> int:
    """The returns an object needs to be one: ``min_points`` up to ``dense_range_m``; beyond,
    fewer by the square of the range (a spinning LiDAR's returns on a surface fall as
    1 / range²), never under ``min_points_far``."""
    r = float(np.median(np.hypot(pts[:, 0], pts[:, 1])))
    if c.dense_range_m <= 0 or r <= c.dense_range_m:
        return c.min_points
    return max(c.min_points_far, int(np.ceil(c.min_points * (c.dense_range_m / r) ** 2)))


def _bridged(cell: np.ndarray, lab: np.ndarray, origin: np.ndarray, c: ClusterConfig
             ) -> list[np.ndarray]:
    """Point indices of the groups that cells bridged across gaps of at most ``gap_deg``
    form (the gap seen from the sensor: at ``origin`` in cell units), where a group joins
    several of the 0.2 m grid's objects (a distant car whose slivers the grid kept apart)."""
    uniq, inv = np.unique(cell, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    xy = (uniq + 0.5 - origin) * c.grid_m
    rng = np.hypot(xy[:, 0], xy[:, 1])
    # two points that close lie in cells up to a cell diagonal further apart (a car's rear
    # face at 12 m, points 0.23 m apart, fell into cells 0.4 m apart: two 'pedestrians')
    tol = 1.5 * c.grid_m + rng * np.tan(np.radians(c.gap_deg))
    tree = cKDTree(xy)
    nb = tree.query_ball_point(xy, tol)
    rows = np.repeat(np.arange(len(xy)), [len(v) for v in nb])
    cols = np.fromiter((j for v in nb for j in v), np.int64, len(rows))
    n, comp = connected_components(coo_matrix((np.ones(len(rows), bool), (rows, cols)),
                                              shape=(len(xy), len(xy))), directed=False)
    pt_comp = comp[inv]
    order = np.argsort(pt_comp, kind="stable")
    bounds = np.searchsorted(pt_comp[order], np.arange(n + 1))
    out = []
    for k in range(n):
        idx = order[bounds[k] : bounds[k + 1]]
        _u, counts = np.unique(lab[idx], return_counts=True)
        if len(counts) > 1 and counts.max() < c.bridge_new_share * len(idx):
            out.append(idx)
    return out


def yaw_quat(yaw: np.ndarray) -> np.ndarray:
    """Unit quaternions (w, x, y, z) of rotations about z."""
    y = np.asarray(yaw, float) / 2
    return np.stack([np.cos(y), np.zeros_like(y), np.zeros_like(y), np.sin(y)], 1)


def track_ids(t_ns: np.ndarray, centre: np.ndarray, size: np.ndarray, yaw: np.ndarray,
              category: np.ndarray, gate_m: float, max_gap_ns: int) -> np.ndarray:
    """One track number per box of one LiDAR's scans (boxes of a scan share ``t_ns``; world
    coordinates, so the ego motion is already taken out): each scan's boxes are matched to
    the tracks alive at the previous scans (seen at most ``max_gap_ns`` ago), one to one
    (Hungarian), within ``gate_m`` of where each track's velocity puts it now, preferring its
    category; an unmatched box starts a track.

    Why: the anonymizer carries a key frame's detections to the frames between key frames
    with their region, and only a region whose (instance, part) both neighbouring key frames
    hold can carry (``carry.py``); clusters numbered per scan have no such identity, so every
    frame of a clip without annotations was detected in full. The cost adds the footprint's
    size and yaw (mod 180°) differences to the distance: a short object is returned in both
    orientations at one centre (``_object``), and each copy keeps its own track. A wrong
    match costs little: carried boxes of the two key frames must agree, or the region is
    searched again (``carry.between``)."""
    from scipy.optimize import linear_sum_assignment

    n = len(t_ns)
    out = np.full(n, -1, np.int64)
    if n == 0:
        return out
    t = np.asarray(t_ns, np.int64)
    c = np.asarray(centre, float)[:, :2]
    wl = np.sort(np.asarray(size, float)[:, :2], axis=1)
    yw = np.asarray(yaw, float)
    cat = np.asarray(category).astype(str)
    # alive tracks: last centre, velocity, time, footprint, yaw, category
    tr_c = np.zeros((0, 2))
    tr_v = np.zeros((0, 2))
    tr_t = np.zeros(0, np.int64)
    tr_wl = np.zeros((0, 2))
    tr_y = np.zeros(0)
    tr_cat = np.zeros(0, cat.dtype)
    tr_id = np.zeros(0, np.int64)
    nxt = 0
    for ts in np.unique(t):
        idx = np.flatnonzero(t == ts)
        alive = (ts - tr_t) <= max_gap_ns
        tr_c, tr_v, tr_t, tr_wl = tr_c[alive], tr_v[alive], tr_t[alive], tr_wl[alive]
        tr_y, tr_cat, tr_id = tr_y[alive], tr_cat[alive], tr_id[alive]
        dt = (ts - tr_t) * 1e-9
        pred = tr_c + tr_v * dt[:, None]
        match = np.full(len(idx), -1)
        if len(tr_id):
            d = np.hypot(*(c[idx, None, :] - pred[None, :, :]).transpose(2, 0, 1))
            dy = np.abs((yw[idx, None] - tr_y[None, :] + np.pi / 2) % np.pi - np.pi / 2)
            ds = np.abs(wl[idx, None, :] - tr_wl[None, :, :]).sum(2)
            ok = d <= gate_m
            # a sparse object's class flips between scans (person-sized slivers of a car):
            # another class costs more, but may continue the track
            cost = np.where(ok, d + ds + dy + (cat[idx, None] != tr_cat[None, :]), 1e6)
            rows, cols = linear_sum_assignment(cost)
            keep = ok[rows, cols]
            match[rows[keep]] = cols[keep]
        for k, i in enumerate(idx):
            j = match[k]
            if j >= 0:
                v = (c[i] - tr_c[j]) / max(dt[j], 1e-3)
                tr_v[j] = v if np.hypot(*tr_v[j]) == 0 else 0.5 * (v + tr_v[j])
                tr_c[j], tr_t[j], tr_wl[j], tr_y[j] = c[i], ts, wl[i], yw[i]
                out[i] = tr_id[j]
            else:
                out[i] = nxt
                tr_c = np.vstack([tr_c, c[i]])
                tr_v = np.vstack([tr_v, np.zeros(2)])
                tr_t = np.append(tr_t, ts)
                tr_wl = np.vstack([tr_wl, wl[i]])
                tr_y = np.append(tr_y, yw[i])
                tr_cat = np.append(tr_cat, cat[i])
                tr_id = np.append(tr_id, nxt)
                nxt += 1
    return out


TIE_M = 0.1  # two tracks this close to a track's best partner tie (a cluster's two copies)


def object_ids(t_ns: np.ndarray, centre: np.ndarray, track: np.ndarray, lidar: np.ndarray,
               gate_m: float) -> np.ndarray:
    """One object number per box, shared by the tracks of different LiDARs (``lidar``: each
    box's LiDAR; ``track``: its track there, ``track_ids``) that follow one object: boxes
    in one world frame (each agent's registered / INS poses), so a track of agent A's
    LiDAR and one of agent B's are one object when, at half their scan times (of either,
    where both are seen; the other's centre interpolated in time) or more, their centres
    are within ``gate_m`` and it is the nearest of the other LiDAR's tracks there (within
    ``TIE_M``: the copies of one cluster, ``_object``'s end-on one, share its centre).
    Half, not all: a track may switch to a neighbouring object (a parked car's track of
    one agent went on 3 m away for its last 4 of 10 scans), and then it is not joined
    with that object's track of the other agent unless they agree most of the time. Each
    track (with its copies) takes one partner per other LiDAR, the one agreeing at the
    most scans: joining every agreeing pair chained fragments of one agent's tracks into
    objects of 25 tracks on the simulated clip (seed 0). Tracks of one LiDAR are joined
    alone only when they held one box at a scan both saw and are within ``gate_m`` at
    half their scans: copies of one cluster, or a cluster and a bridged group or row
    piece holding it (``cluster_boxes``), whose tracks went apart where one switched
    objects; they are one object to the other agents' tracks. On the simulated two-agent
    1.0 s clip (seed 0): 265 tracks, 101 objects, 25 of them seen by both agents; at one
    scan an object's boxes lie within 3.8 m of each other at the 95th percentile (7.6 m
    at most: two cars parked close may become one object; carrying then pairs their finds
    by image distance first, ``carry.between_tracked``).

    Why: each LiDAR numbers its clusters its own way, so a plate found in a region of
    agent A's track on one key frame and of agent B's on the next was two objects to the
    carrying: never paired, no image velocity (a 64 px plate leaving the view at 90 px a
    frame went unblurred between key frames on the simulated two-agent clip). Geometry,
    not ids: the agents' ids of one object are unrelated. A track is seen at a time when
    that time lies within its first and last scan, or one of its scan intervals outside
    them (two agents' LiDARs scan out of phase)."""
    n = len(t_ns)
    out = np.arange(n, dtype=np.int64)
    if n == 0:
        return out
    t = np.asarray(t_ns, np.int64)
    xy = np.asarray(centre, float)[:, :2]
    key = np.array([f"{a}\x00{b}" for a, b in zip(np.asarray(lidar).astype(str),
                                                   np.asarray(track), strict=True)])
    names, inv = np.unique(key, return_inverse=True)
    m = len(names)
    tl: list[np.ndarray] = []
    cl: list[np.ndarray] = []
    lid = np.empty(m, dtype=object)
    for k in range(m):
        idx = np.flatnonzero(inv == k)
        idx = idx[np.argsort(t[idx], kind="stable")]
        ts, first = np.unique(t[idx], return_index=True)  # copies at one scan: one centre
        tl.append(ts)
        cl.append(xy[idx[first]])
        lid[k] = str(np.asarray(lidar)[idx[0]])
    step = np.array([float(np.median(np.diff(ts))) if len(ts) > 1 else 0.0 for ts in tl])
    lo = np.array([ts[0] for ts in tl], float) - step
    hi = np.array([ts[-1] for ts in tl], float) + step
    bmin = np.array([c.min(0) for c in cl]) - gate_m
    bmax = np.array([c.max(0) for c in cl]) + gate_m

    def at(k: int, ts: np.ndarray) -> np.ndarray:
        """Track ``k``'s centre at times ``ts`` (linear in time; its velocity at the ends
        beyond its first and last scan)."""
        tk, ck = tl[k].astype(float), cl[k]
        if len(tk) == 1:
            return np.broadcast_to(ck[0], (len(ts), 2)).copy()
        out_xy = np.stack([np.interp(ts, tk, ck[:, 0]), np.interp(ts, tk, ck[:, 1])], 1)
        v0 = (ck[1] - ck[0]) / (tk[1] - tk[0])
        v1 = (ck[-1] - ck[-2]) / (tk[-1] - tk[-2])
        early, late = ts < tk[0], ts > tk[-1]
        out_xy[early] = ck[0] + v0 * (ts[early] - tk[0])[:, None]
        out_xy[late] = ck[-1] + v1 * (ts[late] - tk[-1])[:, None]
        return out_xy

    # pairs of tracks seen at once (a sweep in order of first sight: a pair overlaps in
    # time when the later-starting one starts while the other is alive), of two LiDARs,
    # their boxes' extents within the gate: the distance at each scan time of either
    pairs: list[tuple[int, int, np.ndarray, np.ndarray]] = []
    alive: list[int] = []
    for a in np.argsort(lo, kind="stable"):
        alive = [b for b in alive if hi[b] >= lo[a]]
        for b in alive:
            if (bmin[b] > bmax[a]).any() or (bmax[b] < bmin[a]).any():
                continue
            ia = np.flatnonzero((tl[a] >= lo[b]) & (tl[a] <= hi[b]))
            ib = np.flatnonzero((tl[b] >= lo[a]) & (tl[b] <= hi[a]))
            if not len(ia) + len(ib):
                continue
            da = np.hypot(*(at(b, tl[a][ia].astype(float)) - cl[a][ia]).T)
            db = np.hypot(*(at(a, tl[b][ib].astype(float)) - cl[b][ib]).T)
            pairs.append((int(a), b, np.stack([ia, da], 1), np.stack([ib, db], 1)))
        alive.append(int(a))
    parent = np.arange(m)

    def root(k: int) -> int:
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = int(parent[k])
        return k

    # one LiDAR's tracks that held one box at a scan both saw and are within the gate at
    # half their scans or more: one cluster's copies, or a cluster and the bridged group
    # holding it, whose tracks went apart where one switched objects (a parked car's two
    # tracks of one agent: one box at 3 of 10 scans, within 1 m at 6). A track that ended
    # and one that began are not joined.
    for a, b, da, db in pairs:
        if lid[a] != lid[b]:
            continue
        both = np.isin(tl[a][da[:, 0].astype(np.int64)], tl[b])
        d_all = np.concatenate([da[:, 1], db[:, 1]])
        if (both.any() and da[both, 1].min() <= TIE_M
                and 2 * int((d_all <= gate_m).sum()) >= len(d_all)):
            parent[root(a)] = root(b)
    copy = np.array([root(k) for k in range(m)])
    cross = [(a, b, da, db) for a, b, da, db in pairs if lid[a] != lid[b]]
    # each track's nearest other-LiDAR track at each of its scans
    near = [np.full(len(ts), np.inf) for ts in tl]
    for a, b, da, db in cross:
        ia, ib = da[:, 0].astype(np.int64), db[:, 0].astype(np.int64)
        near[a][ia] = np.minimum(near[a][ia], da[:, 1])
        near[b][ib] = np.minimum(near[b][ib], db[:, 1])
    cands: list[tuple[int, float, int, int]] = []
    for a, b, da, db in cross:
        ia, ib = da[:, 0].astype(np.int64), db[:, 0].astype(np.int64)
        hit = np.concatenate([(da[:, 1] <= gate_m) & (da[:, 1] <= near[a][ia] + TIE_M),
                              (db[:, 1] <= gate_m) & (db[:, 1] <= near[b][ib] + TIE_M)])
        if 2 * int(hit.sum()) >= len(hit):
            cands.append((-int(hit.sum()), float(np.concatenate([da[:, 1], db[:, 1]]).mean()),
                          a, b))
    # one partner per other LiDAR (a copy group's), the most scans agreeing first: a chain
    # through tracks that switched objects would make one object of a whole parked row
    taken: set[tuple[int, str]] = set()
    for _n, _d, a, b in sorted(cands):
        if (copy[a], lid[b]) in taken or (copy[b], lid[a]) in taken:
            continue
        taken |= {(copy[a], lid[b]), (copy[b], lid[a])}
        parent[root(a)] = root(b)
    roots = np.array([root(k) for k in range(m)])
    return roots[inv]


def off_axis_copies(t_ns: np.ndarray, centre: np.ndarray, size: np.ndarray, yaw: np.ndarray,
                    category: np.ndarray, obj: np.ndarray, window_ns: int,
                    full_length_m: float, lidar: np.ndarray | None = None) -> np.ndarray:
    """Which boxes are the wrong one of a short cluster's two orientations (``_object``
    returns a vehicle footprint shorter than ``full_length_m`` both ways: seen end-on, its
    length axis is unknown), where the object's axis is known from another box of it: a
    vehicle box of the same object (``object_ids``: another agent's LiDAR, or a copy, row
    piece or bridged group of its own) at most ``window_ns`` away in time whose footprint
    is at least ``full_length_m`` long. Of the pair (same scan, same centre, lengths
    swapped, yaw 90° apart) the one whose length axis is further from that box's is
    marked (True); a pair without such a box keeps both.

    Why: a car that one agent's LiDAR sees end-on (its rear face, a 1.8 m x 0.5 m
    footprint) is often seen side-on by the other agent's (a 4.5 m footprint): both
    copies' camera-facing faces (two sides of the footprint) were searched for plates,
    one of them a car's side."""
    n = len(t_ns)
    drop = np.zeros(n, bool)
    if n == 0:
        return drop
    t = np.asarray(t_ns, np.int64)
    c = np.asarray(centre, float)[:, :2]
    sz = np.asarray(size, float)
    y = np.asarray(yaw, float)
    veh = np.asarray(category).astype(str) == "Car"
    ob = np.asarray(obj)
    lid = np.asarray(lidar).astype(str) if lidar is not None else np.zeros(n, str)
    length = sz[:, 1]
    short = veh & (length < full_length_m)
    long_ = veh & (length >= full_length_m)
    by_obj: dict[Any, list[int]] = {}
    for q in map(int, np.flatnonzero(long_)):
        by_obj.setdefault(ob[q], []).append(q)
    if not by_obj:
        return drop
    # the short boxes of each scan (time and LiDAR): a copy is looked for in its own scan
    # only, not over the clip's boxes (quadratic in a long clip)
    scans: dict[tuple[int, str], list[int]] = {}
    for q in map(int, np.flatnonzero(short)):
        scans.setdefault((int(t[q]), str(lid[q])), []).append(q)
    done = np.zeros(n, bool)
    for i in map(int, np.flatnonzero(short)):
        if done[i]:
            continue
        # its copy: same scan, same centre, the footprint's sides swapped
        same = np.array(scans[(int(t[i]), str(lid[i]))])
        cand = same[np.hypot(*(c[same] - c[i]).T) < 0.01]
        cand = cand[np.abs(np.abs(sz[cand, 1] - sz[i, 0]) + np.abs(sz[cand, 0] - sz[i, 1]))
                    < 0.01]
        cand = cand[cand != i]
        if not len(cand):
            continue
        j = int(cand[0])
        done[i] = done[j] = True
        ref = [k for k in by_obj.get(ob[i], []) + by_obj.get(ob[j], [])
               if abs(int(t[k]) - int(t[i])) <= window_ns]
        if not ref:
            continue
        k = min(ref, key=lambda q: abs(int(t[q]) - int(t[i])))  # the nearest in time
        # the angle between each copy's length axis and the reference's, mod 180°
        off_i, off_j = (float(np.abs((y[a] - y[k] + np.pi / 2) % np.pi - np.pi / 2))
                        for a in (i, j))
        drop[i if off_i > off_j else j] = True
    return drop
