"""Several LiDARs on one agent (issue #27): refine a secondary LiDAR's extrinsic against the
agent's primary one, ``T_primary_secondary``, from a coarse published start.

Why not plain GICP from the published start: the side LiDARs of the real lidar2lidar rig are
published about 45 deg and 10 cm off their real mounting. GICP converges from there on some
scans and, on others (or at a fine voxel), settles in a wrong minimum tens of degrees away
while still reporting convergence. So the refinement is coarse to fine and checks itself:

1. **Search** (``IntraConfig.seed_*``): rotation seeds on a roll/pitch/yaw grid around the
   published rotation (the sensor's position kept: a mis-tilted sensor is wrong in its
   rotation far more than in its lever arm), each finished by a short GICP on coarse voxels.
   Every end point is scored by a robust overlap score (a truncated kernel over the source's
   distance to the primary cloud, the same for every candidate) and end points within
   ``minimum_sep_*`` of each other are one minimum.
2. **Refusal of a wrong minimum**: the best minimum must beat every distinct other one by
   ``ambiguity_ratio`` (two minima that score alike: the data cannot tell which is the mounting),
   must lie within the searched correction (``max_correction_deg``: beyond it nothing was
   searched against it), and must overlap the primary cloud enough (``min_overlap``).
3. **Finish**: multi-scale GICP (``fine_stages``) from the winner; a finish that leaves the
   winner's basin is refused.
4. **Uncertainty**: GICP's information (Hessian, left perturbation ``[rot, trans]`` in the
   primary frame) scaled by the residuals' variance factor and inflated for correlated points
   (``correlation``), plus a systematic floor (``floor_*``: what one scan cannot average out,
   e.g. motion between the LiDARs' sweeps); a direction whose 1-sigma exceeds ``max_std_*``
   (a single plane, a corridor) is not observed and the result is refused.

``combine`` pools several frames' (or scenes') estimates of the same rig: they must agree
within ``agree_*`` (a majority of them, at least ``min_agreeing``), else the rig's extrinsic is
refused; the pooled estimate is the mean in the tangent space of the medoid.

Everything here works on arrays (no lake I/O); the register stage calls it on deskewed frames.
"""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from v2xlake.tasks.geometry import invert, so3_exp, so3_log
from v2xlake.tasks.register.backends import right_to_left_information


