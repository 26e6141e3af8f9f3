"""Voxel-grid downsampling in one pass (numba), with the range crop and NaN filter folded in.

GICP works on a voxel-downsampled cloud; small_gicp's own ``voxelgrid_sampling`` spent
~30 ms on a 240k-point scan here (NumPy -> PointCloud conversion plus a sort), this hash
accumulation does it in ~4.5 ms (one core, 2-core machine under load), which matters when
the whole pair budget is 0.05 s.
Output: the centroid of the points in each occupied voxel, in first-seen order, and with
``voxel_downsample_t`` the mean of a per-point value (the points' capture times: static-scene
filtering moves annotated boxes to each voxel's time).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import cast

import numpy as np
from numba import njit, types
from numba.extending import intrinsic

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_BIAS = 1 << 20  # 21-bit signed voxel coordinates per axis
_START_CAP = 1 << 16
# the most cells a search grid's bounding box may span (its occupancy bitmap: 4 MB of bits
# and 2 MB of ranks); a cloud spread wider is gridded with larger cells (:class:`VoxelGrid`)
_MAX_BOX_CELLS = 1 << 25


@intrinsic
def _ctpop(typingctx: object, x: types.Integer) -> tuple[object, object]:
    """Set bits of a uint64 (LLVM's ctpop: one instruction where the CPU has it)."""
    sig = types.int64(types.uint64)

    def codegen(context: object, builder: object, signature: object, args: list[object]
                ) -> object:
        return builder.zext(builder.ctpop(args[0]), context.get_value_type(  # type: ignore
            types.int64))

    return sig, codegen


_popcount = cast("Callable[[np.uint64], int]", _ctpop)  # as numba kernels call it


@njit(cache=True, nogil=True, inline="always")
def _pow2_at_least(n: int) -> int:
    """A hash table's capacity for ``n / 2`` keys (open addressing stays under half full)."""
    c = 16
    while c < n:
        c <<= 1
    return c


@njit(cache=True, nogil=True, inline="always")
def _cell_key(ix: int, iy: int, iz: int) -> int:
    """Three biased 21-bit cell coordinates packed into one int64 hash key."""
    return (ix << 42) | (iy << 21) | iz


def cell_keys(points: np.ndarray, cell_m: float) -> np.ndarray:
    """:func:`_cell_key` of every point's ``cell_m`` cell, vectorised: one int64 per point
    (for NumPy code that groups points by the hash grids' cells)."""
    c = np.floor(points / cell_m).astype(np.int64) + _BIAS
    return np.asarray((c[:, 0] << 42) | (c[:, 1] << 21) | c[:, 2])


@njit(cache=True, nogil=True, inline="always")
def _cell_of(x: float, y: float, z: float, inv_cell: float) -> tuple[int, int, int]:
    """The biased (non-negative) grid coordinates of a point."""
    return (int(np.floor(x * inv_cell)) + _BIAS, int(np.floor(y * inv_cell)) + _BIAS,
            int(np.floor(z * inv_cell)) + _BIAS)


@njit(cache=True, nogil=True)
def _voxel_kernel(xyz: np.ndarray, val: np.ndarray, inv_voxel: float, max_r2: float, cap: int
                  ) -> tuple[np.ndarray, np.ndarray, int]:
    """Centroids and value means in first-seen order and their count; count -1 (nothing
    else valid) when more than ``cap / 2`` voxels are occupied."""
    n = xyz.shape[0]
    shift = np.uint64(64 - int(np.log2(cap)))
    keys = np.full(cap, -1, dtype=np.int64)
    slot_of = np.empty(cap, dtype=np.int64)
    acc = np.zeros((cap // 2, 5))
    has_val = val.shape[0] == n
    m = 0
    lim = (1 << 21) - 1
    last_key, s = -1, 0
    for i in range(n):
        x, y, z = np.float64(xyz[i, 0]), np.float64(xyz[i, 1]), np.float64(xyz[i, 2])
        r2 = x * x + y * y + z * z
        if not (r2 < np.inf and r2 <= max_r2):  # also drops NaN and inf
            continue
        ix, iy, iz = _cell_of(x, y, z, inv_voxel)
        if ix < 0 or iy < 0 or iz < 0 or ix > lim or iy > lim or iz > lim:
            continue
        key = _cell_key(ix, iy, iz)
        if key != last_key:  # a run of returns in one voxel probes once
            h = np.int64((np.uint64(key) * _GOLDEN) >> shift)
            while True:  # open addressing, linear probing
                k = keys[h]
                if k == key:
                    s = slot_of[h]
                    break
                if k == -1:
                    if 2 * (m + 1) > cap:
                        return np.empty((0, 3)), np.empty(0), -1
                    keys[h] = key
                    s = m
                    slot_of[h] = s
                    m += 1
                    break
                h = (h + 1) & (cap - 1)
            last_key = key
        acc[s, 0] += x
        acc[s, 1] += y
        acc[s, 2] += z
        acc[s, 3] += 1.0
        if has_val:
            acc[s, 4] += val[i]
    out = np.empty((m, 3))
    mean = np.zeros(m)
    for s in range(m):
        c = 1.0 / acc[s, 3]
        out[s, 0] = acc[s, 0] * c
        out[s, 1] = acc[s, 1] * c
        out[s, 2] = acc[s, 2] * c
        mean[s] = acc[s, 4] * c
    return out, mean, m


def voxel_downsample(xyz: np.ndarray, voxel_m: float, max_range_m: float = np.inf) -> np.ndarray:
    """(M, 3) float64 voxel centroids of the finite points within ``max_range_m``."""
    return voxel_downsample_t(xyz, None, voxel_m, max_range_m)[0]


def voxel_downsample_t(xyz: np.ndarray, values: np.ndarray | None, voxel_m: float,
                       max_range_m: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
    """Voxel centroids (M, 3) of the finite points within ``max_range_m`` and the mean of
    ``values`` (N,) over each voxel's points (zeros without ``values``). Non-finite
    coordinates never reach a centroid (NaN and inf fail the range test)."""
    if voxel_m <= 0:
        raise ValueError(f"voxel size must be positive, got {voxel_m}")
    p = np.asarray(xyz)
    if p.dtype not in (np.float32, np.float64):
        p = p.astype(np.float64)
    p = np.ascontiguousarray(p).reshape(-1, 3)
    if len(p) == 0:
        return np.zeros((0, 3)), np.zeros(0)
    v = (np.zeros(0) if values is None
         else np.ascontiguousarray(np.asarray(values, dtype=np.float64).reshape(-1)))
    if values is not None and len(v) != len(p):
        raise ValueError(f"{len(v)} values for {len(p)} points")
    r2 = float(max_range_m) ** 2 if np.isfinite(max_range_m) else np.inf
    # The hash table starts at 64k entries (a 240k-point scan has ~30k voxels at 0.3 m) and
    # the pass is repeated with twice as many when more than half fill. Sized for every
    # point (2n entries, 8 MB) it missed the cache on almost every probe: 7 ms per scan
    # against 4.5 ms here.
    cap = min(_START_CAP, _pow2_at_least(2 * len(p)))
    while True:
        out, mean, m = _voxel_kernel(p, v, 1.0 / voxel_m, r2, cap)
        if m >= 0:
            return out, mean
        cap *= 2


# ------------------------------------------------------------------ neighbour searches
# A hash grid over a cloud, searched in numba without the GIL. WHY: the sparse GICP backend
# spent most of its preparation building small_gicp k-d trees (6 ms per 28k-centroid cloud
# here) and every search of small_gicp holds the GIL, so frame pairs registered on several
# threads ran one at a time. Building this grid is one hashing pass and a counting sort
# (~1 ms); the searches below are exact (the same neighbours as a k-d tree, up to ties
# between equal distances): cells are visited in shells of growing Chebyshev distance
# around the query's cell and the search stops when no unvisited cell can hold anything
# closer than what was found.
#
# A search looks its cells up in an occupancy bitmap of the cloud's bounding box with a rank
# per 64-bit word (a cell's id is the number of occupied cells before it), not in the hash
# table the build uses. WHY: two thirds of the cells a search looks up are empty (k = 10 on
# 1.6 m cells: 17.7 looked up per query, 5.8 occupied; the nearest within 1 m on 1.0 m
# cells: 12.6 and 1.6), and the hash table, sized for every point (a 17k-centroid scan's
# 2,200 cells in 64k slots, 1 MB), missed the cache on most of them; the bitmap of a scan's
# box is 10-45 kB at 1.6 m. The kernels replayed on the 922 grid calls of one run of seed 2's
# roadside unit 3 s (one core, min of 3, two rounds): k nearest 196-202 / 55 / 62-64 ->
# 166-177 / 45-49 / 51-54 ms (k = 10 / 6 / 1), GICP's held nearest (whose later shells
# now take only the cells the ball of its second nearest reaches, as the k-nearest search's
# do) 146-152 -> 115-127 ms, the builds no slower. The same neighbours in the same order:
# cells are visited in the same order, only their numbering (box order instead of first
# seen) and so the points' order in memory differ.
#
# The k-nearest search visits its first shell's cells nearest first (by their distance
# bound) and stops at the first one beyond the k-th distance: the k-th distance shrinks
# sooner, so fewer cells are scanned (replayed as above: k = 10 / 6 161-170 / 47-48 ms
# against 174-178 / 48-50 in scan order). Points at exactly the same distance then come in
# that order, which depends on the query only (so :class:`sparse.Neighbours` still takes a
# search's first columns for fewer neighbours); none such on the three 3 s boulevard clips
# (registrations the same bytes). The held nearest search gained nothing from it and keeps
# scan order.


@njit(cache=True, nogil=True, inline="always")
def _lookup(bits: np.ndarray, rank: np.ndarray, b: int) -> int:
    """Cell id of the cell at position ``b`` of the grid's bounding box (:func:`_grid_build`),
    -1 when empty: its bit, and the occupied cells before it (the word's rank plus the set
    bits below it in the word)."""
    w = b >> 6
    word = bits[w]
    sh = np.uint64(b & 63)
    if not (word >> sh) & np.uint64(1):
        return -1
    return rank[w] + _popcount(word & ((np.uint64(1) << sh) - np.uint64(1)))


@njit(cache=True, nogil=True)
def _grid_build(pts: np.ndarray, inv_cell: float) -> tuple[
        np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The occupancy bitmap of the cells of the points' bounding box (x, y, z, z fastest)
    and its ranks (occupied cells before each 64-bit word), CSR cell starts, point order by
    cell, the points in that order, and the bounding box of the occupied cells (lo, hi).
    Cells are numbered in bounding-box order (a cell's id is its rank in the bitmap); the
    points of a cell keep their input order. An empty bitmap: the box spans more than
    ``_MAX_BOX_CELLS`` cells (nothing else valid)."""
    n = pts.shape[0]
    cap = _pow2_at_least(2 * n)
    shift = np.uint64(64 - int(np.log2(cap)))
    keys = np.full(cap, -1, dtype=np.int64)
    cells = np.empty(cap, dtype=np.int64)
    cell_of = np.empty(n, dtype=np.int64)
    count = np.zeros(n + 1, dtype=np.int64)
    where = np.empty((n, 3), dtype=np.int64)  # each first-seen cell's coordinates
    lo = np.full(3, 1 << 22, dtype=np.int64)
    hi = np.full(3, -1, dtype=np.int64)
    m = 0
    last_key, s = -1, 0
    for i in range(n):
        c0, c1, c2 = _cell_of(pts[i, 0], pts[i, 1], pts[i, 2], inv_cell)
        key = _cell_key(c0, c1, c2)
        if key != last_key:  # a run of points in one cell (scan order) probes once
            h = np.int64((np.uint64(key) * _GOLDEN) >> shift)
            while True:
                k = keys[h]
                if k == key:
                    s = cells[h]
                    break
                if k == -1:
                    keys[h] = key
                    cells[h] = m
                    s = m
                    where[m, 0], where[m, 1], where[m, 2] = c0, c1, c2
                    lo[0], lo[1], lo[2] = min(lo[0], c0), min(lo[1], c1), min(lo[2], c2)
                    hi[0], hi[1], hi[2] = max(hi[0], c0), max(hi[1], c1), max(hi[2], c2)
                    m += 1
                    break
                h = (h + 1) & (cap - 1)
            last_key = key
        cell_of[i] = s
    ny, nz = hi[1] - lo[1] + 1, hi[2] - lo[2] + 1
    boxed = (hi[0] - lo[0] + 1) * ny * nz if m else 0
    if boxed > _MAX_BOX_CELLS:
        return (np.zeros(0, dtype=np.uint64), np.zeros(0, dtype=np.int32),
                np.zeros(1, dtype=np.int64), np.zeros(0, dtype=np.int64), np.empty((0, 3)),
                lo, hi)
    words = (boxed + 63) >> 6
    bits = np.zeros(words + 1, dtype=np.uint64)
    at = np.empty(m, dtype=np.int64)
    for c in range(m):
        b = ((where[c, 0] - lo[0]) * ny + (where[c, 1] - lo[1])) * nz + (where[c, 2] - lo[2])
        at[c] = b
        bits[b >> 6] |= np.uint64(1) << np.uint64(b & 63)
    rank = np.empty(words + 1, dtype=np.int32)
    r = 0
    for w in range(words + 1):
        rank[w] = r
        r += _popcount(bits[w])
    renum = np.empty(m, dtype=np.int64)  # first-seen id -> id in box order
    for c in range(m):
        renum[c] = _lookup(bits, rank, at[c])
    for i in range(n):
        s = renum[cell_of[i]]
        cell_of[i] = s
        count[s + 1] += 1
    start = np.empty(m + 1, dtype=np.int64)
    start[0] = 0
    for s in range(m):
        start[s + 1] = start[s] + count[s + 1]
    fill = start[:m].copy()
    order = np.empty(n, dtype=np.int64)
    sorted_pts = np.empty((n, 3))
    for i in range(n):  # stable: input order within a cell
        s = cell_of[i]
        j = fill[s]
        fill[s] += 1
        order[j] = i
        sorted_pts[j, 0], sorted_pts[j, 1], sorted_pts[j, 2] = pts[i, 0], pts[i, 1], pts[i, 2]
    return bits, rank, start, order, sorted_pts, lo, hi


@njit(cache=True, nogil=True, inline="always")
def _face_margin(x: float, y: float, z: float, inv_cell: float) -> float:
    """Distance (in cells) from a point to the nearest face of its own cell."""
    fx, fy, fz = x * inv_cell, y * inv_cell, z * inv_cell
    fx, fy, fz = fx - np.floor(fx), fy - np.floor(fy), fz - np.floor(fz)
    return min(fx, 1.0 - fx, fy, 1.0 - fy, fz, 1.0 - fz)


@njit(cache=True, nogil=True, inline="always")
def _cell_d2(x: float, y: float, z: float, ix: int, iy: int, iz: int, cell: float) -> float:
    """Squared distance from a point to the nearest point of cell (ix, iy, iz) (biased grid
    coordinates): a cell farther than the current k-th neighbour is not even looked up."""
    a = (ix - _BIAS) * cell
    b = (iy - _BIAS) * cell
    c = (iz - _BIAS) * cell
    dx = max(a - x, 0.0, x - a - cell)
    dy = max(b - y, 0.0, y - b - cell)
    dz = max(c - z, 0.0, z - c - cell)
    return dx * dx + dy * dy + dz * dz


@njit(cache=True, nogil=True, inline="always")
def _shell_z(ix: int, iy: int, cx: int, cy: int, cz: int, s: int, z0: int, z1: int
             ) -> tuple[int, int, int]:
    """The z range of shell ``s`` (cells at Chebyshev distance s from (cx, cy, cz)) at
    column (ix, iy), clipped to [z0, z1]: (first, last, step). On the shell's x / y faces
    the whole column belongs to it, elsewhere only its two ends."""
    if ix == cx - s or ix == cx + s or iy == cy - s or iy == cy + s:
        return z0, z1, 1
    a, b = cz - s, cz + s
    a_in, b_in = z0 <= a <= z1, z0 <= b <= z1
    if a_in and b_in:
        return a, b, max(b - a, 1)
    if a_in:
        return a, a, 1
    if b_in:
        return b, b, 1
    # neither end in range: a query above or below the cloud by more than the shell (both
    # ends then on one side; a cell outside the grid's box has no bit in the bitmap)
    return 1, 0, 1


@njit(cache=True, nogil=True, inline="always")
def _covered(cx: int, cy: int, cz: int, s: int, lo: np.ndarray, hi: np.ndarray) -> bool:
    """Whether shells 0..s cover every occupied cell."""
    return (cx - s <= lo[0] and cx + s >= hi[0] and cy - s <= lo[1] and cy + s >= hi[1]
            and cz - s <= lo[2] and cz + s >= hi[2])


@njit(cache=True, nogil=True, inline="always")
def _knn_cell(sp: np.ndarray, j0: int, j1: int, x: float, y: float, z: float,
              bd: np.ndarray, bi: np.ndarray, m: int) -> int:
    """Points ``j0:j1`` of the grid's order (one cell) into a query's sorted k-nearest list
    (``bd`` squared distances, ``bi`` positions; k = its length) whose first ``m`` entries
    are filled (the others hold the bound and -1): a point enters only when strictly closer
    than the last entry, after every entry as close as itself; returns the entries filled.

    A point entering a list that is not full starts its insertion at the first free entry:
    started at the last one, it passed the free entries (each holding the bound, which it
    is closer than) one by one, shifting them right, and came to the same place. WHY: the
    k = 10 searches shifted 91.6 entries a query, 45 of them free ones (the 284k such
    searches of one register run on seed 2's roadside unit 3 s clip); replayed (one core,
    min of 3, three interleaved pairs) they took 188-191 ms instead of 205-218 (k = 6:
    53-54 instead of 55-56), the same neighbours and distances."""
    k = bd.shape[0]
    for j in range(j0, j1):
        dx, dy, dz = sp[j, 0] - x, sp[j, 1] - y, sp[j, 2] - z
        d2 = dx * dx + dy * dy + dz * dz
        if d2 < bd[k - 1]:
            u = m if m < k else k - 1  # insertion into the sorted list
            while u > 0 and bd[u - 1] > d2:
                bd[u], bi[u] = bd[u - 1], bi[u - 1]
                u -= 1
            bd[u], bi[u] = d2, j
            if m < k:
                m += 1
    return m


@njit(cache=True, nogil=True)
def _grid_knn(bits: np.ndarray, rank: np.ndarray, start: np.ndarray, order: np.ndarray,
              sp: np.ndarray, lo: np.ndarray, hi: np.ndarray, inv_cell: float,
              q: np.ndarray, k: int, max_d2: float) -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` nearest points of each query within ``sqrt(max_d2)`` (original indices,
    squared distances, nearest first; -1 / inf where fewer lie within); k must not exceed
    the number of points. A bound ends the search early: without one, a query far from the
    cloud visits every cell in between."""
    nq = q.shape[0]
    out_i = np.full((nq, k), -1, dtype=np.int64)
    out_d = np.full((nq, k), max_d2)
    cell = 1.0 / inv_cell
    ny, nz = hi[1] - lo[1] + 1, hi[2] - lo[2] + 1
    near_d = np.empty(26)  # the first shell's cells to visit: distance bound, cell id
    near_c = np.empty(26, dtype=np.int64)
    for t in range(nq):
        x, y, z = q[t, 0], q[t, 1], q[t, 2]
        cx, cy, cz = _cell_of(x, y, z, inv_cell)
        m0 = _face_margin(x, y, z, inv_cell) * cell
        bd = out_d[t]
        bi = out_i[t]
        s = 0
        m = 0  # entries filled
        while True:
            x0, y0, z0 = max(cx - s, lo[0]), max(cy - s, lo[1]), max(cz - s, lo[2])
            x1, y1, z1 = min(cx + s, hi[0]), min(cy + s, hi[1]), min(cz + s, hi[2])
            if s > 0:
                w = bd[k - 1]
                lb = (s - 1) * cell + m0
                if lb * lb > w:  # free slots hold the bound
                    break
                if w * inv_cell * inv_cell < 1e12:
                    # only the cells the ball of the k-th distance reaches: the others would
                    # be skipped below (farther than it), in the same order (WHY: a sparse
                    # region's query reaching the next shell looped over its 98 cells)
                    r = np.sqrt(w) * (1.0 + 1e-9) + 1e-12
                    a0, a1, a2 = _cell_of(x - r, y - r, z - r, inv_cell)
                    b0, b1, b2 = _cell_of(x + r, y + r, z + r, inv_cell)
                    x0, y0, z0 = max(x0, a0), max(y0, a1), max(z0, a2)
                    x1, y1, z1 = min(x1, b0), min(y1, b1), min(z1, b2)
            if s == 1:
                # the first shell's occupied cells within the bound, visited nearest first
                # (by their distance bound, in scan order among equal bounds), until the
                # next one lies beyond the k-th distance
                nc = 0
                for ix in range(x0, x1 + 1):
                    for iy in range(y0, y1 + 1):
                        za, zb, zs = _shell_z(ix, iy, cx, cy, cz, s, z0, z1)
                        col = ((ix - lo[0]) * ny + (iy - lo[1])) * nz - lo[2]
                        for iz in range(za, zb + 1, zs):
                            cd = _cell_d2(x, y, z, ix, iy, iz, cell)
                            if cd > bd[k - 1]:
                                continue
                            c = _lookup(bits, rank, col + iz)
                            if c < 0:
                                continue
                            u = nc
                            while u > 0 and near_d[u - 1] > cd:
                                near_d[u], near_c[u] = near_d[u - 1], near_c[u - 1]
                                u -= 1
                            near_d[u], near_c[u] = cd, c
                            nc += 1
                for e in range(nc):
                    if near_d[e] > bd[k - 1]:
                        break
                    m = _knn_cell(sp, start[near_c[e]], start[near_c[e] + 1], x, y, z,
                                  bd, bi, m)
            else:
                for ix in range(x0, x1 + 1):
                    for iy in range(y0, y1 + 1):
                        za, zb, zs = _shell_z(ix, iy, cx, cy, cz, s, z0, z1)
                        col = ((ix - lo[0]) * ny + (iy - lo[1])) * nz - lo[2]  # + iz: box
                        for iz in range(za, zb + 1, zs):
                            if s > 0 and _cell_d2(x, y, z, ix, iy, iz, cell) > bd[k - 1]:
                                continue
                            c = _lookup(bits, rank, col + iz)
                            if c >= 0:
                                m = _knn_cell(sp, start[c], start[c + 1], x, y, z, bd,
                                              bi, m)
            if _covered(cx, cy, cz, s, lo, hi):
                break
            s += 1
        for u in range(k):
            if bi[u] >= 0:
                bi[u] = order[bi[u]]
            else:
                bd[u] = np.inf
    return out_i, out_d


@njit(cache=True, nogil=True)
def _grid_nn_held(bits: np.ndarray, rank: np.ndarray, start: np.ndarray, order: np.ndarray,
                  sp: np.ndarray, lo: np.ndarray, hi: np.ndarray, inv_cell: float,
                  q: np.ndarray, max_d2: float, anchor: np.ndarray, lb: np.ndarray,
                  hold: np.ndarray, slack: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """:func:`_grid_knn` with k = 1 for a query set that moves a little between calls (the
    source of a GICP iteration), skipping the searches that cannot change their answer
    (triangle inequality). A query that finds nothing within ``sqrt(max_d2)`` records a
    lower bound on its distance to the cloud (``lb``) and where it was (``anchor``): while
    ``lb`` minus its move still exceeds the search radius it cannot find anything and is
    not searched. A query that finds its nearest point ``j`` (distance ``d1``) also gets a
    lower bound ``d2`` on every other point's distance (its second nearest within
    ``sqrt(max_d2)``, else that bound) and records ``j`` (``hold``, a position in the
    grid's order) and half the gap ``(d2 - d1) / 2`` (``slack``): while it stays within
    ``slack`` of its anchor, ``j`` is still its unique nearest point (every other point is
    farther than ``d2 - move > d1 + move``), so only ``j``'s distance is computed, as the
    search computes it. ``lb`` 0 and ``hold`` -1: no bound. Results are the plain search's
    distances; between points at exactly the same distance the index may differ (this
    search visits the first shell in scan order, :func:`_grid_knn` nearest cell first);
    also returns the number of queries not searched."""
    nq = q.shape[0]
    out_i = np.full(nq, -1, dtype=np.int64)
    out_d = np.full(nq, np.inf)
    cell = 1.0 / inv_cell
    ny, nz = hi[1] - lo[1] + 1, hi[2] - lo[2] + 1
    max_d = np.sqrt(max_d2)
    skipped = 0
    for t in range(nq):
        x, y, z = q[t, 0], q[t, 1], q[t, 2]
        if lb[t] > 0.0 or hold[t] >= 0:
            ax, ay, az = x - anchor[t, 0], y - anchor[t, 1], z - anchor[t, 2]
            move = np.sqrt(ax * ax + ay * ay + az * az)
            # the margins cover rounding in the bounds and in the move (~1e-15 relative)
            if lb[t] > 0.0:
                if lb[t] - move > max_d * (1.0 + 1e-9) + 1e-9:
                    skipped += 1
                    continue
            elif move < slack[t]:
                j = hold[t]
                dx, dy, dz = sp[j, 0] - x, sp[j, 1] - y, sp[j, 2] - z
                d2 = dx * dx + dy * dy + dz * dz
                if d2 < max_d2:
                    out_i[t] = order[j]
                    out_d[t] = d2
                skipped += 1
                continue
        cx, cy, cz = _cell_of(x, y, z, inv_cell)
        m0 = _face_margin(x, y, z, inv_cell) * cell
        b0, b1 = max_d2, max_d2  # the two nearest (squared), within the bound
        i0 = -1
        low = np.inf  # a miss: lower bound on every squared distance (all are >= max_d2)
        s = 0
        while True:
            x0, y0, z0 = max(cx - s, lo[0]), max(cy - s, lo[1]), max(cz - s, lo[2])
            x1, y1, z1 = min(cx + s, hi[0]), min(cy + s, hi[1]), min(cz + s, hi[2])
            if s > 0:
                lbs = (s - 1) * cell + m0
                if lbs * lbs > b1:
                    low = min(low, lbs * lbs)
                    break
                if i0 >= 0:
                    # only the cells the ball of the second nearest reaches, as in
                    # _grid_knn; with a nearest found, ``low`` is not kept, so the cells
                    # left out need not add their bound to it
                    r = np.sqrt(b1) * (1.0 + 1e-9) + 1e-12
                    a0, a1, a2 = _cell_of(x - r, y - r, z - r, inv_cell)
                    e0, e1, e2 = _cell_of(x + r, y + r, z + r, inv_cell)
                    x0, y0, z0 = max(x0, a0), max(y0, a1), max(z0, a2)
                    x1, y1, z1 = min(x1, e0), min(y1, e1), min(z1, e2)
            for ix in range(x0, x1 + 1):
                for iy in range(y0, y1 + 1):
                    za, zb, zs = _shell_z(ix, iy, cx, cy, cz, s, z0, z1)
                    col = ((ix - lo[0]) * ny + (iy - lo[1])) * nz - lo[2]
                    for iz in range(za, zb + 1, zs):
                        if s > 0:
                            cd = _cell_d2(x, y, z, ix, iy, iz, cell)
                            if cd > b1:
                                low = min(low, cd)
                                continue
                        c = _lookup(bits, rank, col + iz)
                        if c < 0:
                            continue
                        for j in range(start[c], start[c + 1]):
                            dx, dy, dz = sp[j, 0] - x, sp[j, 1] - y, sp[j, 2] - z
                            d2 = dx * dx + dy * dy + dz * dz
                            if d2 < b0:
                                b1 = b0
                                b0, i0 = d2, j
                            elif d2 < b1:
                                b1 = d2
                            else:
                                low = min(low, d2)
            if _covered(cx, cy, cz, s, lo, hi):
                break
            s += 1
        anchor[t, 0], anchor[t, 1], anchor[t, 2] = x, y, z
        if i0 >= 0:
            out_i[t] = order[i0]
            out_d[t] = b0
            lb[t] = 0.0
            hold[t] = i0
            slack[t] = 0.5 * (np.sqrt(b1) - np.sqrt(b0)) * (1.0 - 1e-9) - 1e-9
        else:
            lb[t] = np.sqrt(low)  # inf: an empty cloud around it, nothing anywhere
            hold[t] = -1
    return out_i, out_d, skipped


@njit(cache=True, nogil=True)
def first_per_cell(pts: np.ndarray, inv_cell: float) -> np.ndarray:
    """Index of the first point of each occupied cell, in input order (so ascending): one
    hashing pass where ``np.unique`` of the cell keys sorts."""
    n = pts.shape[0]
    cap = _pow2_at_least(2 * n)
    shift = np.uint64(64 - int(np.log2(cap)))
    keys = np.full(cap, -1, dtype=np.int64)
    out = np.empty(n, dtype=np.int64)
    m = 0
    last_key = -1
    for i in range(n):
        ix, iy, iz = _cell_of(pts[i, 0], pts[i, 1], pts[i, 2], inv_cell)
        key = _cell_key(ix, iy, iz)
        if key == last_key:  # the cell of the point before: not its first point
            continue
        last_key = key
        h = np.int64((np.uint64(key) * _GOLDEN) >> shift)
        while True:
            k = keys[h]
            if k == key:
                break
            if k == -1:
                keys[h] = key
                out[m] = i
                m += 1
                break
            h = (h + 1) & (cap - 1)
    return out[:m].copy()


class VoxelGrid:
    """Exact nearest-neighbour and k-nearest-neighbour searches over a fixed cloud (a grid
    of ``cell_m`` cells, see above), the interface of small_gicp's ``KdTree`` that the
    sparse backend uses. ``num_threads`` is accepted and ignored: a search runs on the
    calling thread and releases the GIL, the parallelism is across frame pairs."""

    def __init__(self, points: np.ndarray, cell_m: float, knn_cell_m: float | None = None,
                 *, checked: bool = False) -> None:
        """``knn_cell_m``: the k-nearest-neighbour searches (:meth:`batch_knn_search`) use a
        second grid of this cell over the same points, built on the first of them: found
        faster where the k-th neighbour lies beyond a cell or two of ``cell_m``, and the
        same neighbours in the same order as on this grid, except that points at exactly
        the same distance from a query come in the order their cells are visited (which
        depends on the cell): on 1.6 instead of 1.0 m cells, none in the register stage's
        searches on three boulevard clips, 2 of 1.55 M on the hard street (two equidistant
        neighbours swapped; its registrations bit-identical). ``checked``: ``points`` are
        a float64 (N, 3) C array already validated for this cell (the ``knn_cell_m`` grid
        of a validated grid): not scanned again."""
        if cell_m <= 0 or (knn_cell_m is not None and knn_cell_m <= 0):
            raise ValueError(f"grid cell must be positive, got {cell_m} / {knn_cell_m}")
        p = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
        small = min(cell_m, knn_cell_m or cell_m)
        if not checked and len(p) and (not np.isfinite(p).all()
                                       or np.abs(p).max() / small >= _BIAS - 2):
            raise ValueError("grid points must be finite and within 2^20 cells of the origin")
        self.n = len(p)
        self.inv_cell = 1.0 / cell_m
        while True:
            (self._bits, self._rank, self._start, self._order, self._sp, self._lo,
             self._hi) = _grid_build(p, self.inv_cell)
            if len(self._bits):
                break
            # the cloud's bounding box spans more than _MAX_BOX_CELLS cells (points strewn
            # kilometres apart): larger cells, the searches stay exact
            self.inv_cell *= 0.5
        self._points = p if knn_cell_m is not None and knn_cell_m != cell_m else None
        self._knn_cell_m = knn_cell_m
        self._knn: VoxelGrid | None = None
        self._knn_lock = threading.Lock()

    def _knn_grid(self) -> VoxelGrid:
        """The grid the k-nearest-neighbour searches use: this one, or the ``knn_cell_m``
        one (built once; several threads may search one scan's grid)."""
        if self._points is None or self._knn_cell_m is None:
            return self
        with self._knn_lock:
            if self._knn is None:
                self._knn = VoxelGrid(self._points, self._knn_cell_m, checked=True)
            return self._knn

    def _q(self, q: np.ndarray) -> np.ndarray:
        out = np.ascontiguousarray(np.asarray(q, dtype=np.float64).reshape(-1, 3))
        if len(out) and not np.abs(out).max() * self.inv_cell < _BIAS - 2:
            # far beyond any cloud here (the packed cell key has 21 bits per axis), or not
            # finite (NaN: no cell; the search would read outside the grid)
            raise ValueError("queries must be finite and within 2^20 cells of the origin")
        return out

    def batch_nearest_neighbor_search(self, q: np.ndarray, num_threads: int = 1,
                                      max_dist_m: float = np.inf
                                      ) -> tuple[np.ndarray, np.ndarray]:
        """(index, squared distance) of each query's nearest point; -1 / inf where none lies
        within ``max_dist_m`` (bound it: an unbounded search for a point far from the cloud
        visits every cell in between)."""
        del num_threads
        qq = self._q(q)
        if self.n == 0:
            return np.full(len(qq), -1, dtype=np.int64), np.full(len(qq), np.inf)
        i, d2 = _grid_knn(self._bits, self._rank, self._start, self._order, self._sp,
                          self._lo, self._hi, self.inv_cell, qq, 1, float(max_dist_m) ** 2)
        return i[:, 0], d2[:, 0]

    def nearest_bounded(self, q: np.ndarray, max_dist_m: float, anchor: np.ndarray,
                        lb: np.ndarray, hold: np.ndarray, slack: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`batch_nearest_neighbor_search` within ``max_dist_m`` for a query set
        searched again and again as it moves a little (a GICP source, iteration after
        iteration): ``anchor`` (N, 3), ``lb`` (N,) and ``slack`` (N,) float64, zeros at
        first, and ``hold`` (N,) int64, -1 at first, carry from one call to the next what
        makes a search unnecessary (:func:`_grid_nn_held`). WHY: a far pair (a roadside
        unit 70 m away) aligns thousands of centroids that have no correspondence, each
        searching its 27 cells in every iteration, and in GICP's last iterations the
        source barely moves, so most nearest points cannot change. The results are the
        plain search's (the same distances; of points at exactly one distance, perhaps
        another)."""
        qq = self._q(q)
        if self.n == 0:
            return np.full(len(qq), -1, dtype=np.int64), np.full(len(qq), np.inf)
        if (anchor.shape != qq.shape or lb.shape != (len(qq),) or hold.shape != (len(qq),)
                or slack.shape != (len(qq),)):
            raise ValueError("anchor / lb / hold / slack must be (N, 3) / (N,) / (N,) / (N,) "
                             "for N queries")
        i, d2, _ = _grid_nn_held(self._bits, self._rank, self._start, self._order,
                                 self._sp, self._lo, self._hi, self.inv_cell, qq,
                                 float(max_dist_m) ** 2, anchor, lb, hold, slack)
        return i, d2

    def batch_knn_search(self, q: np.ndarray, k: int, num_threads: int = 1
                         ) -> tuple[np.ndarray, np.ndarray]:
        """(indices, squared distances) of each query's ``min(k, n)`` nearest points, nearest
        first (on the ``knn_cell_m`` grid where one was asked for). The first ``j`` columns
        of a search for ``k >= j`` neighbours are the search for ``j`` (a point enters the
        sorted list only when strictly closer than its last entry, and after every entry as
        close as itself, so equal distances keep the order the cells were visited in:
        :class:`sparse.Neighbours` relies on it)."""
        del num_threads
        g = self._knn_grid()
        qq = g._q(q)
        kk = min(int(k), g.n)
        if kk <= 0:
            return np.zeros((len(qq), 0), dtype=np.int64), np.zeros((len(qq), 0))
        return _grid_knn(g._bits, g._rank, g._start, g._order, g._sp, g._lo, g._hi,
                         g.inv_cell, qq, kk, np.inf)
