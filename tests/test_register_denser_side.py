"""A cross pair whose correspondences go from the sparser scan to the denser one at each spot
(``gicp.far_pair_denser_side``, issue #21), on a small synthetic street (cheap: no clip)."""

from __future__ import annotations

import numpy as np

from v2xlake.tasks.geometry import so3_exp
from v2xlake.tasks.register.backends import SparseGicpBackend
from v2xlake.tasks.register.config import GicpSection, RegisterConfig
from v2xlake.tasks.register.sparse import DenserSide, align_sparse


def _street(rng: np.random.Generator, origin: np.ndarray, n: int) -> np.ndarray:
    """Points of a street (road, two walls, four boxes with faces across it), thinned with
    the square of the range from ``origin`` as a LiDAR's are."""
    parts = [np.c_[rng.uniform(-45, 45, n), rng.uniform(-10, 10, n), np.zeros(n)]]
    for y in (-10.0, 10.0):
        parts.append(np.c_[rng.uniform(-45, 45, n // 2), np.full(n // 2, y),
                           rng.uniform(0, 6, n // 2)])
    for x0, y0 in ((-25.0, -6.0), (-5.0, 5.0), (12.0, -5.0), (30.0, 6.0)):
        m = n // 8
        parts.append(np.c_[np.full(m, x0), y0 + rng.uniform(-1, 1, m), rng.uniform(0, 1.5, m)])
        parts.append(np.c_[x0 + rng.uniform(0, 4, m), np.full(m, y0 + 1.0),
                           rng.uniform(0, 1.5, m)])
    p = np.concatenate(parts)
    r = np.linalg.norm(p - origin, axis=1)
    keep = rng.uniform(size=len(p)) < np.minimum(1.0, (12.0 / np.maximum(r, 1e-6)) ** 2)
    return p[keep] - origin


def _pair(seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Target points (LiDAR at the origin), source points (its own frame), true T."""
    rng = np.random.default_rng(seed)
    o_t, o_s = np.array([0.0, 0.0, 1.9]), np.array([35.0, 3.0, 1.9])
    T = np.eye(4)
    T[:3, 3] = o_s - o_t
    tp = _street(rng, o_t, 60000)
    sp = _street(rng, o_s, 60000)
    return tp, sp, T


def _align(tp: np.ndarray, sp: np.ndarray, init: np.ndarray, denser: bool):
    b = SparseGicpBackend(GicpSection())
    t, s = b.prepare_points(tp), b.prepare_points(sp)
    rows = np.arange(len(sp))
    s.handle.ensure(s.points, s.tree, rows, 10)
    side = DenserSide(s.points, s.tree, s.handle) if denser else None
    return align_sparse(t.points, t.tree, t.handle, s.points[rows], s.handle.normals[rows],
                        s.handle.ratio[rows], init, num_neighbors=10,
                        max_correspondence_m=1.0, max_iterations=30, denser=side)


def test_denser_side_converges_and_keeps_the_forward_figures() -> None:
    """From 15 cm / 0.4 deg off both costs reach the true pose; with the denser side the
    squared distances (the quality figures) and ``pairs`` are still one per sample row of
    the forward search, and the information returned is the forward Hessian's size, not the
    smaller split cost's."""
    tp, sp, T = _pair()
    init = T.copy()
    init[:3, :3] = so3_exp(np.radians([0.0, 0.0, 0.4])) @ T[:3, :3]
    init[:3, 3] += [0.12, -0.08, 0.05]
    fwd = _align(tp, sp, init, False)
    den = _align(tp, sp, init, True)
    for out in (fwd, den):
        assert np.linalg.norm(out.T[:3, 3] - T[:3, 3]) < 0.01
    assert den.sq_dist is not None and len(den.sq_dist) == len(sp)
    assert den.pairs == int(np.count_nonzero(den.sq_dist <= 1.0))
    assert abs(den.pairs - fwd.pairs) < 0.02 * fwd.pairs
    ratio = np.trace(den.H[3:, 3:]) / np.trace(fwd.H[3:, 3:])
    assert 0.9 < ratio < 1.1


def test_stationary_pairs_by_default() -> None:
    assert RegisterConfig().gicp.far_pair_denser_side == "stationary"
    for v in ("off", "far"):
        assert GicpSection.model_validate({"far_pair_denser_side": v}).far_pair_denser_side == v
