"""Cross-agent LiDAR registration: eq. 1a from poses, eq. 1b GICP refinement, and its quality.

``T_L1_L2`` maps points of the other agent's deskewed scan (LiDAR 2 at its scan start) into
the reference agent's (LiDAR 1 at its scan start). Eq. 1a chains four transforms whose
small errors add up (INS attitude, RTK position, two extrinsics), so GICP refines it; a
refinement is accepted only if the clouds actually overlap (fitness, inliers) and the
correction stays within what the pose errors can explain, otherwise the initial estimate is
kept and the frame is flagged with the reason. Consecutive frames share the pose errors
(they drift slowly), so each frame starts from the previous accepted correction.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from v2xlake.tasks.geometry import apply, compose, invert, rotation_angle
from v2xlake.tasks.interpolate import PoseTrack
from v2xlake.tasks.register.backends import Prepared, RegistrationBackend
from v2xlake.tasks.register.config import QualitySection


def initial_transform(T_W_I1: np.ndarray, T_W_I2: np.ndarray, T_I1_L1: np.ndarray,
                      T_I2_L2: np.ndarray) -> np.ndarray:
    """Eq. 1a: ``T_L1_L2 = (T_I1_L1)^-1 (T_W_I1)^-1 T_W_I2 T_I2_L2``."""
    return invert(T_I1_L1) @ invert(T_W_I1) @ T_W_I2 @ T_I2_L2


def initial_transform_at(track1: PoseTrack, track2: PoseTrack, T_I1_L1: np.ndarray,
                         T_I2_L2: np.ndarray, t1_ns: int, t2_ns: int | None = None) -> np.ndarray:
    """Eq. 1a with INS poses interpolated (eq. 2) at each scan's reference time.

    Both agents are PPS-synchronised, so their scans start at the same instants and
    ``t2_ns`` defaults to ``t1_ns``; each deskewed scan lives at its own scan start.
    """
    w1 = track1.matrices(t1_ns)[0]
    w2 = track2.matrices(t1_ns if t2_ns is None else t2_ns)[0]
    return initial_transform(w1, w2, T_I1_L1, T_I2_L2)


def transform_delta(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """(metres, degrees) between two estimates of the same transform: where the source
    origin lands, and the angle of ``R_b R_a^T``."""
    dt = float(np.linalg.norm(b[:3, 3] - a[:3, 3]))
    ang = float(np.degrees(rotation_angle(compose(b, invert(a)))))
    return dt, ang


@dataclass(frozen=True)
class PairResult:
    T_init: np.ndarray  # eq. 1a
    T_start: np.ndarray  # where GICP started (warm start from the previous correction)
    T_refined: np.ndarray  # what GICP returned, accepted or not
    T_final: np.ndarray  # T_refined if accepted, else T_init
    fitness: float
    inlier_rmse: float
    n_inliers: int
    correction_m: float  # T_refined relative to T_init
    correction_deg: float
    accepted: bool
    reason: str
    iterations: int
    seconds: float  # GICP + quality (preparation of the clouds not included)
    observability: float = float("nan")
    H: np.ndarray | None = None  # GICP information at T_refined (left perturbation, target)
    sample_short: bool = False  # sparse backend: the source's sample found too few pairs

    @property
    def correction(self) -> np.ndarray:
        """Left correction ``T_final T_init^-1``: what warm-starts the next frame."""
        return self.T_final @ invert(self.T_init)


def evaluate(backend: RegistrationBackend, target: Prepared, source: Prepared, T: np.ndarray,
             distance_m: float, sq_dist: np.ndarray | None = None
             ) -> tuple[float, float, int]:
    """(fitness, inlier RMSE m, inliers) of ``source`` moved by ``T`` against ``target``.

    The RMSE is point to nearest target voxel centroid, so it includes the voxel
    discretisation (about half the target voxel on sparse scans). ``sq_dist``: each source
    row's squared nearest distance already found by the GICP's last search (one update
    before ``T``: at convergence under 0.1 deg / 1 mm), used instead of searching again; a
    NaN row was not in that search and is searched here."""
    pts = source.points if source.sample is None else source.points[source.sample]
    n = len(pts)
    if n == 0 or len(target.points) == 0:
        return 0.0, 0.0, 0
    if sq_dist is not None and len(sq_dist) == n:
        d2 = sq_dist.copy()
        miss = np.isnan(d2)  # rows the last search did not cover: searched here
        if miss.any():
            d2[miss] = backend.nearest_sq_dist(target, apply(T, pts[miss]),
                                               max_dist_m=distance_m)
    else:
        d2 = backend.nearest_sq_dist(target, apply(T, pts), max_dist_m=distance_m)
    inl = d2 <= distance_m**2
    k = int(inl.sum())
    return k / n, float(np.sqrt(d2[inl].mean())) if k else 0.0, k


def observability(H: np.ndarray | None) -> float:
    """How well the matched surfaces pin down translation in every direction: smallest /
    largest eigenvalue of the translation block of the GICP Hessian after eliminating
    rotation (Schur complement). Synthetic streets give 0.2-0.35, a two-wall corridor
    0.003 (GICP slides along it freely). NaN when the backend exposes no Hessian."""
    if H is None or H.shape != (6, 6) or not np.all(np.isfinite(H)):
        return float("nan")
    hrr, hrt, htt = H[:3, :3], H[:3, 3:], H[3:, 3:]
    try:
        s = htt - hrt.T @ np.linalg.solve(hrr, hrt)
    except np.linalg.LinAlgError:
        return 0.0
    w = np.linalg.eigvalsh(0.5 * (s + s.T))
    return float(max(w[0], 0.0) / w[2]) if w[2] > 0 else 0.0


def refine(backend: RegistrationBackend, target: Prepared, source: Prepared, T_init: np.ndarray,
           limits: QualitySection, warm: np.ndarray | None = None) -> PairResult:
    """Eq. 1b with quality control; ``warm`` is the previous frame's left correction."""
    t0 = time.perf_counter()
    starts = [T_init] if warm is None else [warm @ T_init, T_init]
    best: PairResult | None = None
    for start in starts:
        res = _attempt(backend, target, source, T_init, start, limits)
        if best is None or (res.accepted and not best.accepted):
            best = res
        if res.accepted:
            break
    assert best is not None
    return _with_seconds(best, time.perf_counter() - t0)


