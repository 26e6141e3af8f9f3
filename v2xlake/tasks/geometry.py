"""The one geometry vocabulary of v2xlake: rigid transforms, boxes and overlaps.

Conventions (docs/architecture.md, Space): a transform named ``T_a_b`` maps points from frame ``b``
into frame ``a`` and is a (..., 4, 4) float64 matrix; quaternions are unit (w, x, y, z);
boxes carry ``size = (w, l, h)`` with the length along the box x-axis (nuScenes). Every
stage and export composes, inverts and applies transforms, counts points in boxes and
measures overlaps through these functions, so that a point count or an IoU has one
definition in the whole project. The conversions between the stored form (translation,
quaternion) and matrices live in ``schemas.geometry`` (validation needs them, and schemas may
not import tasks) and are re-exported here. Interpolating a pose track in time (linear +
SLERP) is ``tasks.interpolate``: its numba kernels are shared with deskew's inner loop.

SciPy's ``RigidTransform``/``Rotation`` were measured against these functions
(tests/bench/bench_geometry.py): on one transform they are 4-80x slower (object
construction and validation per call) and on a 1000-batch 13-23x; only Rotation's
quaternion -> matrix matches NumPy. So the vocabulary is plain NumPy on (..., 4, 4) arrays.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from functools import reduce
from typing import TypeVar

import numpy as np
from scipy.spatial import cKDTree

from v2xlake.schemas.geometry import matrix_to_quat, quat_to_matrix, transform

__all__ = [
    "BOX_EDGES",
    "apply",
    "box_corners",
    "compose",
    "count_points_in_boxes",
    "invert",
    "iou_xyxy",
    "matrix_to_quat",
    "merge_until_stable",
    "points_in_boxes",
    "quat_to_matrix",
    "quat_wxyz_of",
    "rigid",
    "rotation_angle",
    "transform",
    "transform_boxes",
]

# unit-cube corner signs, ordered so that 0-3 is the bottom face and 4-7 the top face
_SIGNS = np.array(
    [[1, 1, -1], [1, -1, -1], [-1, -1, -1], [-1, 1, -1],
     [1, 1, 1], [1, -1, 1], [-1, -1, 1], [-1, 1, 1]], dtype=np.float64,
)
# the 12 edges of a box as corner index pairs (bottom, top, verticals)
BOX_EDGES = np.array(
    [[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4],
     [0, 4], [1, 5], [2, 6], [3, 7]], dtype=np.int64,
)


def rigid(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations + (..., 3) translations -> (..., 4, 4) transforms."""
    R = np.asarray(rotation, dtype=np.float64)
    m = np.zeros((*R.shape[:-2], 4, 4))
    m[..., :3, :3] = R
    m[..., :3, 3] = translation
    m[..., 3, 3] = 1.0
    return m


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of (..., 4, 4) rigid transforms (transpose, no general matrix inverse)."""
    T = np.asarray(T, dtype=np.float64)
    out = np.zeros_like(T)
    rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out[..., :3, :3] = rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", rt, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def compose(*Ts: np.ndarray) -> np.ndarray:
    """``compose(T_a_b, T_b_c, ...) = T_a_b @ T_b_c @ ...`` (broadcasting over leading axes)."""
    return reduce(np.matmul, (np.asarray(T, dtype=np.float64) for T in Ts))


def apply(T: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """``T @ p`` for (N, 3) points (float32 or float64) -> (N, 3) float64.

    One column at a time with in-place ufuncs: no float64 copy of the input, no BLAS. On a
    225k-point scan (tests/bench/bench_geometry.py) 1.5 ms, steady; ``einsum`` 3.2 ms,
    ``RigidTransform.apply`` 7.7 ms, and ``xyz @ R.T`` 0.9-3.5 ms depending on what BLAS
    threads find free on a shared machine.
    """
    T = np.asarray(T, dtype=np.float64)
    x = np.asarray(xyz)
    out = np.empty((x.shape[0], 3))
    c0, c1, c2 = x[:, 0], x[:, 1], x[:, 2]
    for i in range(3):
        o = out[:, i]
        np.multiply(c0, T[i, 0], out=o)
        o += c1 * T[i, 1]
        o += c2 * T[i, 2]
        o += T[i, 3]
    return out


def rotation_angle(T: np.ndarray) -> np.ndarray:
    """Angle (radians, [0, pi]) of the rotation part of (..., 3, 3) or (..., 4, 4) matrices.

    ``atan2(|axis * sin|, cos)`` rather than ``arccos((tr - 1) / 2)``: arccos loses all
    precision below ~1e-8 rad, which is where registration corrections live.
    """
    R = np.asarray(T, dtype=np.float64)[..., :3, :3]
    cos = (R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1.0) / 2.0
    v = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0],
                  R[..., 1, 0] - R[..., 0, 1]], axis=-1)
    return np.arctan2(np.linalg.norm(v, axis=-1) / 2.0, cos)


def transform_boxes(T: np.ndarray, center: np.ndarray, quat: np.ndarray, velocity: np.ndarray,
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Boxes (M centres, M unit quaternions, M velocities, NaN allowed) expressed in another
    frame: ``T`` is one 4x4 or (M, 4, 4), one per box, mapping old -> new coordinates."""
    T = np.asarray(T, dtype=np.float64)
    m = len(center)
    Tm = np.broadcast_to(T, (m, 4, 4)) if T.ndim == 2 else T
    R = Tm[:, :3, :3]
    c = np.einsum("mij,mj->mi", R, center) + Tm[:, :3, 3]
    q = matrix_to_quat(R @ quat_to_matrix(quat)) if m else np.zeros((0, 4))
    v = np.einsum("mij,mj->mi", R, velocity)
    return c, q, v