@dataclass(frozen=True)
class IntraConfig:
    """Knobs of the intra-agent refinement; defaults measured on the real lidar2lidar rig
    (tests/test_register_intra.py, tests/bench/bench_register_intra.py)."""

    # search: roll/pitch/yaw offsets (deg) on a grid of this step up to this bound, each
    # about the published rotation; the real rig's error is ~45 deg, so +-60 by 30 puts a
    # seed within ~15 deg (coarse GICP's basin) of any mounting within the bound
    seed_max_deg: float = 60.0
    seed_step_deg: float = 30.0
    # coarse GICP of every seed: voxel (both clouds), correspondence distance, iterations
    coarse_voxel_m: float = 1.5
    coarse_max_correspondence_m: float = 3.0
    coarse_iterations: int = 15
    # the best ``polish_top`` coarse minima are polished (one GICP at these settings) before
    # they are compared: a coarse end point may be a half-converged copy of another minimum
    polish_top: int = 6
    polish_voxel_m: float = 0.5
    polish_max_correspondence_m: float = 1.0
    polish_iterations: int = 30
    # overlap score: source voxel, kernel width (a source point at distance d from the
    # primary cloud counts max(0, 1 - d^2 / tau^2))
    score_voxel_m: float = 0.3
    score_tau_m: float = 0.3
    # two end points closer than these are the same minimum
    minimum_sep_deg: float = 3.0
    minimum_sep_m: float = 0.3
    # refuse when a distinct other minimum scores at least this fraction of the best
    ambiguity_ratio: float = 0.85
    # refuse a correction beyond the searched region (deg from the published rotation)
    max_correction_deg: float = 65.0
    max_correction_m: float = 1.0
    # refuse when less than this fraction of the source (score voxels) overlaps the primary
    min_overlap: float = 0.15
    min_points: int = 200  # fewer source points than this after the score voxel: refused
    # multi-scale finish: (primary voxel m, secondary voxel m, max correspondence m)
    fine_stages: tuple[tuple[float, float, float], ...] = (
        (0.5, 0.5, 1.5), (0.25, 0.25, 0.75), (0.15, 0.1, 0.4))
    fine_iterations: int = 100
    num_neighbors: int = 10  # covariance estimation
    # the finish may not move the coarse winner by more than this (else: left its basin)
    finish_max_deg: float = 5.0
    finish_max_m: float = 0.5
    # uncertainty: formal covariance x variance factor x correlation, plus the spread of the
    # finish repeated on ``split_halves`` half-planes of the secondary scan (each half's
    # deviation from the full result has about the full result's variance: what the data
    # says, where the formal figure only says what the geometry could give), plus a floor
    correlation: float = 10.0
    split_halves: int = 4
    floor_deg: float = 0.1
    floor_m: float = 0.005
    # refuse when the 1-sigma of any direction exceeds these (degenerate geometry, or a pair
    # whose halves disagree: the real Pandar64/QT64 pair gives ~1 deg / 18 cm and is refused)
    max_std_deg: float = 0.5
    max_std_m: float = 0.05
    max_range_m: float = 120.0  # farther returns: sparse, noisy
    min_range_m: float = 0.5  # nearer returns: the vehicle's own body
    num_threads: int = 1
    # combine(): estimates of one rig must agree within these (pairwise to the medoid)
    agree_deg: float = 0.5
    agree_m: float = 0.03
    min_agreeing: int = 2
    agree_fraction: float = 0.5  # more than this fraction of estimates must agree


@dataclass(frozen=True)
class Minimum:
    """One distinct end point of the search."""

    T: np.ndarray  # T_primary_secondary
    score: float  # overlap score (fraction of source points, kernel weighted)
    seeds: int  # how many seeds ended here


@dataclass(frozen=True)
class IntraResult:
    """A refined ``T_primary_secondary`` with its 1-sigma, or a refusal with its reason."""

    T_init: np.ndarray
    T: np.ndarray  # refined (the coarse winner or T_init when refused before the finish)
    accepted: bool
    reason: str
    cov: np.ndarray = field(default_factory=lambda: np.full((6, 6), np.nan))  # [rot, trans]
    std_deg: float = float("nan")  # largest rotation 1-sigma
    std_m: float = float("nan")  # largest translation 1-sigma
    overlap: float = 0.0  # kernel-weighted overlap of the refined result
    rmse_m: float = float("nan")  # inlier RMSE at the finest stage
    minima: tuple[Minimum, ...] = ()
    seconds: float = 0.0

    @property
    def correction(self) -> tuple[float, float]:
        """(deg, m) from the published start to the result."""
        return pose_distance(self.T_init, self.T)


