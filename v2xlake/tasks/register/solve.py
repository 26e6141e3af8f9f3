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
observe itself needs observing frames before and after it within ``max_bridge_s``. A pair
with a stationary agent (``still``) sees the same surfaces from the same place all clip long,
so in the reported covariance its frames carry their weak-geometry floor too and count once
per ``stationary_correlation_s`` (:func:`stationary_cross_information`). So do the frames of
a pair farther apart than ``weak_geometry_beyond_m`` (once per ``correlation_s``): at 40-50 m
a following vehicle's GICP was 3-19 cm short along the street, the one direction its
surfaces barely constrain, for seconds on end, each frame claiming ~0.5 cm.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

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


def so3_right_jacobian(w: np.ndarray) -> np.ndarray:
    """``Jr(w)`` with ``Exp(w + d) = Exp(w) Exp(Jr(w) d)`` to first order (3, 3)."""
    th = float(np.linalg.norm(w))
    K = _hat(np.asarray(w, np.float64)[None])[0]
    if th < 1e-8:
        return np.eye(3) - 0.5 * K + K @ K / 6.0
    return np.eye(3) - (1 - np.cos(th)) / th**2 * K + (th - np.sin(th)) / th**3 * (K @ K)


def nonholonomic_residual(eps: np.ndarray, Z: np.ndarray, E: np.ndarray
                          ) -> tuple[np.ndarray, np.ndarray]:
    """Straight driving moves the body along its own x axis: for each measured LiDAR motion
    ``Z`` (m, 4, 4) and extrinsic ``E exp(eps)``, the body motion ``Tb = X Z X^-1`` and the
    direction of its chord (constant curvature: it leaves at half the heading change) across
    (lateral) and up (vertical), ``(m, 2)`` radians, and their Jacobian in ``eps`` (m, 2, 6).

    Analytic: ``d exp(eps) = exp(eps) Xi`` with ``Xi`` the twist ``[Jr(w) dw, R^T dt]``, so
    ``dTb = X (Xi Z - Z Xi) X^-1``; the chain rule through atan2 and the normalisation does
    the rest (a test compares it with central differences)."""
    X = E @ se3_exp(eps)
    Xi_inv = invert(X)
    Tb = X @ Z @ Xi_inv  # ego(t0) <- ego(t1), (m, 4, 4)
    c, s_ = Tb[:, 0, 0], Tb[:, 1, 0]
    half = 0.5 * np.arctan2(s_, c)
    d = Tb[:, :3, 3]
    sh, ch = np.sin(half), np.cos(half)
    lat = -sh * d[:, 0] + ch * d[:, 1]
    nrm = np.linalg.norm(d, axis=1)
    n = np.maximum(nrm, 1e-9)
    r = np.stack([lat / n, d[:, 2] / n], 1)
    # the six generators of d exp(eps) = exp(eps) Xi, as 4x4 twist matrices
    Xi = np.zeros((6, 4, 4))
    Xi[:3, :3, :3] = _hat(so3_right_jacobian(eps[:3]).T)  # d w_k: hat(Jr e_k)
    Xi[3:, :3, 3] = so3_exp(eps[:3])  # d t_k: R^T e_k, row k of R
    dTb = X @ (np.einsum("kij,mjl->mkil", Xi, Z) - np.einsum("mij,kjl->mkil", Z, Xi)) @ Xi_inv
    dT = np.asarray(dTb)  # (m, 6, 4, 4)
    dc, ds = dT[:, :, 0, 0], dT[:, :, 1, 0]
    dhalf = 0.5 * (c[:, None] * ds - s_[:, None] * dc) / (c**2 + s_**2)[:, None]
    dd = dT[:, :, :3, 3]  # (m, 6, 3)
    dlat = (-ch[:, None] * dhalf * d[:, None, 0] - sh[:, None] * dd[:, :, 0]
            - sh[:, None] * dhalf * d[:, None, 1] + ch[:, None] * dd[:, :, 1])
    dn = np.where((nrm > 1e-9)[:, None], np.einsum("mi,mki->mk", d, dd) / n[:, None], 0.0)
    J = np.stack([dlat / n[:, None] - lat[:, None] * dn / n[:, None] ** 2,
                  dd[:, :, 2] / n[:, None] - d[:, None, 2] * dn / n[:, None] ** 2], 1)
    return r, J


def _so3_exp1(w: np.ndarray) -> np.ndarray:
    """:func:`so3_exp` of one rotation vector (the same formula) without the broadcasting
    machinery: the solve evaluates it for every agent at every step."""
    x, y, z = float(w[0]), float(w[1]), float(w[2])
    th2 = x * x + y * y + z * z
    th = math.sqrt(th2)
    if th > 1e-8:
        a, b = math.sin(th) / th, (1.0 - math.cos(th)) / th2
    else:
        a, b = 1.0 - th2 / 6.0, 0.5 - th2 / 24.0
    K = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + a * K + b * (K @ K)


