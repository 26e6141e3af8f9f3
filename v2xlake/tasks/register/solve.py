"""Clip-level registration solve (issue #13): per-frame GICP results are measurements, not
answers.

Why: on a street of parallel walls one frame's GICP is blind along the street (its
information matrix says so), and a wrong LiDAR extrinsic is the same error in every frame.
Frame by frame, eq. 1b can only reject such frames (and keep eq. 1a's decimetres) or accept a
slide. What is constant or slow over a clip is estimated once, from all frames, each weighted
by what it actually constrains.

Model. Every agent ``a``'s LiDAR pose in the world is

    T_W_La(t) = C_a(t) M_a(t) E_a exp(eps_a),     C_a(t) M = [Exp(omega_a) R_M, p_M + v_a(t)]

with ``M_a`` its INS pose (eq. 1a's ``T_W_Ia``), ``E_a`` its published extrinsic, ``eps_a`` a
constant extrinsic correction (LiDAR frame, 6), ``omega_a`` a constant INS attitude bias
(world axes, 3) and ``v_a(t)`` the INS position error (world, piecewise linear over knots
``knot_s`` apart: INS drift of a few cm/s is smooth). ``exp([w, t]) := [Exp(w), t]``.

Measurements (each a 6-vector residual ``[rotvec, trans]`` of ``Z T_model^-1``, whitened by
its GICP information ``W`` (left perturbation in the target frame, see ``backends``)):

* cross-agent, frame k: ``Z = T_L1_Lj`` from GICP; model ``T_W_L1(t_k)^-1 T_W_Lj(t_k)``;
* odometry of agent a over (t0, t1) (hand-eye): ``Z = T_La(t0)_La(t1)`` from GICP between the
  agent's own scans; model ``T_W_La(t0)^-1 T_W_La(t1)``. This is what separates a wrong
  extrinsic from INS drift: the INS says how the body moved, the scans how the LiDAR moved;
  a turn makes every direction of the extrinsic but its height observable (planar motion
  leaves the extrinsic's z and the INS height bias indistinguishable: the prior decides and
  the covariance says so).

Priors (metric, ``SolveSection``): extrinsic corrections, attitude bias, the drift's level,
rate and acceleration between knots. A degenerate frame (blind along the street) contributes
nothing in its blind direction, which the smooth ``v_a`` and the constant ``eps_a`` carry over
from frames that see it (turns, intersections, poles).

An INS position step (found in the pose track by the stage) gets a free world offset of that
agent's ``v_a`` from the step on (``steps``), so it is neither smoothed into the drift nor
absorbed into ``eps_a``.

Solver: Levenberg-Marquardt on the normal equations (``_gauss_newton``), analytic Jacobians.

Robustness. GICP's Hessian has no absolute scale (plane-regularised covariances, correlated
points), so a variance factor is estimated from the residuals (median chi^2, 6 dof), and each
frame gets a Cauchy weight on its whitened residual norm (iteratively reweighted least
squares): the binary accept/reject gate becomes a weight. Afterwards every cross-agent frame
is tested against the solution of all OTHER frames (leave-one-out, closed form on the
linearised problem): a frame whose own GICP result disagrees beyond the ``outlier_p`` chi^2
quantile is an outlier, flagged with its reason.

Honest uncertainty. A frame's reported covariance is the clip's plus the per-frame floor (a
systematic error shared by neighbouring frames does not average out), with the measurements'
information counted once per ``correlation_s`` (consecutive GICP errors are correlated), and
``bracketing`` refuses what the clip would only extrapolate: a direction a frame did not
observe itself needs observing frames before and after it within ``max_bridge_s``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from v2xlake.tasks.geometry import compose, invert, se3_adjoint, so3_exp, so3_log
from v2xlake.tasks.register.config import SolveSection


def chi2_isf(p: float, dof: int) -> float:
    """The chi-square quantile exceeded with probability ``p`` (``scipy.stats.chi2.isf``):
    through ``scipy.special``, which SciPy's spatial module has already loaded, because
    importing ``scipy.stats`` took 1.0-1.2 s of every register stage's run."""
    from scipy.special import chdtri

    return float(chdtri(dof, p))


def normal_sf(x: float) -> float:
    """P(Z > x) for a standard normal (``scipy.stats.norm.sf``), as :func:`chi2_isf`."""
    from scipy.special import ndtr

    return float(ndtr(-x))


# ------------------------------------------------------------------ small SE(3) kit
def se3_exp(x: np.ndarray) -> np.ndarray:
    """``exp([w, t]) = [Exp(w), t]`` (the perturbation the GICP information is for)."""
    x = np.asarray(x, np.float64)
    out = np.zeros((*x.shape[:-1], 4, 4))
    out[..., :3, :3] = so3_exp(x[..., :3])
    out[..., :3, 3] = x[..., 3:]
    out[..., 3, 3] = 1.0
    return out