def pose_distance(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """(rotation deg, translation m) between two poses of the same sensor."""
    d = invert(a) @ b
    return float(np.degrees(np.linalg.norm(so3_log(d[:3, :3])))), float(
        np.linalg.norm(b[:3, 3] - a[:3, 3]))


def nearest_rigid(T: np.ndarray) -> tuple[np.ndarray, float]:
    """The rigid transform nearest ``T`` (its 3x3 block replaced by the rotation of its polar
    decomposition, translation kept) and how far the block was from a rotation (largest
    ``|singular value - 1|``).

    Why: a calibration file's matrix need not be rigid -- the Pandar64/QT64 file's 3x3 has
    singular values 0.989-0.990, a 1.1% scale -- and GICP started from it keeps that scale in
    every result (its updates multiply the start), while ``invert`` (transpose) assumes a
    rotation: both moved the real pair's minimum by ~8 cm (20 m x 1%)."""
    T = np.asarray(T, np.float64)
    U, S, Vt = np.linalg.svd(T[:3, :3])
    out = T.copy()
    out[:3, :3] = U @ np.diag([1.0, 1.0, float(np.linalg.det(U @ Vt))]) @ Vt
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out, float(np.abs(S - 1.0).max())


def euler_zyx(roll_deg: float, pitch_deg: float, yaw_deg: float) -> np.ndarray:
    """R = Rz(yaw) Ry(pitch) Rx(roll) (degrees), the convention of published roll/pitch/yaw."""
    r, p, y = np.radians([roll_deg, pitch_deg, yaw_deg])
    return np.asarray(so3_exp(np.array([0.0, 0.0, y])) @ so3_exp(np.array([0.0, p, 0.0]))
                      @ so3_exp(np.array([r, 0.0, 0.0])))


def _crop(xyz: np.ndarray, c: IntraConfig) -> np.ndarray:
    p = np.asarray(xyz, np.float64).reshape(-1, 3)
    p = p[np.isfinite(p).all(axis=1)]
    r = np.linalg.norm(p, axis=1)
    return np.ascontiguousarray(p[(r >= c.min_range_m) & (r <= c.max_range_m)])


class _Cloud:
    """One voxelised cloud with a k-d tree (small_gicp), made once per voxel; covariances
    only where GICP needs them (the overlap score needs the tree alone, and estimating them
    is most of a cloud's cost)."""

    def __init__(self, sg: Any, xyz: np.ndarray, voxel_m: float, c: IntraConfig,
                 covariances: bool = True) -> None:
        self.cloud = sg.voxelgrid_sampling(xyz, voxel_m, num_threads=c.num_threads)
        self.tree = sg.KdTree(self.cloud, num_threads=c.num_threads)
        if covariances and self.cloud.size() > c.num_neighbors:
            sg.estimate_covariances(self.cloud, self.tree, c.num_neighbors,
                                    num_threads=c.num_threads)
        self.points = np.asarray(self.cloud.points())[:, :3].copy()


class _Prepared:
    """Both clouds at every voxel the refinement needs, cached; ``with_secondary`` shares the
    primary's clouds with another secondary scan (the half-scans of the uncertainty)."""

    def __init__(self, primary: np.ndarray, secondary: np.ndarray, c: IntraConfig,
                 _cache: dict[tuple[str, float, bool], _Cloud] | None = None) -> None:
        import small_gicp

        self.sg, self.c = small_gicp, c
        self.primary, self.secondary = _crop(primary, c), _crop(secondary, c)
        self._cache: dict[tuple[str, float, bool], _Cloud] = _cache or {}

    def with_secondary(self, secondary: np.ndarray) -> _Prepared:
        """The same primary (its prepared clouds reused) against another secondary scan."""
        shared = {k: v for k, v in self._cache.items() if k[0] == "primary"}
        out = _Prepared(np.zeros((0, 3)), secondary, self.c, shared)
        out.primary = self.primary
        return out

    def get(self, which: str, voxel_m: float, covariances: bool = True) -> _Cloud:
        key = (which, voxel_m, covariances)
        if key not in self._cache:
            if not covariances and (which, voxel_m, True) in self._cache:
                return self._cache[(which, voxel_m, True)]
            xyz = self.primary if which == "primary" else self.secondary
            self._cache[key] = _Cloud(self.sg, xyz, voxel_m, self.c, covariances)
        return self._cache[key]

    def align(self, T: np.ndarray, vt: float, vs: float, corr: float, iters: int) -> Any:
        t, s = self.get("primary", vt), self.get("secondary", vs)
        return self.sg.align(t.cloud, s.cloud, t.tree, init_T_target_source=np.asarray(T),
                             registration_type="GICP", max_correspondence_distance=corr,
                             max_iterations=iters, num_threads=self.c.num_threads)

    def score(self, T: np.ndarray) -> float:
        """Kernel-weighted fraction of the source (score voxels) on the primary cloud."""
        c = self.c
        t = self.get("primary", c.score_voxel_m, covariances=False)
        s = self.get("secondary", c.score_voxel_m, covariances=False)
        q = s.points @ T[:3, :3].T + T[:3, 3]
        _, d2 = t.tree.batch_nearest_neighbor_search(np.ascontiguousarray(q),
                                                     num_threads=c.num_threads)
        w = np.clip(1.0 - np.asarray(d2) / c.score_tau_m**2, 0.0, None)
        return float(w.mean()) if len(w) else 0.0


def seed_rotations(c: IntraConfig) -> list[np.ndarray]:
    """Roll/pitch/yaw offsets on the grid (identity first)."""
    n = int(np.floor(c.seed_max_deg / c.seed_step_deg + 1e-9))
    steps = [k * c.seed_step_deg for k in range(-n, n + 1)]
    offsets = sorted(itertools.product(steps, steps, steps), key=lambda o: np.abs(o).sum())
    return [euler_zyx(r, p, y) for r, p, y in offsets]


def _distinct(cands: list[tuple[np.ndarray, float]], c: IntraConfig) -> list[Minimum]:
    """Group end points (best first) into distinct minima: each joins the first (best) minimum
    within ``minimum_sep_*`` of it (``pose_distance``, vectorised over the minima: 125 seeds
    against a handful of minima were a tenth of a refinement in a Python loop)."""
    Ts: list[np.ndarray] = []
    scores: list[float] = []
    counts: list[int] = []
    cos_sep = np.cos(np.radians(c.minimum_sep_deg))
    for T, s in sorted(cands, key=lambda x: -x[1]):
        if Ts:
            A = np.asarray(Ts)
            # angle of R_m^T R: trace(R_m^T R) = sum(R_m * R); translation distance direct
            cos = np.clip((np.einsum("nij,ij->n", A[:, :3, :3], T[:3, :3]) - 1.0) / 2.0,
                          -1.0, 1.0)
            dt = np.linalg.norm(A[:, :3, 3] - T[:3, 3], axis=1)
            hit = np.flatnonzero((cos > cos_sep) & (dt < c.minimum_sep_m))
            if len(hit):
                counts[int(hit[0])] += 1
                continue
        Ts.append(T)
        scores.append(s)
        counts.append(1)
    return [Minimum(T, s, k) for T, s, k in zip(Ts, scores, counts, strict=True)]


def _covariance(r: Any, T: np.ndarray, c: IntraConfig, floor: bool = True) -> np.ndarray:
    """1-sigma covariance [rot rad, trans m] (left perturbation, primary frame) of a GICP
    result: its information scaled by the residuals' variance factor (the Hessian has no
    absolute scale), inflated by ``correlation`` (neighbouring points share their error), plus
    the systematic floor."""
    H = right_to_left_information(np.asarray(r.H, np.float64), T)
    dof = max(3 * int(r.num_inliers) - 6, 1)
    vf = 2.0 * float(r.error) / dof
    w, v = np.linalg.eigh(0.5 * (H + H.T))
    inv_w = np.where(w > 1e-12 * max(w.max(), 1e-300), 1.0 / np.maximum(w, 1e-300), 1e12)
    cov = (v * inv_w) @ v.T * vf * c.correlation
    if not floor:
        return np.asarray(cov)
    f = np.array([np.radians(c.floor_deg)] * 3 + [c.floor_m] * 3) ** 2
    return np.asarray(cov + np.diag(f))


def _split_covariance(P: _Prepared, secondary: np.ndarray, T: np.ndarray,
                      c: IntraConfig) -> np.ndarray:
    """Covariance [rot, trans] of the finish repeated on half-planes of the secondary scan
    (azimuths facing ``split_halves`` directions) about ``T``: how much the result depends on
    which part of the scene it saw."""
    if c.split_halves <= 0:
        return np.zeros((6, 6))
    sec = _crop(secondary, c)
    az = np.arctan2(sec[:, 1], sec[:, 0])
    devs = []
    for k in range(c.split_halves):
        half = sec[np.cos(az - 2.0 * np.pi * k / c.split_halves) > 0.0]
        H = P.with_secondary(half)
        if len(H.get("secondary", c.score_voxel_m, covariances=False).points) < \
                c.min_points // 2:
            continue
        # from the full result, at the finest stage only: the question is where the half's
        # own data pulls, not which basin a wide correspondence distance reaches
        vt, vs, corr = c.fine_stages[-1]
        r = H.align(T, vt, vs, corr, c.fine_iterations)
        Th = np.asarray(r.T_target_source)
        if not r.converged or not np.isfinite(Th).all():
            continue  # still sliding after fine_iterations: a direction this half lacks
        # a half that cannot see a direction (a facade seen from one side, sliding along the
        # street) says nothing about it: keep only the deviation along the directions the
        # half itself observes within the limits (in units of max_std_*)
        S = np.array([1.0 / np.radians(c.max_std_deg)] * 3 + [1.0 / c.max_std_m] * 3)
        N = _covariance(r, Th, c, floor=False) * np.outer(S, S)
        w, v = np.linalg.eigh(0.5 * (N + N.T))
        seen = v[:, w < 1.0]
        dn = _tangent(T, Th) * S
        devs.append((seen @ (seen.T @ dn)) / S)
    if not devs:
        return np.zeros((6, 6))
    d = np.array(devs)
    return np.asarray(d.T @ d / len(d))


def _max_std(cov: np.ndarray) -> tuple[float, float]:
    """Largest 1-sigma over any rotation / translation direction (eigenvalues of each block:
    a degenerate direction need not be an axis)."""
    wr = np.linalg.eigvalsh(cov[:3, :3])
    wt = np.linalg.eigvalsh(cov[3:, 3:])
    return float(np.degrees(np.sqrt(max(wr.max(), 0.0)))), float(np.sqrt(max(wt.max(), 0.0)))


def refine_extrinsic(primary: np.ndarray, secondary: np.ndarray, T_init: np.ndarray,
                     config: IntraConfig | None = None) -> IntraResult:
    """``T_primary_secondary`` of a secondary LiDAR from its coarse ``T_init``; ``primary`` and
    ``secondary`` are (N, 3) points of scans taken at (nearly) the same time, each in its own
    sensor frame (deskewed to a common instant where the agent moves)."""
    c = config or IntraConfig()
    t0 = time.perf_counter()
    # a non-rigid start would make every result non-rigid (see nearest_rigid): start from
    # the nearest rigid transform and say so
    T_init, scale_dev = nearest_rigid(T_init)
    note = (f"; the start was not rigid (scale off by {scale_dev * 100:.2f}%): its nearest "
            "rotation used" if scale_dev > 1e-4 else "")

    def refuse(reason: str, T: np.ndarray | None = None, minima: tuple[Minimum, ...] = (),
               overlap: float = 0.0) -> IntraResult:
        return IntraResult(T_init, T_init if T is None else T, False, reason + note,
                           overlap=overlap, minima=minima, seconds=time.perf_counter() - t0)

    P = _Prepared(primary, secondary, c)
    n_src = len(P.get("secondary", c.score_voxel_m, covariances=False).points)
    if n_src < c.min_points or \
            len(P.get("primary", c.score_voxel_m, covariances=False).points) < c.min_points:
        return refuse(f"too few points ({n_src} secondary voxels < {c.min_points})")

    # 1. search
    cands: list[tuple[np.ndarray, float]] = []
    for dR in seed_rotations(c):
        T = T_init.copy()
        T[:3, :3] = dR @ T_init[:3, :3]
        r = P.align(T, c.coarse_voxel_m, c.coarse_voxel_m, c.coarse_max_correspondence_m,
                    c.coarse_iterations)
        Tc = np.asarray(r.T_target_source)
        if np.isfinite(Tc).all():
            cands.append((Tc, P.score(Tc)))
    if not cands:
        return refuse("no seed converged")
    coarse = _distinct(cands, c)
    polished = []
    for m in coarse[:c.polish_top]:
        r = P.align(m.T, c.polish_voxel_m, c.polish_voxel_m, c.polish_max_correspondence_m,
                    c.polish_iterations)
        Tp = np.asarray(r.T_target_source)
        if np.isfinite(Tp).all():
            polished.append((Tp, P.score(Tp)))
    if not polished:
        return refuse("no minimum survived polishing")
    minima = tuple(_distinct(polished, c))
    best = minima[0]
    # 2. refusal of a wrong minimum
    if best.score < c.min_overlap:
        return refuse(f"not supported by the data: overlap {best.score:.2f} < "
                      f"{c.min_overlap:.2f}", best.T, minima, best.score)
    for other in minima[1:]:
        if other.score >= c.ambiguity_ratio * best.score:
            dr, dt = pose_distance(best.T, other.T)
            return refuse(f"ambiguous: a minimum {dr:.1f} deg / {dt * 100:.0f} cm away scores "
                          f"{other.score:.3f} vs {best.score:.3f}", best.T, minima, best.score)
    # 3. finish
    T = best.T
    r = None
    for vt, vs, corr in c.fine_stages:
        r = P.align(T, vt, vs, corr, c.fine_iterations)
        T = np.asarray(r.T_target_source)
    assert r is not None
    overlap = P.score(T)
    dr, dt = pose_distance(best.T, T)
    if not np.isfinite(T).all() or dr > c.finish_max_deg or dt > c.finish_max_m:
        return refuse(f"the finish left the coarse minimum ({dr:.1f} deg / {dt * 100:.0f} cm)",
                      best.T, minima, best.score)
    cr, ct = pose_distance(T_init, T)
    if cr > c.max_correction_deg or ct > c.max_correction_m:
        return refuse(f"correction {cr:.1f} deg / {ct * 100:.0f} cm beyond the searched "
                      f"{c.max_correction_deg:.0f} deg / {c.max_correction_m * 100:.0f} cm",
                      T, minima, overlap)
    # 4. uncertainty
    cov_formal = _covariance(r, T, c)
    cov_split = _split_covariance(P, secondary, T, c)
    cov = cov_formal + cov_split
    sd, sm = _max_std(cov)
    rmse = float(np.sqrt(2.0 * float(r.error) / max(int(r.num_inliers), 1)))
    res = IntraResult(T_init, T, True, "", cov, sd, sm, overlap, rmse, minima,
                      time.perf_counter() - t0)
    if sd > c.max_std_deg or sm > c.max_std_m:
        # which part is too large says why: the formal part (the geometry leaves a direction
        # unconstrained) or the half-scans' spread (the data fit, but parts of the scene pull
        # the extrinsic to different places: motion, timing, a non-rigid cloud)
        fd, fm = _max_std(cov_formal)
        hd, hm = _max_std(cov_split)
        why = ("half-scans disagree: their spread alone is "
               f"{hd:.2f} deg / {hm * 100:.1f} cm" if hd / c.max_std_deg + hm / c.max_std_m
               > fd / c.max_std_deg + fm / c.max_std_m else "degenerate geometry")
        return IntraResult(T_init, T, False,
                           f"not observed: 1-sigma {sd:.2f} deg / {sm * 100:.1f} cm > "
                           f"{c.max_std_deg} deg / {c.max_std_m * 100:.0f} cm ({why})" + note,
                           cov, sd, sm, overlap, rmse, minima, res.seconds)
    second = minima[1].score / best.score if len(minima) > 1 else 0.0
    reason = (f"refined {cr:.1f} deg / {ct * 100:.1f} cm from the published start; "
              f"{len(minima)} minima, next best scores {second:.2f} of the best; "
              f"overlap {overlap:.2f}{note}")
    return IntraResult(T_init, T, True, reason, cov, sd, sm, overlap, rmse, minima,
                       res.seconds)


@dataclass(frozen=True)
class Pooled:
    """Several estimates of one rig's ``T_primary_secondary`` combined."""

    T: np.ndarray | None
    accepted: bool
    reason: str
    cov: np.ndarray
    std_deg: float
    std_m: float
    used: tuple[int, ...]  # indices of the estimates that agreed and were pooled
    spread_deg: float = float("nan")  # largest disagreement among the used ones
    spread_m: float = float("nan")


def _tangent(T_ref: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Left correction of T relative to T_ref as [rot rad, trans m] (primary frame)."""
    d = T @ invert(T_ref)
    return np.concatenate([so3_log(d[:3, :3]), T[:3, 3] - T_ref[:3, 3]])


def combine(results: list[IntraResult], config: IntraConfig | None = None) -> Pooled:
    """Pool the accepted estimates of one rig (frames or scenes): the medoid's agreeing ones
    (within ``agree_*``) must be at least ``min_agreeing`` and more than ``agree_fraction`` of
    the accepted; otherwise the estimates disagree and nothing is vouched for."""
    c = config or IntraConfig()
    nan6 = np.full((6, 6), np.nan)
    ok = [i for i, r in enumerate(results) if r.accepted]
    refused = len(results) - len(ok)
    if len(ok) < c.min_agreeing:
        return Pooled(None, False, f"{len(ok)} accepted estimates of {len(results)} "
                      f"(< {c.min_agreeing}): nothing to check the rig against", nan6,
                      float("nan"), float("nan"), tuple(ok))
    Ts = [results[i].T for i in ok]
    D = np.array([[pose_distance(a, b) for b in Ts] for a in Ts])  # (n, n, 2)
    norm = D[..., 0] / c.agree_deg + D[..., 1] / c.agree_m
    med = int(np.argmin(norm.sum(axis=1)))
    agree = [j for j in range(len(Ts))
             if D[med, j, 0] <= c.agree_deg and D[med, j, 1] <= c.agree_m]
    used = tuple(ok[j] for j in agree)
    if len(agree) < c.min_agreeing or len(agree) <= c.agree_fraction * len(Ts):
        worst = int(np.argmax(norm[med]))
        return Pooled(None, False, f"estimates disagree: {len(agree)} of {len(Ts)} within "
                      f"{c.agree_deg} deg / {c.agree_m * 100:.0f} cm of the medoid (the "
                      f"farthest {D[med, worst, 0]:.2f} deg / {D[med, worst, 1] * 100:.1f} cm)",
                      nan6, float("nan"), float("nan"), used)
    xi = np.array([_tangent(Ts[med], Ts[j]) for j in agree])
    m = xi.mean(axis=0)
    T = np.eye(4)
    T[:3, :3] = so3_exp(m[:3]) @ Ts[med][:3, :3]
    T[:3, 3] = Ts[med][:3, 3] + m[3:]
    n = len(agree)
    # the floor is systematic (shared by all frames): it does not average out; the formal
    # part does; the spread between frames is an honest check on both
    floor = np.diag(np.array([np.radians(c.floor_deg)] * 3 + [c.floor_m] * 3) ** 2)
    formal = np.mean([results[ok[j]].cov for j in agree], axis=0) - floor
    spread = np.cov(xi.T) if n >= 2 else np.zeros((6, 6))
    cov = formal / n + spread / n + floor
    sd, sm = _max_std(cov)
    sp = D[np.ix_(agree, agree)]
    spread_deg, spread_m = float(sp[..., 0].max()), float(sp[..., 1].max())
    out = [f"pooled {n} of {len(results)} estimates (spread {spread_deg:.2f} deg / "
           f"{spread_m * 100:.1f} cm)"]
    if n < len(ok):
        out.append(f"{len(ok) - n} disagreeing left out")
    if refused:
        out.append(f"{refused} refused")
    if sd > c.max_std_deg or sm > c.max_std_m:
        return Pooled(T, False, "; ".join(out) + f"; 1-sigma {sd:.2f} deg / {sm * 100:.1f} cm "
                      "too large", cov, sd, sm, used, spread_deg, spread_m)
    return Pooled(T, True, "; ".join(out), cov, sd, sm, used, spread_deg, spread_m)