def _se3_exp1(x: np.ndarray) -> np.ndarray:
    """:func:`se3_exp` of one 6-vector."""
    out = np.eye(4)
    out[:3, :3] = _so3_exp1(x[:3])
    out[:3, 3] = x[3:6]
    return out


@dataclass(frozen=True)
class _Group:
    """The rows of one side of a measurement stack that belong to one agent."""

    agent: str
    rows: np.ndarray
    M: np.ndarray  # (m, 4, 4) INS poses
    i0: np.ndarray  # knot interpolation: indices and the weight of i0 + 1
    i1: np.ndarray
    w: np.ndarray
    steps: list[tuple[int, np.ndarray]]  # (parameter column, rows from the step on)


@dataclass(frozen=True)
class _Side:
    n: int
    groups: list[_Group]
    D0: np.ndarray  # (n, 6, n_params): the theta-independent part of the Jacobian


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
        self._plans: dict[int, tuple[object, tuple[_Side, _Side]]] = {}
        # straight odometry pairs: (agent, measured T_La0_La1)
        self.nh = [(o.agent, o.Z) for o in odo
                   if np.degrees(np.linalg.norm(so3_log(o.Z[:3, :3]))) < s.straight_deg
                   and np.linalg.norm(o.Z[:3, 3]) >= s.nonholonomic_min_m]

    def ground_rows(self, th: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One residual per agent with a measured ground distance and a declared body: the
        corrected LiDAR origin's height above the ego frame's ground plane. The height of
        ``E exp(eps)``'s origin is ``E[2, :3] . t + E[2, 3]``: linear in the translation of
        ``eps`` and independent of its rotation, so the Jacobian is exact and constant."""
        agents = sorted(self.ground)
        r = np.zeros(len(agents))
        J = np.zeros((len(agents), self.n))
        sig = self.s.ground_sigma_m
        for i, a in enumerate(agents):
            h, g = self.ground[a]
            e, E = self.eps(th, a), self.E[a]
            r[i] = (float(E[2, :3] @ e[3:] + E[2, 3] - g) - h) / sig
            J[i, self.idx[a] + 3:self.idx[a] + 6] = E[2, :3] / sig
        return r, J

    def nonholonomic(self, th: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Residuals (2 per straight odometry pair: lateral and vertical direction of the
        body's displacement, radians / sigma) and their Jacobian in the agent's extrinsic
        correction (analytic, :func:`nonholonomic_residual`; it was central differences, 12
        evaluations per agent and step)."""
        if not self.nh:
            return np.zeros(0), np.zeros((0, self.n))
        sig = np.radians(self.s.nonholonomic_deg)
        agents = [a for a, _ in self.nh]
        Zs = np.stack([Z for _, Z in self.nh])
        r = np.zeros((len(self.nh), 2))
        J = np.zeros((len(self.nh), 2, self.n))
        for a in sorted(set(agents)):
            m = np.array([x == a for x in agents])
            rr, JJ = nonholonomic_residual(self.eps(th, a), Zs[m], self.E[a])
            r[m] = rr / sig
            J[m, :, self.idx[a]:self.idx[a] + 6] = JJ / sig
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

    def _side(self, agents: list[str], M: np.ndarray, t: np.ndarray) -> _Side:
        """What one side of a stack of relative transforms needs besides theta: its rows per
        agent, their knot interpolation and step masks, and the constant part of its
        Jacobian (knots, attitude rotation, steps)."""
        n = len(M)
        D0 = np.zeros((n, 6, self.n))
        groups = []
        for a in sorted(set(agents)):
            rows = np.flatnonzero(np.array([x == a for x in agents]))
            tg = np.asarray(t, np.float64)[rows]
            i0, i1, w = self.interp_w(tg)
            b = self.idx[a]
            D0[rows, :3, b + 6:b + 9] = np.eye(3)  # omega: a world rotation about the ego
            for k in range(3):
                D0[rows, 3 + k, b + 9 + 3 * i0 + k] = 1 - w
                D0[rows, 3 + k, b + 9 + 3 * i1 + k] += w
            steps = []
            for i, (sa, ts) in enumerate(self.steps):
                if sa == a:
                    c = self.n_base + 3 * i
                    on = tg >= ts
                    D0[rows[on], 3:, c:c + 3] = np.eye(3)
                    steps.append((c, on))
            groups.append(_Group(a, rows, M[rows], i0, i1, w, steps))
        return _Side(n, groups, D0)

    def _world(self, th: np.ndarray, side: _Side) -> tuple[np.ndarray, np.ndarray]:
        """Corrected ``T_W_La`` (N, 4, 4) of every row and d(its world-left twist)/d(theta)
        (N, 6, n): ``eps`` moves it by ``Ad_L`` (``L exp(d) = exp(Ad_L d) L``), ``omega`` by
        a world rotation about the corrected ego position, the knots and steps by the
        constant part."""
        L = np.zeros((side.n, 4, 4))
        D = side.D0.copy()
        for g in side.groups:
            V = self.knots_v(th, g.agent)
            v = V[g.i0] * (1 - g.w)[:, None] + V[g.i1] * g.w[:, None]
            for c, on in g.steps:
                v = v + np.where(on[:, None], th[c:c + 3][None, :], 0.0)
            C = g.M.copy()
            C[:, :3, :3] = _so3_exp1(self.omega(th, g.agent)) @ g.M[:, :3, :3]
            C[:, :3, 3] = g.M[:, :3, 3] + v
            Lg = C @ (self.E[g.agent] @ _se3_exp1(self.eps(th, g.agent)))
            b = self.idx[g.agent]
            L[g.rows] = Lg
            D[g.rows, :, b:b + 6] = se3_adjoint(Lg)
            D[g.rows, 3:, b + 6:b + 9] = _hat(C[:, :3, 3])
        return L, D

    def _pairs(self, th: np.ndarray, s1: _Side, s2: _Side) -> tuple[np.ndarray, np.ndarray]:
        """``T = L_1^-1 L_2`` per row and d(left perturbation of T)/d(theta) (N, 6, n): a
        world twist on ``L_1`` moves ``T`` by ``-Ad(L_1^-1) xi``, one on ``L_2`` by
        ``+Ad(L_1^-1) xi``."""
        L1, D1 = self._world(th, s1)
        L2, D2 = self._world(th, s2)
        L1i = invert(L1)
        return L1i @ L2, se3_adjoint(L1i) @ (D2 - D1)

    def _plan(self, key: list[CrossMeasurement] | list[OdoMeasurement],
              make: Callable[[], tuple[_Side, _Side]]) -> tuple[_Side, _Side]:
        """The two sides of a measurement list, built once per list (the solve evaluates
        the same lists at every step)."""
        hit = self._plans.get(id(key))
        if hit is None or hit[0] is not key:
            hit = (key, make())
            self._plans[id(key)] = hit
        return hit[1]

    def cross_model(self, th: np.ndarray, cross: list[CrossMeasurement]
                    ) -> tuple[np.ndarray, np.ndarray]:
        if not cross:
            return np.zeros((0, 4, 4)), np.zeros((0, 6, self.n))

        def make() -> tuple[_Side, _Side]:
            t1 = np.array([c.t_s for c in cross])
            t2 = np.array([c.t_oth_s if c.t_oth_s is not None else c.t_s for c in cross])
            return (self._side([self.ref] * len(cross), np.stack([c.M_ref for c in cross]), t1),
                    self._side([c.other for c in cross], np.stack([c.M_oth for c in cross]),
                               t2))

        return self._pairs(th, *self._plan(cross, make))

    def odo_model(self, th: np.ndarray, odo: list[OdoMeasurement]
                  ) -> tuple[np.ndarray, np.ndarray]:
        if not odo:
            return np.zeros((0, 4, 4)), np.zeros((0, 6, self.n))

        def make() -> tuple[_Side, _Side]:
            ag = [o.agent for o in odo]
            return (self._side(ag, np.stack([o.M0 for o in odo]), np.array([o.t0_s for o in odo])),
                    self._side(ag, np.stack([o.M1 for o in odo]), np.array([o.t1_s for o in odo])))

        return self._pairs(th, *self._plan(odo, make))

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
    V, weak = weak_directions_batch(np.asarray(H, np.float64)[None], ratio)
    return [V[0, :, i] for i in range(3) if weak[0, i]]


def weak_directions_batch(H: np.ndarray, ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`weak_directions` of a stack (n, 6, 6) at once: the eigenvectors of each
    translation Schur complement (n, 3, 3; columns, ascending) and which are weak (n, 3).
    One LAPACK call per stack instead of one per frame and IRLS pass (the solve's
    reweighting calls it for every measurement each time). A rotation block that cannot be
    inverted leaves that Hessian without weak directions, as before."""
    n = len(H)
    weak = np.zeros((n, 3), bool)
    V = np.zeros((n, 3, 3))
    if ratio <= 0 or not n:
        return V, weak
    lam, V, ok = _translation_eig(H)
    weak = (lam < ratio * np.maximum(lam[:, -1:], 0.0)) & ok[:, None]
    return V, weak


def _translation_eig(H: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eigenvalues (n, 3; ascending) and eigenvectors (n, 3, 3; columns) of each Hessian's
    translation block after eliminating rotation (Schur complement), and whether its
    rotation block could be inverted (n,)."""
    n = len(H)
    H = 0.5 * (H + H.transpose(0, 2, 1))
    ok = np.ones(n, bool)
    try:
        X = np.linalg.solve(H[:, :3, :3], H[:, :3, 3:])
    except np.linalg.LinAlgError:  # some singular: one by one, those get none
        X = np.zeros((n, 3, 3))
        for i in range(n):
            try:
                X[i] = np.linalg.solve(H[i, :3, :3], H[i, :3, 3:])
            except np.linalg.LinAlgError:
                ok[i] = False
    S = H[:, 3:, 3:] - H[:, 3:, :3] @ X
    lam, V = np.linalg.eigh(0.5 * (S + S.transpose(0, 2, 1)))
    return lam, V, ok


def _drop_weak_batch(W: np.ndarray, V: np.ndarray, weak: np.ndarray) -> np.ndarray:
    """``W`` (n, 6, 6) with the translation along each column of ``V`` (n, 3, 3) flagged in
    ``weak`` (n, 3) marginalised out, one after the other. Along a street of parallel walls
    GICP's Hessian still claims a little (poles, what filtering left) and the scan slides
    exactly there: trusting that little is how a slide enters a fused solution;
    marginalising it lets the other frames decide."""
    W = 0.5 * (W + W.transpose(0, 2, 1))
    for i in range(3):
        m = weak[:, i]
        if not m.any():
            continue
        e = np.zeros((int(m.sum()), 6))
        e[:, 3:] = V[m, :, i]
        Wm = W[m]
        We = (Wm @ e[:, :, None])[:, :, 0]
        d = np.einsum("ni,ni->n", e, We)
        pos = d > 0
        upd = Wm - We[:, :, None] * We[:, None, :] / np.where(pos, d, 1.0)[:, None, None]
        W[m] = np.where(pos[:, None, None], upd, Wm)
    return np.asarray(0.5 * (W + W.transpose(0, 2, 1)))


def _gauss_newton(fun_jac: Callable[[np.ndarray], tuple[np.ndarray, Callable[[], np.ndarray]]],
                  th: np.ndarray, max_iterations: int) -> np.ndarray:
    """Levenberg-Marquardt on the normal equations: the problem is small (about a hundred
    parameters) and nearly linear (corrections of centimetres and tenths of a degree), so a
    few Gauss-Newton steps converge; measured 4-6x faster here than
    ``scipy.optimize.least_squares`` (trf), which spends its time in an SVD per step.

    ``fun_jac(th)``: the residuals and a function computing the whitened rows' Jacobian
    (the bulk of it; the small nonholonomic and ground rows' come with the residuals),
    called only for a step that is taken; the normal equations are formed once per point
    taken, not again after a refused step (which only raises the damping). On a 10 s
    three-agent clip 49 of 77 steps were refused: the same numbers, without their
    Jacobians and products."""
    f, jac = fun_jac(th)
    J = jac()
    cost = float(f @ f)
    lam = 1e-8
    A = g = None
    for _ in range(max_iterations):
        if A is None or g is None:
            A, g = J.T @ J, J.T @ f
        d = np.diag(A)
        try:
            step = -np.linalg.solve(A + lam * np.diag(d + 1e-12 * max(d.max(), 1.0)), g)
        except np.linalg.LinAlgError:
            lam *= 10
            continue
        f2, jac2 = fun_jac(th + step)
        cost2 = float(f2 @ f2)
        if cost2 <= cost:
            th, f, J = th + step, f2, jac2()
            A = g = None
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


def _mv(M: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Batched matrix-vector product ``M[n] @ x[n]`` (n, 6, 6) x (n, 6)."""
    return np.asarray((M @ x[:, :, None])[:, :, 0])


def _chol_upper(W: np.ndarray) -> np.ndarray:
    """U with U^T U = W (W symmetric PSD, (6, 6) or a stack (n, 6, 6); a tiny ridge keeps
    rank-deficient ones usable)."""
    W = 0.5 * (W + np.swapaxes(W, -1, -2))
    ridge = 1e-12 * np.maximum(np.trace(W, axis1=-2, axis2=-1), 1e-30)
    L = np.linalg.cholesky(W + ridge[..., None, None] * np.eye(6))
    return np.asarray(np.swapaxes(L, -1, -2))


def _leave_one_out(A_inv: np.ndarray, J: np.ndarray, r: np.ndarray, w: np.ndarray
                   ) -> np.ndarray:
    """Each measurement against the solution of all the others: its rows ``J[k]`` (6, n;
    whitened, weighted ``w[k]`` in the solve) are taken out of the normal equations ``A``
    (a rank-6 downdate, Woodbury), its residual predicted from the rest and compared with
    its own (whitened) residual ``r[k]``: the chi^2 (6 dof) of the difference, (m,).

    With ``AJ = A^-1 J^T`` and ``S = I - w J AJ``, ``(A - w J^T J)^-1 x = A^-1 x + w AJ
    S^+ J A^-1 x``; every term reduces to 6x6 algebra per measurement, batched."""
    if not len(J):
        return np.zeros(0)
    wc = w[:, None, None]
    AJ = A_inv @ J.transpose(0, 2, 1)  # (m, n, 6)
    JAJ = J @ AJ  # (m, 6, 6)
    eye = np.eye(6)
    S_inv = np.linalg.pinv(eye - wc * JAJ, rcond=1e-12)
    JAJr = _mv(JAJ, r)
    r_loo = r + w[:, None] * JAJr + w[:, None] * _mv(JAJ, _mv(S_inv, w[:, None] * JAJr))
    Ck = eye + JAJ + wc * (JAJ @ (S_inv @ JAJ))
    return np.asarray(np.einsum("mi,mi->m", r_loo, np.linalg.solve(Ck, r_loo[:, :, None])[:, :, 0]))


def _cauchy_weight(chi: np.ndarray, c: float) -> np.ndarray:
    return 1.0 / (1.0 + (chi / c) ** 2)


def solve_clip(agents: list[str], ref: str, extrinsics: dict[str, np.ndarray],
               cross: list[CrossMeasurement], odo: list[OdoMeasurement],
               settings: SolveSection = DEFAULT_SOLVE,
               ground: dict[str, tuple[float, float]] | None = None,
               steps: list[tuple[str, float]] | None = None,
               still: set[str] | None = None) -> ClipSolution:
    """Fuse a clip's per-frame GICP measurements (see the module doc). ``ground``: per agent
    (measured LiDAR height above the ground, the ground's z in the ego frame from the
    declared body); ``still``: the agents that do not move during the clip. The dense
    algebra is small (hundreds of rows, about a hundred parameters): one BLAS thread."""
    with _blas_controller().limit(limits=1):
        return _solve_clip(agents, ref, extrinsics, cross, odo, settings, ground or {},
                           steps or [], still or set())


@functools.cache
def _blas_controller() -> Any:
    """One ``threadpoolctl.ThreadpoolController`` per process: building one scans every
    loaded shared library (15 ms, 2 per clip, as much as a tenth of the solve); NumPy's BLAS
    is loaded before any solve runs."""
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController()


def _solve_clip(agents: list[str], ref: str, extrinsics: dict[str, np.ndarray],
                cross: list[CrossMeasurement], odo: list[OdoMeasurement],
                settings: SolveSection, ground: dict[str, tuple[float, float]],
                steps: list[tuple[str, float]], still: set[str]) -> ClipSolution:
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
    Cw = np.linalg.pinv(np.stack([0.5 * (W + W.T) for W in Ws]), rcond=1e-12,
                        hermitian=True) if Ws else np.zeros((0, 6, 6))
    Uh = _chol_upper(np.stack(Ws)) if Ws else np.zeros((0, 6, 6))
    # the effective information of each measurement without its degenerate directions, as
    # the last reweighting computed it (reported per frame)
    dropped: list[np.ndarray] = [np.zeros((0, 6, 6)), np.zeros(0, bool), np.zeros((0, 3, 3)),
                                 np.zeros((0, 3), bool)]

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
        infos = np.linalg.inv(vf * Cw + floors)
        V, weak = weak_directions_batch(infos, s.degenerate_ratio)
        dropped[:] = [_drop_weak_batch(infos, V, weak), np.asarray(weak.any(axis=1)), V, weak]
        return _chol_upper(dropped[0])

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

    # the residuals at the last theta asked: each reweighting evaluates them again where the
    # last accepted step left theta (for the weights, then for the first Gauss-Newton step),
    # and so does the covariance after the last one (a 3 s three-agent clip: 144 -> 102
    # model evaluations, the same arrays; nothing writes into them)
    last: list[Any] = [None, None]

    def residuals(th: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        key = th.tobytes()
        if last[0] != key:
            T, G = model(th)
            last[:] = [key, (se3_left_residual(Z, T), G)]
        out: tuple[np.ndarray, np.ndarray] = last[1]
        return out

    def fun_jac(th: np.ndarray) -> tuple[np.ndarray, Callable[[], np.ndarray]]:
        r, G = residuals(th)
        f = np.sqrt(np.maximum(w, 0.0))[:, None]
        rw = _mv(U, r) * f
        rn, Jn = P.nonholonomic(th)
        rg, Jg = P.ground_rows(th)
        U_now = U  # the whitening of this evaluation, whenever the Jacobian is asked

        def jac() -> np.ndarray:
            Jw = -(U_now @ G) * f[:, :, None]
            return np.concatenate([Jw.reshape(-1, P.n), Jn, Jg, P.P])

        return np.concatenate([rw.ravel(), rn, rg, P.P @ th]), jac

    med6 = chi2_isf(0.5, 6)
    for it in range(max(1, s.irls_iterations) + 1):
        th = _gauss_newton(fun_jac, th, s.max_iterations)
        if it == max(1, s.irls_iterations):
            break
        r, _ = residuals(th)
        rh = _mv(Uh, r)
        chi_h = np.einsum("ni,ni->n", rh, rh)
        if len(chi_h) >= s.min_for_variance:  # the Hessians' scale, from the median one
            vf = max(float(np.median(chi_h)) / med6, 1e-12)
        U = effective(vf)
        re = _mv(U, r)
        w = _cauchy_weight(np.sqrt(np.einsum("ni,ni->n", re, re)), s.robust_scale)
        w[n_c:] *= s.odometry_weight
    J_all = fun_jac(th)[1]()
    A = J_all.T @ J_all
    A_inv = np.linalg.pinv(A, rcond=1e-13, hermitian=True)
    r, G = residuals(th)
    rw = _mv(U, r)  # unweighted, whitened: unit variance for an inlier
    Jw = -(U @ G)
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
    pair = np.array([ref in still or c.other in still for c in uc], bool)
    far = s.weak_geometry_beyond_m
    moving = ~pair & np.array([far is not None and pair_range(c) > far for c in uc], bool)
    f = np.sqrt(np.maximum(w[:n_c], 0.0))[:, None, None]

    def recounted(A_c: np.ndarray, sel: np.ndarray, weak: bool, n_count: float
                  ) -> np.ndarray:
        """``A_c`` with the frames ``sel`` honestly whitened (their degenerate directions
        dropped as in the solve, the weak-geometry floor added where ``weak``) and counted
        once per ``n_count`` frames (:func:`stationary_cross_information`)."""
        ix = np.flatnonzero(sel)
        C_h = vf * Cw[ix] + floors[ix]
        if weak:
            C_h = C_h + weak_geometry_floor(np.stack([Ws[i] for i in ix]), s)
        U_h = _chol_upper(_drop_weak_batch(np.linalg.inv(C_h), dropped[2][ix], dropped[3][ix]))
        J_h = np.zeros((n_c, 6, P.n))
        J_h[ix] = -(U_h @ G[ix]) * f[ix]
        return stationary_cross_information(A_c, -(U[:n_c] @ G[:n_c]) * f, J_h, sel, corr,
                                            n_count)

    if moving.any():
        # a far pair's frames honestly whitened too (weak_geometry_beyond_m), counted as
        # before, once per correlation_s: only the weak directions' variance changes. At
        # 40-50 m the other agent's sparse rings on the poles and car flanks that alone fix
        # the pair along the street bias it the same way for seconds (seed 3, 50 m behind:
        # 3-19 cm short for 4 s, each frame claiming ~0.5 cm), which the isotropic range
        # floor covered only by refusing every far frame
        A_c = recounted(A_c, moving, True, corr)
    if pair.any():
        # a stationary pair's frames: honestly whitened (its weak-geometry floor, the same
        # degenerate directions dropped) and counted once per stationary_correlation_s
        sp = np.flatnonzero(pair)
        span = s.correlation_s if s.stationary_correlation_s is None \
            else s.stationary_correlation_s
        # frames per pair within the span, never more than the pair has
        n_pair = max(1.0, min(span * rate / n_same, float(pair.sum()) / max(
            1, len({uc[i].other for i in sp}))))
        A_c = recounted(A_c, pair, s.stationary_weak_geometry, n_pair)
    A_c_inv = np.linalg.pinv(A_c, rcond=1e-13, hermitian=True)
    cov_all = (G_all @ A_c_inv) @ G_all.transpose(0, 2, 1)
    d = np.arange(6)
    cov_all[:, d, d] = np.maximum(cov_all[:, d, d], np.diag(floor))
    weight, chi_all, loo = np.zeros(N), np.full(N, np.nan), np.full(N, np.nan)
    limit = chi2_isf(s.outlier_p, 6)
    uix = np.array(usable, np.int64)
    weight[uix], chi_all[uix] = w[:n_c], chi[:n_c]
    loo[uix] = _leave_one_out(A_inv, Jw[:n_c], rw[:n_c], w[:n_c])
    outlier = np.where(np.isfinite(loo), loo > limit, False)
    if s.own_bound and n_c:
        # an estimate that contains a measurement is never worse than that measurement
        # honestly stated (see own_bound); only for inliers that observe every direction
        Cown = vf * Cw[:n_c] + floors[:n_c] + weak_geometry_floor(np.stack(Ws[:n_c]), s)
        d_own = se3_left_residual(Z[:n_c], T_all[uix])
        use = ~outlier[uix] & ~dropped[1][:n_c]
        cov_all[uix[use]] = own_bound(cov_all[uix[use]], Cown[use], w[:n_c][use],
                                      d_own[use])
    info = np.full((N, 6, 6), np.nan)
    for j, k in enumerate(usable):
        info[k] = dropped[0][j]
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


def stationary_cross_information(A_c: np.ndarray, J: np.ndarray, J_honest: np.ndarray,
                                 pair: np.ndarray, corr: float, corr_pair: float
                                 ) -> np.ndarray:
    """The normal matrix of the reported clip covariance (n, n) with the rows of a
    stationary pair's frames (``pair``, (m,) bool) counted as ``J_honest`` (m, 6, n; each
    frame whitened by its honest covariance, weak-geometry floor included) once per
    ``corr_pair`` frames instead of as ``J`` (whitened as in the solve) once per ``corr``.

    Why: a stationary agent sees the same surfaces from the same place all clip long, so
    the bias of its pair's GICP along a weak direction (voxel aliasing of the same poles,
    its point spacing on the same facades) is not drawn anew each frame: with a roadside
    unit 12-39 m from the reference (seed 2, 10 s) 26 consecutive frames (2.6 s) were 2-9
    cm off along the street with the same sign, each claiming 0.5 cm (variance factor
    0.22, set by the other pairs) plus the 1 cm floor; counted once per 2 s the clip
    reported 1.0-1.5 cm and accepted 28 frames 3.0-4.7 cm off. Only the reported
    covariance changes, never the estimate."""
    n = A_c.shape[0]
    if not pair.any():
        return A_c
    Jo = J[pair].reshape(-1, n)
    Jh = J_honest[pair].reshape(-1, n)
    return np.asarray(A_c - Jo.T @ Jo / corr + Jh.T @ Jh / max(corr_pair, 1.0))


def _unobserved(info: np.ndarray, ok: np.ndarray, lim_t: float, lim_r: float
                ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Each frame's own marginal covariance, translation then rotation (N, 3, 3; L1 frame),
    from its metric information ``info`` (N, 6, 6; ``ok``: it has one), with the
    eigenvectors of that marginal (N, 3, 3; columns) and which of them have a 1-sigma above
    the limit (N, 3): every direction of a frame without a measurement."""
    n = len(info)
    I = np.where(ok[:, None, None], info, 0.0)
    out = []
    for sl, o, lim in ((slice(3, 6), slice(0, 3), lim_t), (slice(0, 3), slice(3, 6), lim_r)):
        # a direction without information (pinv: zero variance) is unobserved too
        Ib = I[:, sl, sl] - I[:, sl, o] @ np.linalg.pinv(I[:, o, o], rcond=1e-12,
                                                        hermitian=True) @ I[:, o, sl]
        lam, V = np.linalg.eigh(0.5 * (Ib + Ib.transpose(0, 2, 1)))
        # marginal covariance: a direction without information has infinite variance (not
        # the zero a pseudo-inverse would give it)
        C = (V / np.maximum(lam, 1e-30)[:, None, :]) @ V.transpose(0, 2, 1)
        weak = lam < 1.0 / lim**2
        C[~ok] = np.eye(3) * 1e12
        V[~ok] = np.eye(3)
        weak[~ok] = True
        out.append((C, V, weak))
    return out if n else [(np.zeros((0, 3, 3)), np.zeros((0, 3, 3)), np.zeros((0, 3), bool))] * 2


def own_bound(cov_clip: np.ndarray, cov_own: np.ndarray, weight: np.ndarray,
              d: np.ndarray) -> np.ndarray:
    """Each frame's reported covariance (m, 6, 6): the clip's, or the bound its own
    measurement gives where that is tighter, per block (the largest rotation and the largest
    translation variance are what the acceptance reads; a block from each source keeps no
    cross-covariance).

    Why: the clip covariance counts correlated frames once per ``correlation_s``, so a frame
    whose neighbours lie on one side only (the clip's ends) was reported up to twice as
    uncertain as its own GICP result alone (the demo clip's first and last frame: 2.0-2.1
    cm, their own GICP 1.0 cm, both 0.3 cm off). An estimate that contains a measurement is
    never worse than the measurement, whatever the correlation between frames. The bound:
    the measurement's honest covariance ``cov_own`` (variance factor, floor and
    :func:`weak_geometry_floor`), divided by its robust weight, plus ``d d^T`` with ``d``
    ([rot, trans], left) from the measurement to the clip estimate, so an estimate that
    left its frame's result is not credited with it."""
    C = cov_own / np.maximum(weight, 1e-12)[:, None, None] + d[:, :, None] * d[:, None, :]
    dc = np.einsum("mii->mi", cov_clip)
    do = np.einsum("mii->mi", C)
    rot = (do[:, :3].max(1) < dc[:, :3].max(1))[:, None, None]
    tra = (do[:, 3:].max(1) < dc[:, 3:].max(1))[:, None, None]
    src_r, src_t = np.where(rot, C, cov_clip), np.where(tra, C, cov_clip)
    # one source for both blocks: its whole matrix; a block from each: no cross-covariance
    out = np.where(rot == tra, src_r, 0.0)
    out[:, :3, :3] = src_r[:, :3, :3]
    out[:, 3:, 3:] = src_t[:, 3:, 3:]
    return out


def weak_geometry_floor(W: np.ndarray, s: SolveSection) -> np.ndarray:
    """The error a GICP result's Hessian does not show along a direction its surfaces barely
    constrain (m, 6, 6; translation only): for each eigen-direction of the Hessian's
    translation block (rotation eliminated) weaker than ``weak_geometry_ratio`` of the
    strongest, a variance of ``floor_m^2 (weak_geometry_ratio / ratio - 1)`` along it.

    Why: the Hessian counts every point of a surface as independent, but a voxel-aliasing or
    sampling bias is shared by the whole surface; where a few poles and car flanks are all
    that fix the scan along the street, that bias is the error. Measured on the cooperative
    boulevard's captured frames (observability 0.01-0.03): the error along the weakest
    direction was 0.9-1.5x the claimed 1-sigma (rms; up to 3.7x: seed 2's first frame 3.4 cm
    off while claiming 1.05 cm), frames at 0.03-0.05 and the demo street (0.11-0.20) stayed
    within 0.45x. ``None``: no such floor."""
    out = np.zeros((len(W), 6, 6))
    ref = s.weak_geometry_ratio
    if ref is None or not len(W):
        return out
    lam, V, ok = _translation_eig(W)
    ratio = np.maximum(lam, 1e-30) / np.maximum(lam[:, -1:], 1e-30)
    var = s.floor_m**2 * np.maximum(0.0, ref / ratio - 1.0)
    var = np.where(ok[:, None], var, 1e6)  # a Hessian without a rotation block: unknown
    out[:, 3:, 3:] = (V * var[:, None, :]) @ V.transpose(0, 2, 1)
    return out


def pair_range(c: CrossMeasurement) -> float:
    """The distance between the two LiDARs of a cross measurement, by the INS (metres)."""
    return float(np.linalg.norm((np.linalg.inv(c.M_ref) @ c.M_oth)[:3, 3]))


def range_floor(c: CrossMeasurement, s: SolveSection) -> np.ndarray:
    """The 6x6 error floor of a cross-agent GICP result: ``floor_m`` / ``floor_deg``, times
    ``range / floor_range_m`` beyond ``floor_range_m`` between the two LiDARs (INS; 40 m by
    default since the reference's scans reach 120 m, the far pairs' bias along the street
    being covered by ``weak_geometry_beyond_m``).

    Why: what both agents see, the farther one sees with a point spacing that grows with
    range, and the voxel centroids of a sparse surface depend on where its rings fall. That
    bias repeats frame after frame and GICP's Hessian does not show it: a roadside unit 40-70
    m away measured 3-19 cm off with the same sign for a second, while the same street gave
    results within 1 cm at 5-20 m."""
    f = np.array([np.radians(s.floor_deg)] * 3 + [s.floor_m] * 3)
    if s.floor_range_m is not None:
        f = f * max(1.0, pair_range(c) / s.floor_range_m)
    return np.diag(f**2)


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
    usable = np.array([c.usable for c in cross], bool)
    ok = usable & np.isfinite(info).all(axis=(1, 2)) if n else usable
    own = _unobserved(np.nan_to_num(info), ok, lim_t, lim_r)
    other = np.array([c.other for c in cross])
    good = usable & ~np.asarray(outlier, bool)
    out = []
    for k, c in enumerate(cross):
        why = []
        cand = np.flatnonzero(good & (other == c.other) & (np.abs(t - t[k]) <= s.max_bridge_s))
        cand = cand[cand != k]
        for kind, (C, V, weak), lim in (("translation", own[0], lim_t),
                                        ("rotation", own[1], lim_r)):
            for u in V[k][:, weak[k]].T:
                uw = R[k] @ u
                uj = np.einsum("jba,b->ja", R[cand], uw)  # R_j^T uw
                seen = np.einsum("ja,jab,jb->j", uj, C[cand], uj) <= lim**2
                before = bool((seen & (t[cand] < t[k])).any())
                after = bool((seen & (t[cand] > t[k])).any())
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