def se3_left_residual(Z: np.ndarray, T: np.ndarray) -> np.ndarray:
    """``[rotvec, trans]`` of ``Z T^-1``: the left perturbation taking ``T`` to ``Z``."""
    E = Z @ invert(T)
    return np.concatenate([so3_log(E[..., :3, :3]), E[..., :3, 3]], -1)


# ------------------------------------------------------------------ inputs and settings
@dataclass(frozen=True)
class CrossMeasurement:
    """Frame k: GICP's ``T_L1_Lj`` (None when GICP gave nothing) and its information."""

    key: int  # the caller's frame id
    other: str
    t_s: float
    M_ref: np.ndarray  # INS T_W_I1 at the reference scan's time
    M_oth: np.ndarray  # INS T_W_Ij at the other scan's time
    Z: np.ndarray | None
    W: np.ndarray | None
    t_oth_s: float | None = None

    @property
    def usable(self) -> bool:
        return self.Z is not None and self.W is not None and bool(np.isfinite(self.W).all())


DEFAULT_SOLVE = SolveSection()  # frozen: one shared default

@dataclass(frozen=True)
class OdoMeasurement:
    """An agent's own scans at t0 and t1: GICP's ``T_La(t0)_La(t1)`` and its information."""

    agent: str
    t0_s: float
    t1_s: float
    M0: np.ndarray
    M1: np.ndarray
    Z: np.ndarray
    W: np.ndarray


@dataclass
class ClipSolution:
    agents: list[str]
    eps: dict[str, np.ndarray]  # agent -> (6,) extrinsic correction [rot, trans]
    eps_cov: dict[str, np.ndarray]  # agent -> (6, 6)
    omega: dict[str, np.ndarray]
    T_cross: np.ndarray  # (N, 4, 4) model T_L1_Lj per cross measurement
    cross_cov: np.ndarray  # (N, 6, 6) covariance of each model T_L1_Lj (left, L1 frame)
    weight: np.ndarray  # (N,) robust weight of each cross measurement (0: unusable)
    chi2: np.ndarray  # (N,) whitened residual^2 / variance factor (NaN: unusable)
    loo_chi2: np.ndarray  # (N,) leave-one-out statistic (NaN: unusable)
    outlier: np.ndarray  # (N,) bool
    variance_factor: float
    odo_weight: np.ndarray
    information: np.ndarray | None = None  # (N, 6, 6) metric information used (rad, m)
    loo_limit: float = float("inf")
    seconds: float = 0.0
    n_params: int = 0
    notes: list[str] = field(default_factory=list)
    # (N,) "" where the frame's own GICP observed every direction or frames that observed
    # the missing ones bracket it within ``max_bridge_s``; otherwise why not (not accepted)
    unbracketed: list[str] = field(default_factory=list)
    # agent -> fraction of the cross-agent frames it takes part in that are outliers
    outlier_fraction: dict[str, float] = field(default_factory=dict)
    steps: list[tuple[str, float]] = field(default_factory=list)  # modelled INS steps


# ------------------------------------------------------------------ the problem
def _hat(p: np.ndarray) -> np.ndarray:
    K = np.zeros((len(p), 3, 3))
    K[:, 0, 1], K[:, 0, 2] = -p[:, 2], p[:, 1]
    K[:, 1, 0], K[:, 1, 2] = p[:, 2], -p[:, 0]
    K[:, 2, 0], K[:, 2, 1] = -p[:, 1], p[:, 0]
    return K