def box_corners(center: np.ndarray, size: np.ndarray, quat: np.ndarray) -> np.ndarray:
    """(M, 8, 3) corners of boxes; the box x-axis carries the length, y the width."""
    half = np.stack([size[:, 1], size[:, 0], size[:, 2]], axis=1) / 2.0  # l, w, h
    local = _SIGNS[None, :, :] * half[:, None, :]
    R = quat_to_matrix(quat)
    return np.einsum("mij,mkj->mki", R, local) + center[:, None, :]


def points_in_boxes(xyz: np.ndarray, center: np.ndarray, size: np.ndarray, quat: np.ndarray,
                    margin: float = 0.0) -> list[np.ndarray]:
    """Sorted indices of the points inside each box (faces inclusive, as the nuScenes
    devkit's ``points_in_box``), optionally grown by ``margin`` metres on every side.

    A KD-tree over xy prunes to the points within each box's circumscribed circle, then the
    exact oriented test runs only on those candidates: O(N log N + sum of candidates)
    instead of O(N * M).
    """
    m = center.shape[0]
    if m == 0 or xyz.shape[0] == 0:
        return [np.zeros(0, dtype=np.int64) for _ in range(m)]
    tree = cKDTree(np.asarray(xyz[:, :2], dtype=np.float64))
    half = np.stack([size[:, 1], size[:, 0], size[:, 2]], axis=1) / 2.0 + margin
    radius = np.linalg.norm(half, axis=1)
    cands = tree.query_ball_point(center[:, :2], r=radius, workers=1)
    R = quat_to_matrix(quat)
    out: list[np.ndarray] = []
    for k in range(m):
        idx = np.asarray(cands[k], dtype=np.int64)
        if idx.size == 0:
            out.append(idx)
            continue
        local = (xyz[idx].astype(np.float64) - center[k]) @ R[k]
        inside = np.all(np.abs(local) <= half[k], axis=1)
        out.append(np.sort(idx[inside]))
    return out


