"""Smooth analytic trajectories: every pose of every agent and actor at any time.

Conventions (all internal geometry of the simulator):

* time ``tau``: float64 seconds since the clip's first PPS (``start_s``); GNSS epoch ns is
  ``start_ns + round(tau * 1e9)``.
* world: the clip's local ENU frame = ``v2xlake.tasks.geodesy.LocalFrame(origin_lat, origin_lon)``,
  z = ellipsoidal height. The red agent's TRUE INS position at tau = 0 is (0, 0, z0) in it,
  i.e. exactly the frame the anonymizer builds from the first (bias-free) INS fix.
* body: x forward, y left, z up; ``R_world_body = Rz(yaw) Ry(-pitch) Rx(roll)`` (pitch positive
  nose-up), the convention of ``tasks.geodesy.attitude_to_matrix`` with yaw = pi/2 - azimuth.

A :class:`KinematicProfile` is a planar path given by closed forms: speed
``v(t) = v0 + dv sin(2 pi t / Tv + phi)`` and yaw rate as a sum of logistic turn windows
``w(t) = sum_i rate_i (s((t - ta_i)/tau_i) - s((t - tb_i)/tau_i))`` (s = logistic), whose
integral (yaw) is closed form via softplus. Position is the integral of
``v [cos yaw, sin yaw]``: cumulative 16-node Gauss-Legendre sums on a 50 ms knot grid plus one
more Gauss-Legendre integral from the knot to the query, accurate to ~1e-12 m. Everything is
C-infinity, so INS samples at 8 ms + linear/SLERP interpolation reproduce the pose to
~v * w * dt^2 / 8 (0.03 mm at 20 m/s and 0.15 rad/s).

A :class:`Trajectory` re-uses a profile with an affine time map ``t' = shift + rate * tau`` and
a lateral offset (left of the path): the whole road traffic follows the red agent's path
(lanes are offsets of it; oncoming traffic has a negative rate). Derivatives (velocity,
acceleration, body angular rate) are central differences of the analytic pose with
h = 1 ms (error ~1e-8 relative), which is all the IMU and INS need.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from scipy.spatial.transform import Rotation

from v2xlake.tasks.geometry import rigid

GRAVITY = 9.80665
_GL_X, _GL_W = np.polynomial.legendre.leggauss(16)
_KNOT_DT = 0.05


@dataclass(frozen=True)
class Turn:
    t_start: float
    t_end: float
    rate: float  # rad/s, positive = left (counter-clockwise seen from above)
    tau: float = 0.3  # s, smoothness of the on/off ramps


def _softplus(x: np.ndarray) -> np.ndarray:
    return np.logaddexp(0.0, x)


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 0.5 * (1.0 + np.tanh(0.5 * x))


@dataclass(frozen=True)
class KinematicProfile:
    """Planar closed-form motion; valid for ``t`` in [t_min, t_max] (seconds)."""

    x0: float = 0.0
    y0: float = 0.0
    yaw0: float = 0.0
    v0: float = 18.0
    dv: float = 0.0
    v_period: float = 10.0
    v_phase: float = 0.0
    turns: tuple[Turn, ...] = ()
    t_min: float = -60.0
    t_max: float = 200.0

    def speed(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, float)
        return self.v0 + self.dv * np.sin(2 * np.pi * t / self.v_period + self.v_phase)

    def accel(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, float)
        w = 2 * np.pi / self.v_period
        return self.dv * w * np.cos(w * t + self.v_phase)

    def yaw_rate(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, float)
        out = np.zeros_like(t)
        for tr in self.turns:
            on = _sigmoid((t - tr.t_start) / tr.tau) - _sigmoid((t - tr.t_end) / tr.tau)
            out += tr.rate * on
        return out

    def yaw(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, float)
        out = np.full_like(t, self.yaw0)
        for tr in self.turns:
            def g(x: np.ndarray, tr: Turn = tr) -> np.ndarray:
                return tr.rate * tr.tau * (
                    _softplus((x - tr.t_start) / tr.tau) - _softplus((x - tr.t_end) / tr.tau)
                )
            out += g(t) - g(np.zeros(1))[0]
        return out

    def _vel_xy(self, t: np.ndarray) -> np.ndarray:
        v, y = self.speed(t), self.yaw(t)
        return np.stack([v * np.cos(y), v * np.sin(y)], axis=-1)

    def _gl(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Integral of the planar velocity from a to b (arrays of equal shape) -> (..., 2)."""
        half, mid = 0.5 * (b - a), 0.5 * (b + a)
        tt = mid[..., None] + half[..., None] * _GL_X
        vel = self._vel_xy(tt)
        return half[..., None] * np.einsum("...kc,k->...c", vel, _GL_W)

    @cached_property
    def _knots(self) -> tuple[np.ndarray, np.ndarray]:
        n = int(np.ceil((self.t_max - self.t_min) / _KNOT_DT)) + 1
        tk = self.t_min + _KNOT_DT * np.arange(n)
        seg = self._gl(tk[:-1], tk[1:])
        cum = np.concatenate([np.zeros((1, 2)), np.cumsum(seg, axis=0)])
        # shift so that position(0) = (x0, y0)
        k0 = int(np.floor((0.0 - self.t_min) / _KNOT_DT))
        at0 = cum[k0] + self._gl(np.array([tk[k0]]), np.array([0.0]))[0]
        return tk, cum - at0 + np.array([self.x0, self.y0])

    def position(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, float)
        if np.any(t < self.t_min) or np.any(t > self.t_max):
            raise ValueError(f"time outside the profile's range [{self.t_min}, {self.t_max}] s")
        tk, cum = self._knots
        k = np.clip(((t - self.t_min) / _KNOT_DT).astype(np.int64), 0, len(tk) - 2)
        return cum[k] + self._gl(tk[k], t)