class _Problem:
    """Parameters per agent: ``[eps (6), omega (3), v at each knot (3 n_k)]``."""

    def __init__(self, agents: list[str], extr: dict[str, np.ndarray],
                 cross: list[CrossMeasurement], odo: list[OdoMeasurement],
                 s: SolveSection, ref: str,
                 steps: list[tuple[str, float]] | None = None) -> None:
        self.agents, self.s, self.ref = agents, s, ref
        times = [c.t_s for c in cross] + [c.t_oth_s or c.t_s for c in cross]
        times += [o.t0_s for o in odo] + [o.t1_s for o in odo]
        t0, t1 = (min(times), max(times)) if times else (0.0, 1.0)
        self.n_k = max(2, int(np.ceil((t1 - t0) / s.knot_s - 1e-9)) + 1)
        self.knots = t0 + s.knot_s * np.arange(self.n_k)
        self.per_agent = 9 + 3 * self.n_k
        # a step of an agent's INS track (detected in its poses) at time t: a free world
        # offset of its position error from t on (3 parameters after all agents' blocks)
        self.steps = [(a, float(t)) for a, t in (steps or []) if a in agents]
        self.n_base = self.per_agent * len(agents)
        self.n = self.n_base + 3 * len(self.steps)
        self.idx = {a: i * self.per_agent for i, a in enumerate(agents)}
        self.E = {a: extr[a] for a in agents}
        self.P = self._prior_matrix()
        self.ground: dict[str, tuple[float, float]] = {}
        # straight odometry pairs: (agent, measured T_La0_La1)
        self.nh = [(o.agent, o.Z) for o in odo
                   if np.degrees(np.linalg.norm(so3_log(o.Z[:3, :3]))) < s.straight_deg
                   and np.linalg.norm(o.Z[:3, 3]) >= s.nonholonomic_min_m]

    def ground_rows(self, th: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One residual per agent with a measured ground distance and a declared body: the
        corrected LiDAR origin's height above the ego frame's ground plane."""
        agents = sorted(self.ground)
        r = np.zeros(len(agents))
        J = np.zeros((len(agents), self.n))
        sig = self.s.ground_sigma_m
        for i, a in enumerate(agents):
            h, g = self.ground[a]
            e = self.eps(th, a)

            def height(eps: np.ndarray, a: str = a, g: float = g) -> float:
                return float((self.E[a] @ se3_exp(eps))[2, 3] - g)

            r[i] = (height(e) - h) / sig
            for k in range(6):
                d = np.zeros(6)
                d[k] = 1e-6
                J[i, self.idx[a] + k] = (height(e + d) - height(e - d)) / (2e-6 * sig)
        return r, J

    def nonholonomic(self, th: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Residuals (2 per straight odometry pair: lateral and vertical direction of the
        body's displacement, radians / sigma) and their Jacobian (finite differences in the
        agent's extrinsic correction only, batched per agent)."""
        if not self.nh:
            return np.zeros(0), np.zeros((0, self.n))
        sig = np.radians(self.s.nonholonomic_deg)
        agents = [a for a, _ in self.nh]
        Zs = np.stack([Z for _, Z in self.nh])

        def res(eps: np.ndarray, Z: np.ndarray, E: np.ndarray) -> np.ndarray:
            Ep = E @ se3_exp(eps)
            Tb = Ep @ Z @ invert(Ep)  # ego(t0) <- ego(t1), (m, 4, 4)
            # constant curvature: the chord leaves at half the heading change
            half = 0.5 * np.arctan2(Tb[:, 1, 0], Tb[:, 0, 0])
            d = Tb[:, :3, 3]
            lat = -np.sin(half) * d[:, 0] + np.cos(half) * d[:, 1]
            n = np.maximum(np.linalg.norm(d, axis=1), 1e-9)
            return np.stack([lat / n, d[:, 2] / n], 1)

        r = np.zeros((len(self.nh), 2))
        J = np.zeros((len(self.nh), 2, self.n))
        h = 1e-6
        for a in set(agents):
            m = np.array([x == a for x in agents])
            e, Z, E = self.eps(th, a), Zs[m], self.E[a]
            r[m] = res(e, Z, E) / sig
            for k in range(6):
                d = np.zeros(6)
                d[k] = h
                J[m, :, self.idx[a] + k] = (res(e + d, Z, E) - res(e - d, Z, E)) / (2 * h * sig)
        return r.ravel(), J.reshape(-1, self.n)

    def eps(self, th: np.ndarray, a: str) -> np.ndarray:
        return th[self.idx[a]:self.idx[a] + 6]

    def omega(self, th: np.ndarray, a: str) -> np.ndarray:
        return th[self.idx[a] + 6:self.idx[a] + 9]

    def knots_v(self, th: np.ndarray, a: str) -> np.ndarray:
        i = self.idx[a] + 9
        return th[i:i + 3 * self.n_k].reshape(self.n_k, 3)

    def interp_w(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Knot indices i, i+1 and the weight of i+1 for each time (linear, clamped)."""
        u = np.clip((np.asarray(t, np.float64) - self.knots[0]) / self.s.knot_s, 0.0,
                    self.n_k - 1 - 1e-9)
        i = np.floor(u).astype(np.int64)
        return i, i + 1, u - i

    def world_lidar(self, th: np.ndarray, a: str, M: np.ndarray, t: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Corrected ``T_W_La`` (N, 4, 4) and, for the Jacobian, the d(world-left twist)/d
        (agent's parameters) (N, 6, per_agent) and the corrected ego positions."""
        i0, i1, w = self.interp_w(t)
        V = self.knots_v(th, a)
        v = V[i0] * (1 - w)[:, None] + V[i1] * w[:, None]
        C = M.copy()
        C[:, :3, :3] = so3_exp(self.omega(th, a)) @ M[:, :3, :3]
        C[:, :3, 3] = M[:, :3, 3] + v + self.step_offset(th, a, t)
        L = C @ (self.E[a] @ se3_exp(self.eps(th, a)))
        n = len(M)
        D = np.zeros((n, 6, self.per_agent))
        D[:, :, :6] = se3_adjoint(L)  # eps: L exp(d) = exp(Ad_L d) L
        D[:, :3, 6:9] = np.eye(3)  # omega: a world rotation about the ego position
        D[:, 3:, 6:9] = _hat(C[:, :3, 3])
        r = np.arange(n)
        for k in range(3):
            D[r, 3 + k, 9 + 3 * i0 + k] = 1 - w
            D[r, 3 + k, 9 + 3 * i1 + k] += w
        return L, D, C[:, :3, 3]

    def step_offset(self, th: np.ndarray, a: str, t: np.ndarray) -> np.ndarray:
        out = np.zeros((len(np.atleast_1d(t)), 3))
        for i, (b, ts) in enumerate(self.steps):
            if b == a:
                c = self.n_base + 3 * i
                out += np.where((np.asarray(t) >= ts)[:, None], th[c:c + 3][None, :], 0.0)
        return out

    def step_jac(self, a: str, t: np.ndarray) -> np.ndarray:
        """d(world-left twist of the agent's LiDAR)/d(step offsets) (N, 6, n)."""
        D = np.zeros((len(t), 6, self.n))
        for i, (b, ts) in enumerate(self.steps):
            if b == a:
                c = self.n_base + 3 * i
                on = np.asarray(t) >= ts
                D[on, 3:, c:c + 3] = np.eye(3)
        return D

    def _pairs(self, th: np.ndarray, a1: list[str], M1: np.ndarray, t1: np.ndarray,
               a2: list[str], M2: np.ndarray, t2: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
        """``T = L_a1^-1 L_a2`` per row and d(left perturbation of T)/d(theta) (N, 6, n)."""
        n = len(M1)
        T = np.zeros((n, 4, 4))
        G = np.zeros((n, 6, self.n))
        L1 = np.zeros((n, 4, 4))
        D1 = np.zeros((n, 6, self.per_agent))
        L2 = np.zeros((n, 4, 4))
        D2 = np.zeros((n, 6, self.per_agent))
        for a in set(a1):
            m = np.array([x == a for x in a1])
            L1[m], D1[m], _ = self.world_lidar(th, a, M1[m], t1[m])
        for a in set(a2):
            m = np.array([x == a for x in a2])
            L2[m], D2[m], _ = self.world_lidar(th, a, M2[m], t2[m])
        L1i = invert(L1)
        T = L1i @ L2
        Ad = se3_adjoint(L1i)
        g1 = -Ad @ D1  # a world twist on L1 moves T by -Ad(L1^-1) xi
        g2 = Ad @ D2
        r = np.arange(n)
        for a in set(a1) | set(a2):
            b = self.idx[a]
            sl = slice(b, b + self.per_agent)
            m1 = np.array([x == a for x in a1])
            m2 = np.array([x == a for x in a2])
            G[r[m1], :, sl] += g1[m1]
            G[r[m2], :, sl] += g2[m2]
            if self.steps:
                G[r[m1]] -= Ad[m1] @ self.step_jac(a, t1[m1])
                G[r[m2]] += Ad[m2] @ self.step_jac(a, t2[m2])
        return T, G

    def cross_model(self, th: np.ndarray, cross: list[CrossMeasurement]
                    ) -> tuple[np.ndarray, np.ndarray]:
        if not cross:
            return np.zeros((0, 4, 4)), np.zeros((0, 6, self.n))
        return self._pairs(
            th, [self.ref] * len(cross), np.stack([c.M_ref for c in cross]),
            np.array([c.t_s for c in cross]), [c.other for c in cross],
            np.stack([c.M_oth for c in cross]),
            np.array([c.t_oth_s if c.t_oth_s is not None else c.t_s for c in cross]))

    def odo_model(self, th: np.ndarray, odo: list[OdoMeasurement]
                  ) -> tuple[np.ndarray, np.ndarray]:
        if not odo:
            return np.zeros((0, 4, 4)), np.zeros((0, 6, self.n))
        ag = [o.agent for o in odo]
        return self._pairs(th, ag, np.stack([o.M0 for o in odo]), np.array([o.t0_s for o in odo]),
                           ag, np.stack([o.M1 for o in odo]), np.array([o.t1_s for o in odo]))

    def _prior_matrix(self) -> np.ndarray:
        """Priors are linear in theta: rows of ``P theta`` (metric, in standard deviations)."""
        s, dt, nk = self.s, self.s.knot_s, self.n_k
        rows: list[np.ndarray] = []
        for a in self.agents:
            b = self.idx[a]

            def row(cols: dict[int, float], b: int = b) -> None:
                r = np.zeros(self.n)
                for c, v in cols.items():
                    r[b + c] = v
                rows.append(r)

            for k in range(3):
                row({k: 1 / np.radians(s.prior_ext_deg)})
                row({3 + k: 1 / s.prior_ext_m})
                row({6 + k: 1 / np.radians(s.prior_att_deg)})
                row({9 + 3 * i + k: 1 / (nk * s.prior_pos_m) for i in range(nk)})
                for i in range(nk - 1):
                    row({9 + 3 * (i + 1) + k: 1 / (s.prior_drift_mps * dt),
                         9 + 3 * i + k: -1 / (s.prior_drift_mps * dt)})
                for i in range(nk - 2):
                    q = 1 / (s.prior_drift_accel * dt * dt)
                    row({9 + 3 * i + k: q, 9 + 3 * (i + 1) + k: -2 * q, 9 + 3 * (i + 2) + k: q})
        for i in range(len(self.steps)):
            for k in range(3):
                r = np.zeros(self.n)
                r[self.n_base + 3 * i + k] = 1 / s.prior_pos_m
                rows.append(r)
        return np.array(rows)


def weak_directions(H: np.ndarray, ratio: float) -> list[np.ndarray]:
    """Translation directions (unit 3-vectors) a GICP Hessian barely constrains: the
    eigen-directions of its translation block after eliminating rotation (the
    ``observability`` of ``core``) below ``ratio`` of the strongest."""
    if ratio <= 0:
        return []
    H = 0.5 * (H + H.T)
    try:
        S = H[3:, 3:] - H[3:, :3] @ np.linalg.solve(H[:3, :3], H[:3, 3:])
    except np.linalg.LinAlgError:
        return []
    lam, V = np.linalg.eigh(0.5 * (S + S.T))
    return [V[:, i] for i in range(3) if lam[i] < ratio * max(lam[-1], 0.0)]


def _drop_weak(W: np.ndarray, directions: list[np.ndarray]) -> np.ndarray:
    """``W`` with the translation along each direction marginalised out. Along a street of
    parallel walls GICP's Hessian still claims a little (poles, what filtering left) and the
    scan slides exactly there: trusting that little is how a slide enters a fused solution;
    marginalising it lets the other frames decide."""
    W = 0.5 * (W + W.T)
    for u in directions:
        e = np.concatenate([np.zeros(3), u])
        We = W @ e
        d = float(e @ We)
        if d > 0:
            W = W - np.outer(We, We) / d
    return np.asarray(0.5 * (W + W.T))


def _gauss_newton(fun_jac: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
                  th: np.ndarray, max_iterations: int) -> np.ndarray:
    """Levenberg-Marquardt on the normal equations: the problem is small (about a hundred
    parameters) and nearly linear (corrections of centimetres and tenths of a degree), so a
    few Gauss-Newton steps converge; measured 4-6x faster here than
    ``scipy.optimize.least_squares`` (trf), which spends its time in an SVD per step."""
    f, J = fun_jac(th)
    cost = float(f @ f)
    lam = 1e-8
    for _ in range(max_iterations):
        A, g = J.T @ J, J.T @ f
        d = np.diag(A)
        try:
            step = -np.linalg.solve(A + lam * np.diag(d + 1e-12 * max(d.max(), 1.0)), g)
        except np.linalg.LinAlgError:
            lam *= 10
            continue
        f2, J2 = fun_jac(th + step)
        cost2 = float(f2 @ f2)
        if cost2 <= cost:
            th, f, J = th + step, f2, J2
            converged = cost - cost2 <= 1e-10 * max(cost, 1e-30)
            cost = cost2
            lam = max(lam / 10, 1e-12)
            if converged:
                break
        else:
            lam *= 10
            if lam > 1e8:
                break
    return th


def _chol_upper(W: np.ndarray) -> np.ndarray:
    """U with U^T U = W (W symmetric PSD; a tiny ridge keeps rank-deficient ones usable)."""
    W = 0.5 * (W + W.T)
    ridge = 1e-12 * max(float(np.trace(W)), 1e-30)
    return np.linalg.cholesky(W + ridge * np.eye(6)).T


def _cauchy_weight(chi: np.ndarray, c: float) -> np.ndarray:
    return 1.0 / (1.0 + (chi / c) ** 2)


def solve_clip(agents: list[str], ref: str, extrinsics: dict[str, np.ndarray],
               cross: list[CrossMeasurement], odo: list[OdoMeasurement],
               settings: SolveSection = DEFAULT_SOLVE,
               ground: dict[str, tuple[float, float]] | None = None,
               steps: list[tuple[str, float]] | None = None) -> ClipSolution:
    """Fuse a clip's per-frame GICP measurements (see the module doc). ``ground``: per agent
    (measured LiDAR height above the ground, the ground's z in the ego frame from the
    declared body). The dense algebra is small (hundreds of rows, about a hundred
    parameters): one BLAS thread."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1):
        return _solve_clip(agents, ref, extrinsics, cross, odo, settings, ground or {},
                           steps or [])


def _solve_clip(agents: list[str], ref: str, extrinsics: dict[str, np.ndarray],
                cross: list[CrossMeasurement], odo: list[OdoMeasurement],
                settings: SolveSection, ground: dict[str, tuple[float, float]],
                steps: list[tuple[str, float]]) -> ClipSolution:
    t_start = time.perf_counter()
    s = settings
    P = _Problem(agents, extrinsics, cross, odo, s, ref, steps)
    P.ground = {a: g for a, g in ground.items() if a in agents and np.isfinite(g).all()}
    usable = [k for k, c in enumerate(cross) if c.usable]
    uc = [cross[k] for k in usable]
    n_c, n_o = len(uc), len(odo)

    # GICP's Hessian (plane-regularised covariances) is close to metric information as it
    # is (variance factor 1.1-1.2 measured on the hard street at test resolution); the
    # factor is re-estimated from the residuals when there are enough measurements
    floor = np.diag([np.radians(s.floor_deg) ** 2] * 3 + [s.floor_m**2] * 3)
    # the floor grows with the range between the LiDARs (their point spacing on what both
    # see): one per cross-agent frame, the plain floor for odometry (consecutive scans)
    floors = np.stack([range_floor(c, s) for c in uc] + [floor] * n_o) \
        if n_c + n_o else np.zeros((0, 6, 6))
    Ws = [c.W for c in uc if c.W is not None] + [o.W for o in odo]
    # GICP's own covariance, and its whitening (for the variance factor)
    Cw = np.stack([np.linalg.pinv(0.5 * (W + W.T), rcond=1e-12, hermitian=True)
                   for W in Ws]) if Ws else np.zeros((0, 6, 6))
    Uh = np.stack([_chol_upper(W) for W in Ws]) if Ws else np.zeros((0, 6, 6))
    weak_dirs: list[list[np.ndarray]] = [[] for _ in Ws]

    def effective(vf: float) -> np.ndarray:
        """Whitening of each measurement: GICP's covariance (scaled by the variance factor)
        plus the floor of what its Hessian cannot see (voxel centroids, deskew residuals,
        what static filtering left): ``chol((vf W^+ + F)^-1)``, without the directions that
        information leaves degenerate.

        Degenerate is judged on this effective information, not on the raw Hessian: beside
        thousands of wall points a street's poles and parked cars look like 1 % of the
        information, yet they fix the scan along the street to 1-3 cm -- as well as the floor
        lets any direction be known. Judged on the raw Hessian, every frame of a straight
        boulevard was "blind" along it and the clip reported 2.5 m for frames within 2 cm."""
        if not len(Cw):
            return np.zeros((0, 6, 6))
        infos = [np.linalg.inv(vf * C + F) for C, F in zip(Cw, floors, strict=True)]
        weak_dirs[:] = [weak_directions(I, s.degenerate_ratio) for I in infos]
        return np.stack([_chol_upper(_drop_weak(I, weak))
                         for I, weak in zip(infos, weak_dirs, strict=True)])

    Z = np.stack([c.Z for c in uc if c.Z is not None] + [o.Z for o in odo]) \
        if n_c + n_o else np.zeros((0, 4, 4))
    w = np.concatenate([np.ones(n_c), np.full(n_o, s.odometry_weight)])
    vf = 1.0
    U = effective(vf)
    th = np.zeros(P.n)

    def model(th: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        Tc, Gc = P.cross_model(th, uc)
        To, Go = P.odo_model(th, odo)
        return np.concatenate([Tc, To]), np.concatenate([Gc, Go])

    def residuals(th: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        T, G = model(th)
        return se3_left_residual(Z, T), G

    def fun_jac(th: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r, G = residuals(th)
        f = np.sqrt(np.maximum(w, 0.0))[:, None]
        rw = np.einsum("nij,nj->ni", U, r) * f
        Jw = -np.einsum("nij,njk->nik", U, G) * f[:, :, None]
        rn, Jn = P.nonholonomic(th)
        rg, Jg = P.ground_rows(th)
        return (np.concatenate([rw.ravel(), rn, rg, P.P @ th]),
                np.concatenate([Jw.reshape(-1, P.n), Jn, Jg, P.P]))

    med6 = chi2_isf(0.5, 6)
    for it in range(max(1, s.irls_iterations) + 1):
        th = _gauss_newton(fun_jac, th, s.max_iterations)
        if it == max(1, s.irls_iterations):
            break
        r, _ = residuals(th)
        rh = np.einsum("nij,nj->ni", Uh, r)
        chi_h = np.einsum("ni,ni->n", rh, rh)
        if len(chi_h) >= s.min_for_variance:  # the Hessians' scale, from the median one
            vf = max(float(np.median(chi_h)) / med6, 1e-12)
        U = effective(vf)
        re = np.einsum("nij,nj->ni", U, r)
        w = _cauchy_weight(np.sqrt(np.einsum("ni,ni->n", re, re)), s.robust_scale)
        w[n_c:] *= s.odometry_weight
    _, J_all = fun_jac(th)
    A = J_all.T @ J_all
    A_inv = np.linalg.pinv(A, rcond=1e-13, hermitian=True)
    r, G = residuals(th)
    rw = np.einsum("nij,nj->ni", U, r)  # unweighted, whitened: unit variance for an inlier
    Jw = -np.einsum("nij,njk->nik", U, G)
    chi = np.einsum("ni,ni->n", rw, rw)

    N = len(cross)
    T_all, G_all = P.cross_model(th, cross)
    # the clip covariance shrinks like 1/sqrt(N) as if each frame's floor were independent;
    # a systematic error (voxels, deskew, what filtering left) is shared by neighbouring
    # frames and does not average out: consecutive frames' GICP errors are correlated, so
    # the measurements' information counts once per ``correlation_s`` (the priors as they
    # are), and a frame is never reported better than the floor. The floor is a lower
    # bound, not a second error term: each measurement's whitening already contains it, and
    # adding it again made a 2 s clip's best frame 1.4x the floor (its edges "uncertain"
    # while their own GICP measured them to 1 cm)
    t_use = np.array([c.t_s for c in uc])
    rate = (len(uc) - 1) / max(float(np.ptp(t_use)), 1e-9) if len(uc) > 1 else 1.0
    n_same = len({c.other for c in uc}) or 1
    # (never more frames than the clip has: a clip shorter than that is one measurement)
    corr = max(1.0, min(s.correlation_s * rate, len(uc)) / n_same)
    PtP = P.P.T @ P.P
    A_c = (A - PtP) / corr + PtP
    A_c_inv = np.linalg.pinv(A_c, rcond=1e-13, hermitian=True)
    cov_all = np.einsum("nai,ij,nbj->nab", G_all, A_c_inv, G_all)
    d = np.arange(6)
    cov_all[:, d, d] = np.maximum(cov_all[:, d, d], np.diag(floor))
    weight, chi_all, loo = np.zeros(N), np.full(N, np.nan), np.full(N, np.nan)
    limit = chi2_isf(s.outlier_p, 6)
    for j, k in enumerate(usable):
        weight[k], chi_all[k] = w[j], chi[j]
        # leave-one-out: take this frame's rows (as weighted in the solve) out of the normal
        # equations (a rank-6 downdate, Woodbury), predict its residual from the rest and
        # compare it with the frame's own measurement
        Jk = Jw[j]
        AJ = A_inv @ Jk.T  # (n, 6)
        S = np.eye(6) - w[j] * Jk @ AJ
        g = w[j] * Jk.T @ rw[j]

        def ak_inv(x: np.ndarray, AJ: np.ndarray = AJ, S: np.ndarray = S,
                   Jk: np.ndarray = Jk, wk: float = float(w[j])) -> np.ndarray:
            """(A - w Jk^T Jk)^-1 x."""
            y = A_inv @ x
            return np.asarray(y + wk * AJ @ np.linalg.lstsq(S, Jk @ y, rcond=1e-12)[0])

        r_loo = rw[j] + Jk @ ak_inv(g)
        Ck = np.eye(6) + Jk @ ak_inv(Jk.T)
        loo[k] = float(r_loo @ np.linalg.solve(Ck, r_loo))
    outlier = np.where(np.isfinite(loo), loo > limit, False)
    info = np.full((N, 6, 6), np.nan)
    for j, k in enumerate(usable):
        info[k] = _drop_weak(np.linalg.inv(vf * Cw[j] + floors[j]), weak_dirs[j])
    unbracketed = bracketing(cross, info, outlier, extrinsics[ref], s)
    frac = {}
    for a in agents:
        m = [k for k in usable if a in (ref, cross[k].other)]
        frac[a] = float(np.mean(outlier[m])) if m else 0.0
    return ClipSolution(
        unbracketed=unbracketed, outlier_fraction=frac, steps=list(P.steps),
        agents=agents, eps={a: P.eps(th, a).copy() for a in agents},
        eps_cov={a: A_inv[P.idx[a]:P.idx[a] + 6, P.idx[a]:P.idx[a] + 6].copy() for a in agents},
        omega={a: P.omega(th, a).copy() for a in agents}, T_cross=T_all, cross_cov=cov_all,
        weight=weight, chi2=chi_all, loo_chi2=loo, outlier=outlier, variance_factor=vf,
        odo_weight=w[n_c:].copy(), information=info, loo_limit=float(limit),
        seconds=time.perf_counter() - t_start, n_params=P.n)


def _unobserved(I: np.ndarray | None, lim_t: float, lim_r: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A frame's own marginal covariances (translation, rotation; 3x3, L1 frame) from its
    metric information, and the eigen-directions of each whose 1-sigma exceeds the limit
    (all of them without a measurement)."""
    if I is None or not np.isfinite(I).all():
        big = np.eye(3) * 1e12
        return big, big, np.eye(3), np.eye(3)
    out = []
    for sl, lim in ((slice(3, 6), lim_t), (slice(0, 3), lim_r)):
        # a direction without information (pinv: zero variance) is unobserved too
        Ib = I[sl, sl] - I[sl, :][:, _other(sl)] @ np.linalg.pinv(
            I[_other(sl), :][:, _other(sl)], rcond=1e-12, hermitian=True) @ I[_other(sl), :][:, sl]
        lam, V = np.linalg.eigh(0.5 * (Ib + Ib.T))
        # marginal covariance: a direction without information has infinite variance (not
        # the zero a pseudo-inverse would give it)
        C = (V / np.maximum(lam, 1e-30)) @ V.T
        out.append((C, V[:, lam < 1.0 / lim**2]))
    (Ct, Ut), (Cr, Ur) = out
    return Ct, Cr, Ut, Ur


def range_floor(c: CrossMeasurement, s: SolveSection) -> np.ndarray:
    """The 6x6 error floor of a cross-agent GICP result: ``floor_m`` / ``floor_deg``, times
    ``range / floor_range_m`` beyond ``floor_range_m`` between the two LiDARs (INS).

    Why: what both agents see, the farther one sees with a point spacing that grows with
    range, and the voxel centroids of a sparse surface depend on where its rings fall. That
    bias repeats frame after frame and GICP's Hessian does not show it: a roadside unit 40-70
    m away measured 3-19 cm off with the same sign for a second, while the same street gave
    results within 1 cm at 5-20 m."""
    f = np.array([np.radians(s.floor_deg)] * 3 + [s.floor_m] * 3)
    if s.floor_range_m is not None:
        d = float(np.linalg.norm((np.linalg.inv(c.M_ref) @ c.M_oth)[:3, 3]))
        f = f * max(1.0, d / s.floor_range_m)
    return np.diag(f**2)


def _other(sl: slice) -> slice:
    return slice(0, 3) if sl.start == 3 else slice(3, 6)


def bracketing(cross: list[CrossMeasurement], info: np.ndarray, outlier: np.ndarray,
               E_ref: np.ndarray, s: SolveSection) -> list[str]:
    """No extrapolation: a direction (world axes) that frame k's own GICP did not observe
    (1-sigma of its own information above ``final_max_std_*``: degenerate, marginalised, or
    no measurement at all) may come from the clip solve only when frames of the same agent
    pair that observed it (inliers, own 1-sigma along it within the limit) exist before AND
    after k within ``max_bridge_s``: the smooth INS model then interpolates between
    measurements; otherwise it extrapolates one through the drift model with nothing to
    check it, and the frame is not accepted. "" where accepted, otherwise the reason."""
    lim_t, lim_r = s.final_max_std_m, np.radians(s.final_max_std_deg)
    n = len(cross)
    R = np.stack([(c.M_ref @ E_ref)[:3, :3] for c in cross]) if n else np.zeros((0, 3, 3))
    t = np.array([c.t_s for c in cross])
    own = []
    for k, c in enumerate(cross):
        ok = c.usable and np.isfinite(info[k]).all()
        own.append(_unobserved(info[k] if ok else None, lim_t, lim_r))
    good = np.array([c.usable and not outlier[k] for k, c in enumerate(cross)], bool)
    out = []
    for k, c in enumerate(cross):
        _, _, Ut, Ur = own[k]
        why = []
        for kind, U, lim, ci in (("translation", Ut, lim_t, 0), ("rotation", Ur, lim_r, 1)):
            for u in U.T:
                uw = R[k] @ u
                cand = [j for j in range(n) if good[j] and j != k and cross[j].other == c.other
                        and abs(t[j] - t[k]) <= s.max_bridge_s]
                before = after = False
                for j in cand:
                    uj = R[j].T @ uw
                    if float(uj @ own[j][ci] @ uj) <= lim**2:
                        before |= t[j] < t[k]
                        after |= t[j] > t[k]
                if not (before and after):
                    side = "before" if not before else "after"
                    ax = "xyz"[int(np.argmax(np.abs(uw)))]
                    why.append(f"{kind} ~world {ax} ({uw[0]:+.2f}, {uw[1]:+.2f}, {uw[2]:+.2f}): "
                               f"no frame observing it within {s.max_bridge_s:g} s {side}")
        if why and not c.usable:
            out.append("no GICP measurement and no bracketing frames (" + "; ".join(why) + ")")
        elif why:
            out.append("uncertain: extrapolated along " + "; ".join(why))
        else:
            out.append("")
    return out


def relative_truth_check(T_est: np.ndarray, T_true: np.ndarray) -> np.ndarray:
    """(N, 2) metres / degrees between estimated and true transforms (for tests, benches)."""
    d = compose(T_true, invert(T_est)) if T_est.ndim == 2 else T_true @ invert(T_est)
    r = so3_log(d[..., :3, :3])
    return np.stack([np.linalg.norm(T_est[..., :3, 3] - T_true[..., :3, 3], axis=-1),
                     np.degrees(np.linalg.norm(r, axis=-1))], -1)
