"""Continuous-time poses from discrete INS samples (CATS-V2V supplementary A.4, eq. 2a-2c).

This is the ONE definition of pose interpolation in v2xlake: deskew (eq. 3), nuScenes ego
poses, the cross-agent initial transform (main paper eq. 1a) and temporal alignment all call
it, so that every stage sees the same pose at the same instant. Translation is linear,
rotation is SLERP along the shortest arc, between the two INS samples that bracket the
query (``t_a <= t <= t_b``). A query outside the sampled span is never extrapolated: it is
flagged (NaN) or raises, because a silently extrapolated pose moves points by decimetres.

The scalar kernels (``bracket``, ``slerp``, ``pose_at``) are numba functions so that the
deskew kernel can inline exactly the same arithmetic; ``interpolate_poses`` is the array
entry point for everything else.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numba import njit

from v2xlake.tasks.geometry import transform

# Below this angle between two quaternions (radians on the 4-sphere) SLERP's 1/sin(theta)
# loses more precision than the normalised linear blend it converges to (error ~theta^3).
_SLERP_EPS = 1e-9


class PoseCoverageError(ValueError):
    """Queries outside the sampled pose span; names the span so the caller can report it."""

    def __init__(self, t_min: int, t_max: int, cover_min: int, cover_max: int, n: int) -> None:
        self.t_min, self.t_max = int(t_min), int(t_max)
        self.cover_min, self.cover_max, self.n = int(cover_min), int(cover_max), int(n)
        super().__init__(
            f"{n} query time(s) in [{t_min}, {t_max}] ns fall outside the pose coverage "
            f"[{cover_min}, {cover_max}] ns (no extrapolation)"
        )


@dataclass(frozen=True, eq=False)  # arrays: identity, not element-wise ==
class PoseTrack:
    """Samples of ``T_world_ego``: times (int64 ns, strictly increasing), xyz, quat wxyz.

    Validated and normalised on construction (contiguous int64 / float64, unit quaternions,
    at least two strictly increasing times), so the numba kernels can trust the arrays.
    """

    t_ns: np.ndarray
    xyz: np.ndarray
    quat_wxyz: np.ndarray

    def __post_init__(self) -> None:
        t, p, q = _validated(self.t_ns, self.xyz, self.quat_wxyz)
        object.__setattr__(self, "t_ns", t)
        object.__setattr__(self, "xyz", p)
        object.__setattr__(self, "quat_wxyz", q)

    @classmethod
    def create(cls, t_ns: np.ndarray, xyz: np.ndarray, quat_wxyz: np.ndarray) -> PoseTrack:
        return cls(t_ns, xyz, quat_wxyz)

    @property
    def t_min(self) -> int:
        return int(self.t_ns[0])

    @property
    def t_max(self) -> int:
        return int(self.t_ns[-1])

    def __len__(self) -> int:
        return len(self.t_ns)

    def covers(self, t_ns: np.ndarray | int) -> np.ndarray:
        t = np.asarray(t_ns, dtype=np.int64)
        return (t >= self.t_ns[0]) & (t <= self.t_ns[-1])

    def at(self, t_query_ns: np.ndarray | int,
           uncovered: Literal["raise", "nan"] = "raise") -> tuple[np.ndarray, np.ndarray]:
        return interpolate_poses(self.t_ns, self.xyz, self.quat_wxyz, t_query_ns, uncovered)

    def matrices(self, t_query_ns: np.ndarray | int,
                 uncovered: Literal["raise", "nan"] = "raise") -> np.ndarray:
        """(N, 4, 4) ``T_world_ego`` at the query times (NaN where uncovered, if allowed)."""
        xyz, q = self.at(np.atleast_1d(np.asarray(t_query_ns, dtype=np.int64)), uncovered)
        return transform(xyz, q)


def _validated(t_ns: np.ndarray, xyz: np.ndarray,
               quat_wxyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    t = np.ascontiguousarray(t_ns, dtype=np.int64).reshape(-1)
    p = np.ascontiguousarray(xyz, dtype=np.float64).reshape(-1, 3)
    q = np.ascontiguousarray(quat_wxyz, dtype=np.float64).reshape(-1, 4)
    if not (len(t) == len(p) == len(q)):
        raise ValueError(f"pose arrays disagree in length: t {len(t)}, xyz {len(p)}, quat {len(q)}")
    if len(t) < 2:
        raise ValueError(f"pose interpolation needs at least 2 samples, got {len(t)}")
    d = np.diff(t)
    if np.any(d <= 0):
        k = int(np.flatnonzero(d <= 0)[0])
        raise ValueError(
            f"pose times must be strictly increasing; sample {k + 1} ({t[k + 1]} ns) "
            f"follows {t[k]} ns"
        )
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
        raise ValueError("pose samples contain NaN / inf")
    n = np.linalg.norm(q, axis=1)
    if np.any(np.abs(n - 1.0) > 1e-3):
        raise ValueError(f"pose quaternions are not unit (norm range {n.min():.6f}..{n.max():.6f})")
    return t, p, q / n[:, None]


@njit(cache=True, inline="always")
def bracket(pose_t: np.ndarray, t: int) -> tuple[int, float]:
    """Index ``k`` with ``pose_t[k] <= t <= pose_t[k+1]`` and alpha (eq. 2c); k=-1 if uncovered."""
    n = pose_t.shape[0]
    if t < pose_t[0] or t > pose_t[n - 1]:
        return -1, 0.0
    lo, hi = 0, n - 1  # invariant: pose_t[lo] <= t, and t <= pose_t[hi]
    while hi - lo > 1:
        mid = (lo + hi) >> 1
        if pose_t[mid] <= t:
            lo = mid
        else:
            hi = mid
    # integer differences first: ns since the bracket start fits a double exactly
    alpha = float(t - pose_t[lo]) / float(pose_t[hi] - pose_t[lo])
    return lo, alpha


@njit(cache=True, inline="always")
def slerp(aw: float, ax: float, ay: float, az: float, bw: float, bx: float, by: float,
          bz: float, alpha: float) -> tuple[float, float, float, float]:
    """Eq. 2b on the shortest arc (q and -q are the same rotation); returns a unit quaternion."""
    dot = aw * bw + ax * bx + ay * by + az * bz
    if dot < 0.0:
        bw, bx, by, bz = -bw, -bx, -by, -bz
    # angle between the 4-vectors from atan2 of |b-a| and |b+a|: accurate at every angle,
    # unlike acos(dot) near 1
    dw, dx, dy, dz = bw - aw, bx - ax, by - ay, bz - az
    sw, sx, sy, sz = bw + aw, bx + ax, by + ay, bz + az
    theta = 2.0 * np.arctan2(np.sqrt(dw * dw + dx * dx + dy * dy + dz * dz),
                             np.sqrt(sw * sw + sx * sx + sy * sy + sz * sz))
    if theta < _SLERP_EPS:
        wa, wb = 1.0 - alpha, alpha
    else:
        s = np.sin(theta)
        wa = np.sin((1.0 - alpha) * theta) / s
        wb = np.sin(alpha * theta) / s
    qw, qx, qy, qz = wa * aw + wb * bw, wa * ax + wb * bx, wa * ay + wb * by, wa * az + wb * bz
    inv = 1.0 / np.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    return qw * inv, qx * inv, qy * inv, qz * inv


@njit(cache=True, inline="always")
def pose_at(pose_t: np.ndarray, pose_xyz: np.ndarray, pose_q: np.ndarray, t: int,
            out: np.ndarray) -> bool:
    """Pose at ``t`` into ``out`` = [x, y, z, qw, qx, qy, qz]; False if ``t`` is uncovered."""
    k, alpha = bracket(pose_t, t)
    if k < 0:
        return False
    b = k + 1
    for j in range(3):
        out[j] = (1.0 - alpha) * pose_xyz[k, j] + alpha * pose_xyz[b, j]
    qw, qx, qy, qz = slerp(pose_q[k, 0], pose_q[k, 1], pose_q[k, 2], pose_q[k, 3],
                           pose_q[b, 0], pose_q[b, 1], pose_q[b, 2], pose_q[b, 3], alpha)
    out[3], out[4], out[5], out[6] = qw, qx, qy, qz
    return True


@njit(cache=True)
def _interp_batch(pose_t: np.ndarray, pose_xyz: np.ndarray, pose_q: np.ndarray,
                  tq: np.ndarray, out_xyz: np.ndarray, out_q: np.ndarray) -> int:
    buf = np.empty(7)
    n_unc = 0
    for i in range(tq.shape[0]):
        if pose_at(pose_t, pose_xyz, pose_q, tq[i], buf):
            out_xyz[i, 0], out_xyz[i, 1], out_xyz[i, 2] = buf[0], buf[1], buf[2]
            out_q[i, 0], out_q[i, 1], out_q[i, 2], out_q[i, 3] = buf[3], buf[4], buf[5], buf[6]
        else:
            n_unc += 1
            for j in range(3):
                out_xyz[i, j] = np.nan
            for j in range(4):
                out_q[i, j] = np.nan
    return n_unc


def interpolate_poses(
    pose_t_ns: np.ndarray,
    pose_xyz: np.ndarray,
    pose_quat_wxyz: np.ndarray,
    t_query_ns: np.ndarray | int,
    uncovered: Literal["raise", "nan"] = "raise",
) -> tuple[np.ndarray, np.ndarray]:
    """Poses at arbitrary times (eq. 2a-2c): linear translation, shortest-arc SLERP rotation.

    Returns ``(xyz (N, 3), quat_wxyz (N, 4))`` float64 (scalar query -> N = 1). A query
    outside ``[pose_t_ns[0], pose_t_ns[-1]]`` raises :class:`PoseCoverageError` naming the
    span, or with ``uncovered="nan"`` gives NaN rows (``np.isnan(xyz[:, 0])`` is the flag).
    Input quaternions may flip sign between samples; output has the sign SLERP produces.
    """
    t, p, q = _validated(pose_t_ns, pose_xyz, pose_quat_wxyz)
    tq = np.ascontiguousarray(np.atleast_1d(np.asarray(t_query_ns)), dtype=np.int64).reshape(-1)
    out_xyz = np.empty((len(tq), 3))
    out_q = np.empty((len(tq), 4))
    n_unc = _interp_batch(t, p, q, tq, out_xyz, out_q)
    if n_unc and uncovered == "raise":
        bad = tq[(tq < t[0]) | (tq > t[-1])]
        raise PoseCoverageError(bad.min(), bad.max(), t[0], t[-1], n_unc)
    return out_xyz, out_q