@dataclass(frozen=True)
class Trajectory:
    """A rigid body moving along ``profile`` at ``t' = shift + rate * tau``.

    ``lateral`` offsets it to the left of the path, ``height`` is the body origin above the
    ground (``ground_z``). ``roll_gain`` (rad per m/s^2 lateral) and ``pitch_gain`` (rad per
    m/s^2 longitudinal) give the small body attitude changes of a real car; they enter only
    through ``pose`` (3D agents), actors in the scene are yaw-only boxes.
    """

    profile: KinematicProfile
    ground_z: float
    height: float = 0.0
    shift: float = 0.0
    rate: float = 1.0
    lateral: float = 0.0
    roll_gain: float = 0.0
    pitch_gain: float = 0.0
    static: bool = field(default=False)

    def _tp(self, tau: np.ndarray) -> np.ndarray:
        if self.static:
            return np.zeros_like(np.asarray(tau, float))
        return self.shift + self.rate * np.asarray(tau, float)

    def pose2d(self, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(..., 3) position (z = ground + height) and (...,) heading yaw of the body."""
        if self.static:
            tau = np.asarray(tau, float)
            pr = self.profile
            p = np.broadcast_to(np.array([pr.x0, pr.y0]), (*tau.shape, 2))
            yaw = np.full(tau.shape, pr.yaw0)
        else:
            tp = self._tp(tau)
            p = self.profile.position(tp)
            yaw = self.profile.yaw(tp)
        if self.lateral:
            p = p + self.lateral * np.stack([-np.sin(yaw), np.cos(yaw)], axis=-1)
        if self.rate < 0:
            yaw = yaw + np.pi
        z = np.full((*p.shape[:-1], 1), self.ground_z + self.height)
        return np.concatenate([p, z], axis=-1), np.mod(yaw + np.pi, 2 * np.pi) - np.pi

    def attitude(self, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """roll, pitch, yaw (rad) of the body."""
        tp = self._tp(tau)
        _, yaw = self.pose2d(tau)
        if self.static:
            z = np.zeros_like(yaw)
            return z, z, yaw
        r2 = self.rate * self.rate
        lat_acc = self.profile.speed(tp) * self.profile.yaw_rate(tp) * r2
        lon_acc = self.profile.accel(tp) * r2 * np.sign(self.rate)
        return self.roll_gain * lat_acc, self.pitch_gain * lon_acc, yaw

    def pose(self, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """True ``T_world_body``: (..., 3) translation and (..., 3, 3) rotation."""
        tau = np.asarray(tau, float)
        p, _ = self.pose2d(tau)
        roll, pitch, yaw = self.attitude(tau)
        eul = np.stack([yaw, -pitch, roll], axis=-1).reshape(-1, 3)
        r = Rotation.from_euler("ZYX", eul).as_matrix().reshape(*tau.shape, 3, 3)
        return p, r

    def matrix(self, tau: np.ndarray) -> np.ndarray:
        p, r = self.pose(tau)
        return rigid(r, p)

    def velocity(self, tau: np.ndarray, h: float = 1e-3) -> np.ndarray:
        tau = np.asarray(tau, float)
        return (self.pose2d(tau + h)[0] - self.pose2d(tau - h)[0]) / (2 * h)

    def acceleration(self, tau: np.ndarray, h: float = 1e-3) -> np.ndarray:
        tau = np.asarray(tau, float)
        p0, p1, p2 = self.pose2d(tau - h)[0], self.pose2d(tau)[0], self.pose2d(tau + h)[0]
        return (p2 - 2 * p1 + p0) / (h * h)

    def body_rates(self, tau: np.ndarray, h: float = 1e-3) -> np.ndarray:
        """Angular velocity in the body frame (rad/s), what a strapdown gyro measures."""
        tau = np.asarray(tau, float)
        _, ra = self.pose(tau - h)
        _, rb = self.pose(tau + h)
        rel = np.einsum("...ji,...jk->...ik", ra, rb)
        rv = Rotation.from_matrix(rel.reshape(-1, 3, 3)).as_rotvec()
        return rv.reshape(*tau.shape, 3) / (2 * h)

    def specific_force(self, tau: np.ndarray) -> np.ndarray:
        """Accelerometer reading in the body frame: R^T (a - g), g = (0, 0, -9.80665)."""
        _, r = self.pose(tau)
        f_world = self.acceleration(tau) + np.array([0.0, 0.0, GRAVITY])
        return np.einsum("...ji,...j->...i", r, f_world)
