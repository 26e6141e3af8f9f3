"""GICP that computes only what it uses: a spread sample of the source, and surfaces only
where correspondences land.

Why: on a pair of 240k-point scans (29k voxel centroids each at 0.3 m) small_gicp spent
most of its time before the first iteration: a 10-nearest-neighbour search and a covariance
for every point of both clouds (60 % of a pair), then one more nearest-neighbour pass over
every source point for the quality check. GICP needs neither. Its accuracy comes from the
fine voxels (a coarse voxel's centroid on a pole or a car body depends on the side it was
seen from, which biased the relative pose by 2 cm along a street), not from using every
fine centroid: the source's constraints repeat along every wall and road.

So, with an exact hash-grid neighbour search (:class:`voxel.VoxelGrid`, numba, releasing
the GIL so frame pairs run in parallel; small_gicp's k-d tree cost 6 ms to build per cloud
and held the GIL):

- **source**: one fine (``voxel_m``) centroid per ``sample_cell_m`` cell (the first one seen,
  not a coarse centroid), each with the surface of its full-resolution neighbourhood (its
  k nearest fine centroids, not the sample's);
- **target**: every fine centroid, but a covariance is computed only for the centroids that
  become some source point's nearest neighbour (a few thousand of 29k), once, and kept;
- **Gauss-Newton** on the GICP cost (Segal et al.) with plane-regularised covariances
  (eigenvalues 1e-3, 1, 1, as small_gicp sets them: ``C = I - (1 - 1e-3) n n^T``) for a
  LEFT perturbation ``exp(xi) T`` of ``T_target_source``, ``xi = [rot, trans]``, stopping as
  small_gicp does (rotation step < 0.1 deg, translation step < 1 mm). The Hessian of the last
  linearisation is the information matrix, in the convention of
  :func:`backends.gicp_information`.

The quality check (:func:`core.evaluate`) uses the same sample. The numeric kernels here are
pure functions on arrays.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

import numpy as np
from numba import njit

from v2xlake.tasks.geometry import so3_exp
from v2xlake.tasks.register.backends import PLANE_EPS
from v2xlake.tasks.register.covisible import covisible_rows, knn_surface
from v2xlake.tasks.register.voxel import (
    _BIAS,
    _GOLDEN,
    VoxelGrid,
    _pow2_at_least,
    first_per_cell,
)

# two more odd multipliers for hashing a point's three coordinates (:func:`_same_rows`)
_MIX1 = np.uint64(0xC2B2AE3D27D4EB4F)
_MIX2 = np.uint64(0x165667B19E3779F9)
_NO_REACH = np.zeros(0)  # :func:`_surfaces` keeps no k-th neighbour distances


@njit(cache=True, nogil=True)
def _shift_rows(m: np.ndarray, t: np.ndarray, sign: float) -> np.ndarray:
    """``m + t`` (``sign`` 1) or ``m - t`` (-1) of (N, 3) ``m`` and (3,) ``t``, in a new
    array: the same sums as NumPy's broadcast add or subtract (one IEEE operation per
    element), without its inner loop of three elements per row (40 us for 12k rows)."""
    out = np.empty((m.shape[0], 3))
    t0, t1, t2 = t[0], t[1], t[2]
    if sign > 0:
        for i in range(m.shape[0]):
            out[i, 0], out[i, 1], out[i, 2] = m[i, 0] + t0, m[i, 1] + t1, m[i, 2] + t2
    else:
        for i in range(m.shape[0]):
            out[i, 0], out[i, 1], out[i, 2] = m[i, 0] - t0, m[i, 1] - t1, m[i, 2] - t2
    return out


def _moved(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    """``p @ T[:3, :3].T + T[:3, 3]``, the same bits (the product as it was, the add by
    :func:`_shift_rows`)."""
    return _shift_rows(p @ T[:3, :3].T, T[:3, 3], 1.0)


@njit(cache=True, nogil=True)
def _unknown(rows: np.ndarray, known: np.ndarray) -> np.ndarray:
    """The rows of ``rows`` not ``known``, sorted and unique (as ``np.unique`` gives them),
    in one pass and a sort of those found."""
    seen = np.zeros(len(known), dtype=np.bool_)
    out = np.empty(len(rows), dtype=np.int64)
    n = 0
    for r in rows:
        if not known[r] and not seen[r]:
            seen[r] = True
            out[n] = r
            n += 1
    return np.sort(out[:n])


@njit(cache=True, nogil=True)
def _surfaces(pts: np.ndarray, rows: np.ndarray, knn: np.ndarray,
              normals: np.ndarray, ratio: np.ndarray, reach: np.ndarray) -> None:
    """For each point ``rows[i]``: the unit normal of its neighbours ``knn[i]`` and the
    planarity ratio smallest / middle eigenvalue, written into ``normals`` / ``ratio`` (a
    ratio stays NaN where the neighbours are degenerate), and the squared distance of its
    last neighbour into ``reach`` (unless ``reach`` is empty)."""
    last = knn.shape[1] - 1
    keep = len(reach) > 0 and last >= 0
    for i in range(len(rows)):
        l_min, l_mid, nx, ny, nz = knn_surface(pts, knn, i)
        r = rows[i]
        normals[r, 0], normals[r, 1], normals[r, 2] = nx, ny, nz
        if l_mid > 1e-12:
            ratio[r] = l_min / l_mid
        if keep:
            j = knn[i, last]
            dx = pts[j, 0] - pts[r, 0]
            dy = pts[j, 1] - pts[r, 1]
            dz = pts[j, 2] - pts[r, 2]
            reach[r] = dx * dx + dy * dy + dz * dz


@njit(cache=True, nogil=True)
def _linearise(tp: np.ndarray, tn: np.ndarray, tr: np.ndarray, sp: np.ndarray,
               sn: np.ndarray, sr: np.ndarray, nn: np.ndarray, nn_d2: np.ndarray,
               T: np.ndarray, max_d2: float) -> tuple[np.ndarray, np.ndarray, int]:
    """GICP Hessian and gradient at ``T`` over the pairs (source i, target ``nn[i]``) within
    ``sqrt(max_d2)``. A pair's covariance is ``C_t + R C_s R^T`` (identity for a point
    without a surface: it acts point to point); scalars only, no allocation per pair.

    The residual's Jacobian ``J = [[q]x, -I]`` is written out: its zero terms are left out
    of ``W J``, ``J^T W J`` and ``J^T W r`` (``x + 0 * y`` is ``x``, ``-1 * x`` is ``-x``),
    and the sums are kept in scalars in the same order as the 3 x 6 products took them (the
    same bits on the 425 calls of one stage run). WHY: 18-25 % of the linearisation's time
    (replayed: 80-82 -> 61-63 ms for 1.44 M sample rows of seed 2's roadside unit 3 s)."""
    H = np.zeros((6, 6))
    b = np.zeros(6)
    k = 1.0 - PLANE_EPS
    used = 0
    # the Hessian's upper triangle and the gradient, summed pair by pair in scalars
    h00 = h01 = h02 = h03 = h04 = h05 = 0.0
    h11 = h12 = h13 = h14 = h15 = 0.0
    h22 = h23 = h24 = h25 = 0.0
    h33 = h34 = h35 = h44 = h45 = h55 = 0.0
    g0 = g1 = g2 = g3 = g4 = g5 = 0.0
    for i in range(len(sp)):
        j = nn[i]
        if j < 0 or not nn_d2[i] <= max_d2:
            continue
        qx = T[0, 0] * sp[i, 0] + T[0, 1] * sp[i, 1] + T[0, 2] * sp[i, 2] + T[0, 3]
        qy = T[1, 0] * sp[i, 0] + T[1, 1] * sp[i, 1] + T[1, 2] * sp[i, 2] + T[1, 3]
        qz = T[2, 0] * sp[i, 0] + T[2, 1] * sp[i, 1] + T[2, 2] * sp[i, 2] + T[2, 3]
        c00, c01, c02, c11, c12, c22 = 2.0, 0.0, 0.0, 2.0, 0.0, 2.0
        if tr[j] == tr[j]:  # NaN: no surface
            n0, n1, n2 = tn[j, 0], tn[j, 1], tn[j, 2]
            c00 -= k * n0 * n0
            c01 -= k * n0 * n1
            c02 -= k * n0 * n2
            c11 -= k * n1 * n1
            c12 -= k * n1 * n2
            c22 -= k * n2 * n2
        if sr[i] == sr[i]:
            m0, m1, m2 = sn[i, 0], sn[i, 1], sn[i, 2]
            n0 = T[0, 0] * m0 + T[0, 1] * m1 + T[0, 2] * m2
            n1 = T[1, 0] * m0 + T[1, 1] * m1 + T[1, 2] * m2
            n2 = T[2, 0] * m0 + T[2, 1] * m1 + T[2, 2] * m2
            c00 -= k * n0 * n0
            c01 -= k * n0 * n1
            c02 -= k * n0 * n2
            c11 -= k * n1 * n1
            c12 -= k * n1 * n2
            c22 -= k * n2 * n2
        i00 = c11 * c22 - c12 * c12  # inverse of the symmetric 3x3 by cofactors
        i01 = c02 * c12 - c01 * c22
        i02 = c01 * c12 - c02 * c11
        det = c00 * i00 + c01 * i01 + c02 * i02
        if not det > 1e-12:
            continue
        inv = 1.0 / det
        w00, w01, w02 = i00 * inv, i01 * inv, i02 * inv
        w11 = (c00 * c22 - c02 * c02) * inv
        w12 = (c01 * c02 - c00 * c12) * inv
        w22 = (c00 * c11 - c01 * c01) * inv
        r0, r1, r2 = tp[j, 0] - qx, tp[j, 1] - qy, tp[j, 2] - qz
        # d(residual) / d(xi) for q = exp(xi) T p: J = [[q]x, -I] = [[0, -qz, qy, -1, 0, 0],
        # [qz, 0, -qx, 0, -1, 0], [-qy, qx, 0, 0, 0, -1]]; p = the first three columns of
        # W J (its last three are -W), without the zero terms
        p00 = w01 * qz + w02 * -qy
        p01 = w00 * -qz + w02 * qx
        p02 = w00 * qy + w01 * -qx
        p10 = w11 * qz + w12 * -qy
        p11 = w01 * -qz + w12 * qx
        p12 = w01 * qy + w11 * -qx
        p20 = w12 * qz + w22 * -qy
        p21 = w02 * -qz + w22 * qx
        p22 = w02 * qy + w12 * -qx
        g0 += p00 * r0 + p10 * r1 + p20 * r2
        g1 += p01 * r0 + p11 * r1 + p21 * r2
        g2 += p02 * r0 + p12 * r1 + p22 * r2
        g3 += -w00 * r0 + -w01 * r1 + -w02 * r2
        g4 += -w01 * r0 + -w11 * r1 + -w12 * r2
        g5 += -w02 * r0 + -w12 * r1 + -w22 * r2
        h00 += qz * p10 + -qy * p20
        h01 += qz * p11 + -qy * p21
        h02 += qz * p12 + -qy * p22
        h03 += qz * -w01 + -qy * -w02
        h04 += qz * -w11 + -qy * -w12
        h05 += qz * -w12 + -qy * -w22
        h11 += -qz * p01 + qx * p21
        h12 += -qz * p02 + qx * p22
        h13 += -qz * -w00 + qx * -w02
        h14 += -qz * -w01 + qx * -w12
        h15 += -qz * -w02 + qx * -w22
        h22 += qy * p02 + -qx * p12
        h23 += qy * -w00 + -qx * -w01
        h24 += qy * -w01 + -qx * -w11
        h25 += qy * -w02 + -qx * -w12
        h33 += w00
        h34 += w01
        h35 += w02
        h44 += w11
        h45 += w12
        h55 += w22
        used += 1
    H[0, 0], H[0, 1], H[0, 2], H[0, 3], H[0, 4], H[0, 5] = h00, h01, h02, h03, h04, h05
    H[1, 1], H[1, 2], H[1, 3], H[1, 4], H[1, 5] = h11, h12, h13, h14, h15
    H[2, 2], H[2, 3], H[2, 4], H[2, 5] = h22, h23, h24, h25
    H[3, 3], H[3, 4], H[3, 5], H[4, 4], H[4, 5], H[5, 5] = h33, h34, h35, h44, h45, h55
    b[0], b[1], b[2], b[3], b[4], b[5] = g0, g1, g2, g3, g4, g5
    for a in range(6):
        for c in range(a):
            H[a, c] = H[c, a]
    return H, b, used


def spread_sample(points: np.ndarray, cell_m: float) -> np.ndarray:
    """Indices of one point per ``cell_m`` cell (the first in input order), ascending. One
    hashing pass (np.unique's sort took 1.7 ms per 28k-centroid cloud)."""
    p = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
    if len(p) == 0:
        return np.zeros(0, dtype=np.int64)
    if np.abs(p).max() / cell_m >= _BIAS - 2:
        raise ValueError("points farther than 2^20 sample cells from the origin")
    return np.asarray(first_per_cell(p, 1.0 / cell_m))


@dataclass
class Neighbours:
    """The ``k`` nearest points of a scan's points, nearest first, kept where computed
    (``known``), for a second surface store of the same scan that takes fewer neighbours.

    WHY: a reference scan registered against a near and a far agent keeps two surface
    stores (``gicp.num_neighbors`` and ``gicp.far_pair_num_neighbors``), and both pairs
    want the surfaces of the same rows in part (the strided rows that decide the target's
    co-visible fraction, every frame; the road and walls where both agents' points land):
    on the roadside unit's 3 s clip 63k of the far store's 157k rows were searched for
    both. The first ``j`` of ``k`` nearest are the ``j`` nearest, in the same order
    (:meth:`voxel.VoxelGrid.batch_knn_search`), so the far store takes them from here."""

    idx: np.ndarray  # (N, k) int64, rows valid where known
    known: np.ndarray  # (N,) bool
    k: int = 0  # columns filled (min(num_neighbors, N)); 0 until the first search
    lock: threading.Lock = field(default_factory=threading.Lock, repr=False, compare=False)

    @classmethod
    def empty(cls, n: int) -> Neighbours:
        return cls(np.zeros((n, 0), dtype=np.int64), np.zeros(n, dtype=bool))

    def take(self, rows: np.ndarray, k: int) -> np.ndarray:
        """Which of ``rows`` have their ``k`` nearest here (a boolean per row)."""
        with self.lock:
            if k > self.k:
                return np.zeros(len(rows), dtype=bool)
            return self.known[rows].copy()

    def get(self, rows: np.ndarray, k: int) -> np.ndarray:
        """The ``k`` nearest of ``rows`` (each known, ``k`` at most :attr:`k`)."""
        with self.lock:
            return np.ascontiguousarray(self.idx[rows, :k])

    def put(self, rows: np.ndarray, knn: np.ndarray) -> None:
        """Keep the ``knn`` (the nearest first) of ``rows`` when they are at least as many
        per row as those kept: more start the store afresh (the store with the most
        neighbours serves the others), fewer are not kept."""
        with self.lock:
            if knn.shape[1] < self.k:
                return
            if knn.shape[1] > self.k:
                self.k = knn.shape[1]
                self.idx = np.empty((len(self.known), self.k), dtype=np.int64)
                self.known[:] = False
            self.idx[rows] = knn
            self.known[rows] = True


@njit(cache=True, nogil=True)
def _untouched(pts: np.ndarray, rows: np.ndarray, reach: np.ndarray, changed: np.ndarray
               ) -> np.ndarray:
    """Whether no point of ``changed`` (sorted by x) lies within ``sqrt(reach[i])`` of
    ``pts[rows[i]]`` (with a margin: a point at the boundary counts as inside)."""
    out = np.ones(len(rows), dtype=np.bool_)
    cx = changed[:, 0]
    for i in range(len(rows)):
        x, y, z = pts[rows[i], 0], pts[rows[i], 1], pts[rows[i], 2]
        lim = reach[i] * (1.0 + 1e-9) + 1e-12
        r = np.sqrt(lim)
        j = np.searchsorted(cx, x - r)
        while j < len(cx) and cx[j] <= x + r:
            dx, dy, dz = changed[j, 0] - x, changed[j, 1] - y, changed[j, 2] - z
            if dx * dx + dy * dy + dz * dz <= lim:
                out[i] = False
                break
            j += 1
    return out


@njit(cache=True, nogil=True)
def _same_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """For each point of ``a`` the row of a bit-identical point of ``b`` (-1: none), by an
    open-addressing hash table of ``b``'s coordinates' bits (one pass over each). A row of
    ``b`` is given once: a repeat in ``a`` of a point already matched gets -1 (it is a point
    the old scan did not have, so it counts as changed)."""
    ab = a.view(np.uint64)
    bb = b.view(np.uint64)
    cap = _pow2_at_least(2 * len(b) + 2)
    shift = np.uint64(64 - int(np.log2(cap)))
    table = np.full(cap, -1, dtype=np.int64)
    for j in range(len(b)):
        h = np.int64(((bb[j, 0] * _GOLDEN) ^ (bb[j, 1] * _MIX1) ^ (bb[j, 2] * _MIX2)) >> shift)
        while table[h] >= 0:
            h = (h + 1) & (cap - 1)
        table[h] = j
    out = np.full(len(a), -1, dtype=np.int64)
    used = np.zeros(len(b), dtype=np.bool_)
    for i in range(len(a)):
        h = np.int64(((ab[i, 0] * _GOLDEN) ^ (ab[i, 1] * _MIX1) ^ (ab[i, 2] * _MIX2)) >> shift)
        while True:
            j = table[h]
            if j < 0:
                break
            if bb[j, 0] == ab[i, 0] and bb[j, 1] == ab[i, 1] and bb[j, 2] == ab[i, 2]:
                if not used[j]:
                    out[i] = j
                    used[j] = True
                break
            h = (h + 1) & (cap - 1)
    return out


@dataclass(frozen=True)
class Predecessor:
    """The same LiDAR's previous scan, for a scan of a stationary agent whose surfaces can
    be taken from it where they cannot differ (:meth:`Surfaces.ensure`).

    WHY: a roadside unit sees the same static scene frame after frame; on the simulated
    boulevard 99 % of its 0.3 m centroids are bit-identical from one of its prepared scans
    to the next (what moves, and the points it hides, differ), yet each scan searched the
    k nearest neighbours of all of them again. A point's surface depends only on its k
    nearest centroids: where the point is in both scans and no point that is in only one
    of them lies within its k-th neighbour's distance (``Surfaces.reach``), the points
    within that distance are the same, found in the same order (the grids visit the same
    cells, and keep the scan's order within a cell, which the unchanged points share), so
    the surface is the one computed before, to the bit."""

    surf: Surfaces  # the previous scan's store of the same number of neighbours
    row: np.ndarray  # (N,) int64: each point's row in the previous scan, -1: not there
    changed: np.ndarray  # (M, 3): the points of either scan not in the other, sorted by x

    @classmethod
    def of(cls, points: np.ndarray, old_points: np.ndarray, old: Surfaces) -> Predecessor:
        row = _same_rows(np.ascontiguousarray(points, dtype=np.float64),
                         np.ascontiguousarray(old_points, dtype=np.float64))
        gone = np.ones(len(old_points), dtype=bool)
        gone[row[row >= 0]] = False
        changed = np.concatenate([points[row < 0], old_points[gone]]).reshape(-1, 3)
        changed = np.ascontiguousarray(changed[np.argsort(changed[:, 0], kind="stable")],
                                       dtype=np.float64)
        return cls(old, row, changed)


@dataclass
class Surfaces:
    """Per point normal and planarity, computed on first use (``known``)."""

    normals: np.ndarray  # (N, 3)
    ratio: np.ndarray  # (N,) smallest / middle eigenvalue; NaN: none (or not computed)
    known: np.ndarray  # (N,) bool
    # one scan's surfaces may be filled by two threads at once (its agent's odometry GICP on
    # the register stage's pool, a cross pair on the calling thread)
    lock: threading.Lock = field(default_factory=threading.Lock, repr=False, compare=False)
    # shared by the scan's two stores (the near pairs' and the far pairs'): the store with
    # the most neighbours keeps its searches there, the other takes its first columns
    neighbours: Neighbours | None = None
    # squared distance of each known point's k-th nearest neighbour (where known)
    reach: np.ndarray | None = None
    k: int = 0  # the neighbours per surface (min(num_neighbors, N)); 0 until the first search
    # a stationary agent's previous scan (:class:`Predecessor`): surfaces taken from there
    # where they cannot differ, before any search
    pred: Predecessor | None = None

    @classmethod
    def empty(cls, n: int, neighbours: Neighbours | None = None) -> Surfaces:
        return cls(np.zeros((n, 3)), np.full(n, np.nan), np.zeros(n, dtype=bool),
                   neighbours=neighbours, reach=np.full(n, np.nan))

    def ensure(self, points: np.ndarray, tree: object, rows: np.ndarray, k: int,
               num_threads: int = 1) -> None:
        """Compute the surfaces of ``rows`` not yet known, from their ``k`` nearest points."""
        with self.lock:
            self._ensure(points, tree, rows, k, num_threads)

    def _inherit(self, points: np.ndarray, todo: np.ndarray, kk: int) -> np.ndarray:
        """Take the surfaces of ``todo`` (sorted, unknown) that cannot differ from the
        predecessor's (:class:`Predecessor`); the rows left to compute."""
        pred = self.pred
        if pred is None or self.reach is None or not len(todo):
            return todo
        old = pred.row[todo]
        with pred.surf.lock:
            src = pred.surf
            if src.k != kk or src.reach is None:
                return todo
            there = old >= 0
            there[there] = src.known[old[there]]
            rows, orow = todo[there], old[there]
            reach = src.reach[orow]
            normals, ratio = src.normals[orow], src.ratio[orow]
        if not len(rows):
            return todo
        ok = _untouched(points, rows, reach, pred.changed)
        rows = rows[ok]
        self.normals[rows] = normals[ok]
        self.ratio[rows] = ratio[ok]
        self.reach[rows] = reach[ok]
        self.known[rows] = True
        left = np.ones(len(todo), dtype=bool)
        left[np.flatnonzero(there)[ok]] = False
        return todo[left]

    def _ensure(self, points: np.ndarray, tree: object, rows: np.ndarray, k: int,
                num_threads: int) -> None:
        # sorted and unique, as np.unique gives it, without its sort (6 % of a pair's time)
        todo = _unknown(np.ascontiguousarray(rows, dtype=np.int64), self.known)
        if not len(todo):
            return
        kk = min(k, len(points))
        if self.k and self.k != kk:
            self.reach = None  # a store asked for two numbers of neighbours: none kept
        self.k = kk
        if self.pred is not None:
            todo = self._inherit(points, todo, kk)
            if not len(todo):
                return
        nb = self.neighbours
        have = nb.take(todo, kk) if nb is not None else None
        if have is not None and have.any():
            knn = np.empty((len(todo), kk), dtype=np.int64)
            knn[have] = nb.get(todo[have], kk)  # type: ignore[union-attr]
            search = todo[~have]
            if len(search):
                got, _ = tree.batch_knn_search(points[search], kk,  # type: ignore[attr-defined]
                                               num_threads=num_threads)
                knn[~have] = got
                nb.put(search, knn[~have])  # type: ignore[union-attr]
        else:
            got, _ = tree.batch_knn_search(points[todo], kk,  # type: ignore[attr-defined]
                                           num_threads=num_threads)
            knn = np.ascontiguousarray(got, dtype=np.int64)
            if nb is not None:
                nb.put(todo, knn)
        _surfaces(points, todo, knn, self.normals, self.ratio,
                  self.reach if self.reach is not None else _NO_REACH)
        self.known[todo] = True


@dataclass
class DenserSide:
    """The whole source of a pair that takes each spot's correspondence from the scan that
    sampled it more densely (``gicp.far_pair_denser_side``): its points, grid, lazily filled
    surfaces and the target LiDAR's origin in its frame (``Prepared.covisible_with``, None:
    no co-visibility test)."""

    points: np.ndarray
    tree: object
    surf: Surfaces
    covisible_with: np.ndarray | None = None


@dataclass(frozen=True)
class SparseOutcome:
    T: np.ndarray
    converged: bool
    iterations: int
    H: np.ndarray
    pairs: int
    # squared distance of each aligned point to its nearest target point (inf beyond the
    # correspondence distance) at the last linearisation, one update before ``T``
    sq_dist: np.ndarray | None = None


def align_sparse(tp: np.ndarray, t_tree: object, t_surf: Surfaces, sp: np.ndarray,
                 s_surf_n: np.ndarray, s_surf_r: np.ndarray, init: np.ndarray, *,
                 num_neighbors: int, max_correspondence_m: float, max_iterations: int,
                 num_threads: int = 1, rotation_eps_rad: float = np.radians(0.1),
                 translation_eps_m: float = 1e-3, t_covisible_with: np.ndarray | None = None,
                 denser: DenserSide | None = None) -> SparseOutcome:
    """Gauss-Newton GICP of the source sample ``sp`` (with its surfaces) onto the target
    points ``tp`` (neighbour grid ``t_tree``, lazily filled ``t_surf``) from ``init``. With
    ``t_covisible_with`` (the source LiDAR's origin in the target frame) a pair is kept only
    where the target surface is seen from that side too (:mod:`covisible`).

    With ``denser`` (the whole source) each spot's correspondences go from the sparser scan
    to the denser one: the cost keeps the source sample's points nearer the target LiDAR than
    the source LiDAR (by ``init``), and every target point nearer the source LiDAR is paired
    with its nearest source point (both surfaces, the same GICP term). WHY: far from its
    LiDAR a scan's rings are far apart; a dense point paired with the nearest centroid of a
    sparse ring sits up to half a ring spacing from it in the plane, so the sparse side's
    leaning normal (its neighbours span several rings) pulls it along the street. The
    quality figures, ``pairs`` (the sample-short decision) and the Hessian returned (the
    information matrix) stay the forward search's, every sample pair's, at the same
    linearisation: the reverse terms count the sparse side's points, fewer, which shrank the
    along-street information and, with it, what the clip solve accepts (its weak-geometry
    floor and variance factor are calibrated on the forward Hessian) without larger errors."""
    if denser is not None:
        return _align_denser(tp, t_tree, t_surf, sp, s_surf_n, s_surf_r, init, denser,
                             num_neighbors, max_correspondence_m, max_iterations,
                             num_threads, rotation_eps_rad, translation_eps_m,
                             t_covisible_with)
    T = np.array(init, dtype=np.float64, copy=True)
    H = np.zeros((6, 6))
    converged, iterations, used = False, 0, 0
    max_d2 = max_correspondence_m**2
    d2: np.ndarray | None = None
    # the lower bounds of the points without correspondence, the nearest point and its
    # margin of those with one (VoxelGrid.nearest_bounded: a point that moved less than its
    # margin keeps its nearest point without a search)
    held = _held(len(sp))
    while iterations < max_iterations:
        iterations += 1
        q = _moved(T, sp)
        nn, d2 = _matches(tp, t_tree, t_surf, q, max_correspondence_m, num_neighbors,
                          num_threads, t_covisible_with, held)
        H, b, used = _linearise(tp, t_surf.normals, t_surf.ratio, sp, s_surf_n, s_surf_r,
                                nn, d2, T, max_d2)
        step = _step(T, H, b, used, rotation_eps_rad, translation_eps_m)
        if step is None:
            break
        T, converged = step
        if converged:
            break
    return SparseOutcome(T, converged, iterations, 0.5 * (H + H.T), used, d2)


def _matches(tp: np.ndarray, t_tree: object, t_surf: Surfaces, q: np.ndarray,
             max_correspondence_m: float, num_neighbors: int, num_threads: int,
             t_covisible_with: np.ndarray | None,
             held: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None
             ) -> tuple[np.ndarray, np.ndarray]:
    """Each query's nearest target point within ``max_correspondence_m`` (:func:`_nearest`),
    with the surfaces of those found computed, and -1 where that surface is not seen from
    the source side (``t_covisible_with``)."""
    nn, d2 = _nearest(t_tree, q, max_correspondence_m, num_threads, held)
    close = np.flatnonzero(d2 <= max_correspondence_m**2)
    t_surf.ensure(tp, t_tree, nn[close], num_neighbors, num_threads)
    if t_covisible_with is not None and len(close):
        seen = covisible_rows(tp, t_surf.normals, t_surf.ratio, nn[close], t_covisible_with)
        nn[close[~seen]] = -1
    return nn, d2


def _step(T: np.ndarray, H: np.ndarray, b: np.ndarray, used: int, rotation_eps_rad: float,
          translation_eps_m: float) -> tuple[np.ndarray, bool] | None:
    """One Gauss-Newton step from ``T``: (the new T, converged); None when there is none
    (fewer than 6 pairs, a singular system)."""
    if used < 6:
        return None
    try:
        dx = np.linalg.solve(H, -b)
    except np.linalg.LinAlgError:
        return None
    return _update(T, dx), bool(np.linalg.norm(dx[:3]) < rotation_eps_rad
                                and np.linalg.norm(dx[3:]) < translation_eps_m)


def _nearest(tree: object, q: np.ndarray, max_dist_m: float, num_threads: int,
             held: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None
             ) -> tuple[np.ndarray, np.ndarray]:
    """Each query's nearest point of ``tree`` within ``max_dist_m`` (-1 / inf: none); on a
    :class:`voxel.VoxelGrid` with ``held`` (anchor, lb, hold, slack) its bounded search for
    a query set that moves a little from call to call."""
    if isinstance(tree, VoxelGrid) and held is not None:
        nn, d2 = tree.nearest_bounded(q, max_dist_m, *held)
    else:
        nn, d2 = tree.batch_nearest_neighbor_search(  # type: ignore[attr-defined]
            q, num_threads=num_threads, max_dist_m=max_dist_m)
    return np.asarray(nn, dtype=np.int64), np.asarray(d2, dtype=np.float64)


def _update(T: np.ndarray, dx: np.ndarray) -> np.ndarray:
    """``exp(dx) T`` for a Gauss-Newton step ``dx = [rot, trans]``."""
    D = np.eye(4)
    D[:3, :3] = _so3_exp1(np.asarray(dx[:3], dtype=np.float64))
    D[:3, 3] = dx[3:]
    return D @ T


def _so3_exp1(w: np.ndarray) -> np.ndarray:
    """``geometry.so3_exp`` of one rotation vector ``w`` (3,), the same bits: the same
    NumPy operations on the same (1, 1) angle, the branch taken instead of both computed
    and selected (``np.where``, under ``np.errstate``), ``K`` filled without ellipsis
    indexing."""
    th = np.linalg.norm(w, axis=-1)[..., None, None]
    if not th[0, 0] < np.inf:  # NaN or infinite: as so3_exp computes it (its warnings off)
        return so3_exp(w)
    K = np.zeros((3, 3))
    K[0, 1], K[0, 2] = -w[2], w[1]
    K[1, 0], K[1, 2] = w[2], -w[0]
    K[2, 0], K[2, 1] = -w[1], w[0]
    if th[0, 0] > 1e-8:
        a = np.sin(th) / th
        b = (1.0 - np.cos(th)) / th**2
    else:
        a = 1.0 - th**2 / 6.0
        b = 0.5 - th**2 / 24.0
    return np.eye(3) + a * K + b * (K @ K)


def _held(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Fresh (anchor, lb, hold, slack) of ``n`` queries for :meth:`VoxelGrid.nearest_bounded`."""
    return np.zeros((n, 3)), np.zeros(n), np.full(n, -1, dtype=np.int64), np.zeros(n)


def _align_denser(tp: np.ndarray, t_tree: object, t_surf: Surfaces, sp: np.ndarray,
                  s_surf_n: np.ndarray, s_surf_r: np.ndarray, init: np.ndarray,
                  denser: DenserSide, num_neighbors: int, max_correspondence_m: float,
                  max_iterations: int, num_threads: int, rotation_eps_rad: float,
                  translation_eps_m: float, t_covisible_with: np.ndarray | None
                  ) -> SparseOutcome:
    """:func:`align_sparse` with ``denser``: the sample rows nearer the target LiDAR (by
    ``init``) and the target points nearer the source LiDAR (:func:`_denser_terms`) in the
    cost. The other sample rows are searched once, at the last linearisation, for what
    stays the forward search's (the quality figures' squared distances, ``pairs``, the
    Hessian returned)."""
    T = np.array(init, dtype=np.float64, copy=True)
    H = np.zeros((6, 6))
    converged, iterations, used = False, 0, 0
    max_d2 = max_correspondence_m**2
    o = T[:3, 3].copy()  # the source LiDAR in the target frame; nearer it: 2 x.o > |o|^2
    half = float(o @ o)
    far = 2.0 * (_shift_rows(sp @ T[:3, :3].T, o, 1.0) @ o) > half  # rows nearer the source
    near = np.flatnonzero(~far)
    sp_n, sn_n, sr_n = sp[near], s_surf_n[near], s_surf_r[near]
    cand = np.flatnonzero(2.0 * (tp @ o) > half)  # target points nearer the source LiDAR
    held, r_held = _held(len(near)), _held(len(cand))
    tp_cand = tp[cand]  # gathered once, moved into the source frame in every iteration
    T_lin = T
    nn = np.zeros(0, dtype=np.int64)
    d2 = np.zeros(0)
    H_near = H
    while iterations < max_iterations:
        iterations += 1
        T_lin = T
        q = _moved(T, sp_n)
        nn, d2 = _matches(tp, t_tree, t_surf, q, max_correspondence_m, num_neighbors,
                          num_threads, t_covisible_with, held)
        H_near, b, used = _linearise(tp, t_surf.normals, t_surf.ratio, sp_n, sn_n, sr_n,
                                     nn, d2, T, max_d2)
        Hr, br, ur = _denser_terms(tp, t_tree, t_surf, cand, denser, T, num_neighbors,
                                   max_correspondence_m, num_threads, t_covisible_with,
                                   r_held, tp_cand)
        H, b, used = H_near + Hr, b + br, used + ur
        step = _step(T, H, b, used, rotation_eps_rad, translation_eps_m)
        if step is None:
            break
        T, converged = step
        if converged:
            break
    # the far rows at the last linearisation, for the forward figures
    fr = np.flatnonzero(far)
    q = _moved(T_lin, sp[fr])
    nn_f, d2_f = _matches(tp, t_tree, t_surf, q, max_correspondence_m, num_neighbors,
                          num_threads, t_covisible_with, None)
    Hf, _, _ = _linearise(tp, t_surf.normals, t_surf.ratio, sp[fr], s_surf_n[fr],
                          s_surf_r[fr], nn_f, d2_f, T_lin, max_d2)
    sq = np.empty(len(sp))
    sq[near], sq[fr] = d2, d2_f
    pairs = int(np.count_nonzero((nn >= 0) & (d2 <= max_d2))
                + np.count_nonzero((nn_f >= 0) & (d2_f <= max_d2)))
    H_info = H_near + Hf  # every sample pair's forward Hessian: the information reported
    return SparseOutcome(T, converged, iterations, 0.5 * (H_info + H_info.T), pairs, sq)


def _denser_terms(tp: np.ndarray, t_tree: object, t_surf: Surfaces, cand: np.ndarray,
                  denser: DenserSide, T: np.ndarray, num_neighbors: int,
                  max_correspondence_m: float, num_threads: int,
                  t_covisible_with: np.ndarray | None,
                  held: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
                  tp_cand: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """GICP terms of the target points ``tp[cand]`` (those nearer the source LiDAR; the
    caller gathers them once as ``tp_cand``), each paired with its nearest source point
    within ``max_correspondence_m`` where both surfaces are seen from the other LiDAR's side
    (:func:`align_sparse`)."""
    if not len(cand):
        return np.zeros((6, 6)), np.zeros(6), 0
    R, t = T[:3, :3], T[:3, 3]
    # in the source frame: ``(tp[cand] - t) @ R``, the subtraction by _shift_rows
    p = _shift_rows(tp_cand, t, -1.0) @ R
    s_tree = denser.tree
    k, d2 = _nearest(s_tree, p, max_correspondence_m, num_threads, held)
    close = np.flatnonzero(d2 <= max_correspondence_m ** 2)
    if not len(close):
        return np.zeros((6, 6)), np.zeros(6), 0
    ks, js = k[close], cand[close]
    denser.surf.ensure(denser.points, s_tree, ks, num_neighbors, num_threads)
    t_surf.ensure(tp, t_tree, js, num_neighbors, num_threads)
    ok = np.ones(len(close), dtype=bool)
    if denser.covisible_with is not None:
        ok &= covisible_rows(denser.points, denser.surf.normals, denser.surf.ratio, ks,
                             denser.covisible_with)
    if t_covisible_with is not None:
        ok &= covisible_rows(tp, t_surf.normals, t_surf.ratio, js, t_covisible_with)
    ks, js, dd = ks[ok], js[ok], d2[close[ok]]
    return _linearise(tp, t_surf.normals, t_surf.ratio, denser.points[ks],
                      denser.surf.normals[ks], denser.surf.ratio[ks], js, dd, T,
                      max_correspondence_m ** 2)