def count_points_in_boxes(xyz: np.ndarray, center: np.ndarray, size: np.ndarray,
                          quat: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """(M,) number of points inside each box (``points_in_boxes``)."""
    return np.array([len(i) for i in points_in_boxes(xyz, center, size, quat, margin)],
                    dtype=np.int64)


def iou_xyxy(a: np.ndarray, b: np.ndarray, *, paired: bool = False) -> np.ndarray:
    """IoU of (N, 4) and (M, 4) image boxes (x0, y0, x1, y1): the (N, M) matrix, or with
    ``paired`` the (N,) IoU of a[i] with b[i]. 0 where a box is empty or NaN."""
    a = np.asarray(a, dtype=np.float64).reshape(-1, 4)
    b = np.asarray(b, dtype=np.float64).reshape(-1, 4)
    if paired:
        if len(a) != len(b):
            raise ValueError(f"paired IoU of {len(a)} and {len(b)} boxes")
        a, b = a[:, None, :], b[:, None, :]
    else:
        a, b = a[:, None, :], b[None, :, :]
    iw = np.minimum(a[..., 2], b[..., 2]) - np.maximum(a[..., 0], b[..., 0])
    ih = np.minimum(a[..., 3], b[..., 3]) - np.maximum(a[..., 1], b[..., 1])
    inter = np.clip(iw, 0, None) * np.clip(ih, 0, None)
    area_a = np.clip(a[..., 2] - a[..., 0], 0, None) * np.clip(a[..., 3] - a[..., 1], 0, None)
    area_b = np.clip(b[..., 2] - b[..., 0], 0, None) * np.clip(b[..., 3] - b[..., 1], 0, None)
    union = area_a + area_b - inter
    with np.errstate(invalid="ignore", divide="ignore"):
        iou = np.where(union > 0, inter / union, 0.0)
    iou = np.nan_to_num(iou, nan=0.0)
    return iou[:, 0] if paired else iou


_Item = TypeVar("_Item")


def greedy_boxes(scored: Sequence[tuple[float, tuple[float, float, float, float]]], keep: int,
                 iou: float = 0.2, accept: Callable[[tuple[float, float, float, float]], bool]
                 | None = None, candidates: int | None = None
                 ) -> list[tuple[tuple[float, float, float, float], float]]:
    """(box, score) of the highest-scoring boxes (xyxy) of ``scored`` (score, box), each kept
    unless it overlaps one kept before by ``iou`` or more or ``accept`` refuses it, at most
    ``keep``; only the best ``candidates`` are looked at (None: all). Why not ``nms``: the
    small-plate tests need a cap on what is kept and looked at, not a suppression per kind."""
    order = sorted(scored, key=lambda f: -f[0])[:candidates]
    out: list[tuple[tuple[float, float, float, float], float]] = []
    for score, box in order:
        if len(out) >= keep:
            break
        if out and iou_xyxy(np.array([box]), np.array([o for o, _s in out])).max() >= iou:
            continue
        if accept is None or accept(box):
            out.append((box, score))
    return out


def merge_until_stable(items: Sequence[_Item], union: Callable[[_Item, _Item], _Item | None]
                       ) -> list[_Item]:
    """``items`` merged pairwise until no pair merges: the first pair (i < j, in order) whose
    ``union`` is not None is replaced by it at i, and the scan starts again. Why one loop:
    boxes, bands and crops are merged under different rules, but always this way, and a
    result that depends on the order must depend on it the same way everywhere."""
    out = list(items)
    merged = True
    while merged:
        merged = False
        for i in range(len(out)):
            for j in range(i + 1, len(out)):
                u = union(out[i], out[j])
                if u is not None:
                    out[i] = u
                    del out[j]
                    merged = True
                    break
            if merged:
                break
    return out


def quat_wxyz_of(T: np.ndarray) -> np.ndarray:
    """(..., 4) unit quaternions (w >= 0) of (..., 4, 4) transforms."""
    return matrix_to_quat(np.asarray(T)[..., :3, :3])


def so3_exp(w: np.ndarray) -> np.ndarray:
    """(..., 3) rotation vectors -> (..., 3, 3) rotation matrices (Rodrigues)."""
    w = np.asarray(w, np.float64)
    th = np.linalg.norm(w, axis=-1)[..., None, None]
    K = np.zeros((*w.shape[:-1], 3, 3))
    K[..., 0, 1], K[..., 0, 2] = -w[..., 2], w[..., 1]
    K[..., 1, 0], K[..., 1, 2] = w[..., 2], -w[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -w[..., 1], w[..., 0]
    with np.errstate(invalid="ignore", divide="ignore"):
        a = np.where(th > 1e-8, np.sin(th) / th, 1.0 - th**2 / 6.0)
        b = np.where(th > 1e-8, (1.0 - np.cos(th)) / th**2, 0.5 - th**2 / 24.0)
    return np.eye(3) + a * K + b * (K @ K)


def so3_log(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) -> (..., 3) rotation vectors; exact to the last digit at small angles
    (atan2 of sin and cos, not arccos of the trace)."""
    R = np.asarray(R, np.float64)
    v = 0.5 * np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0],
                        R[..., 1, 0] - R[..., 0, 1]], -1)
    s = np.linalg.norm(v, axis=-1)
    c = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    th = np.arctan2(s, c)
    with np.errstate(invalid="ignore", divide="ignore"):
        f = np.where(s > 1e-12, th / s, 1.0)
    return v * f[..., None]


def se3_adjoint(T: np.ndarray) -> np.ndarray:
    """Adjoint of a transform (4, 4) or a stack (N, 4, 4) on ``[rot, trans]`` twists:
    ``T exp(d) T^-1 = exp(Ad_T d)``, ``Ad_T = [[R, 0], [t^ R, R]]`` ((6, 6) or (N, 6, 6)).
    It moves an information matrix or a perturbation from one frame to another."""
    M = np.asarray(T, dtype=np.float64)
    one = M.ndim == 2
    M = M[None] if one else M
    R, t = M[:, :3, :3], M[:, :3, 3]
    tx = np.zeros((len(M), 3, 3))
    tx[:, 0, 1], tx[:, 0, 2] = -t[:, 2], t[:, 1]
    tx[:, 1, 0], tx[:, 1, 2] = t[:, 2], -t[:, 0]
    tx[:, 2, 0], tx[:, 2, 1] = -t[:, 1], t[:, 0]
    out = np.zeros((len(M), 6, 6))
    out[:, :3, :3] = R
    out[:, 3:, 3:] = R
    out[:, 3:, :3] = tx @ R
    return out[0] if one else out