def _attempt(backend: RegistrationBackend, target: Prepared, source: Prepared,
             T_init: np.ndarray, start: np.ndarray, limits: QualitySection) -> PairResult:
    if len(source.points) < limits.min_inliers or len(target.points) < limits.min_inliers:
        return PairResult(T_init, start, T_init.copy(), T_init, 0.0, 0.0, 0, 0.0, 0.0, False,
                          f"too few points after downsampling (source {len(source.points)}, "
                          f"target {len(target.points)}; need {limits.min_inliers})", 0, 0.0)
    try:
        out = backend.align(target, source, start)
    except Exception as e:  # a backend failure is this frame's reason, never the clip's end
        return failed_pair(T_init, f"{backend.name} GICP failed: {type(e).__name__}: {e}",
                           start)
    T = out.T
    if not np.all(np.isfinite(T)):
        return failed_pair(T_init, "GICP returned a non-finite transform", start)
    fit, rmse, k = evaluate(backend, target, source, T, limits.fitness_distance_m,
                            out.sq_dist)
    obs = observability(out.H)
    dm, ddeg = transform_delta(T_init, T)
    reason = "ok"
    if k < limits.min_inliers:
        reason = f"too little overlap: {k} inliers < {limits.min_inliers}"
    elif fit < limits.min_fitness:
        reason = f"too little overlap: fitness {fit:.3f} < {limits.min_fitness}"
    elif dm > limits.max_correction_m:
        reason = f"diverged: correction {dm:.2f} m > {limits.max_correction_m} m"
    elif ddeg > limits.max_correction_deg:
        reason = f"diverged: correction {ddeg:.2f} deg > {limits.max_correction_deg} deg"
    elif obs < limits.min_observability:  # NaN (no Hessian) never rejects
        reason = (f"degenerate geometry: translation observability {obs:.3f} < "
                  f"{limits.min_observability} (surfaces do not constrain every direction)")
    ok = reason == "ok"
    return PairResult(T_init, start, T, T if ok else T_init, fit, rmse, k, dm, ddeg, ok, reason,
                      out.iterations, 0.0, obs, out.H, out.sample_short)


def failed_pair(T_init: np.ndarray, reason: str, start: np.ndarray | None = None
                ) -> PairResult:
    """A frame pair with no usable GICP result: the eq. 1a estimate is kept, with the reason."""
    return PairResult(T_init, T_init if start is None else start, T_init.copy(), T_init, 0.0,
                      0.0, 0, 0.0, 0.0, False, reason, 0, 0.0)


def _with_seconds(r: PairResult, s: float) -> PairResult:
    from dataclasses import replace

    return replace(r, seconds=s)
