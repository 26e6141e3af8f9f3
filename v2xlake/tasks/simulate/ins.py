"""INS (125 Hz), IMU (125 Hz) and GNSS (10 Hz) samples from the analytic trajectories.

Timing (CATS-V2V supp. A.1): INS / IMU records at every 8 ms from the PPS
(``start_ns + k * 8_000_000``), GNSS fixes on the 100 ms grid.

What the INS reports (its error model, per agent, seeded):
* position: ``p_ins(t) = p_true(t) + b(t)``, ``b(t) = b0 + b1 sin(2 pi t / P + phi)``: a
  constant bias of norm ``ins_bias_m`` (mostly horizontal) plus a slow wander of amplitude
  ``ins_bias_drift_m`` and period ``ins_bias_period_s`` (default 300 s, i.e. < 0.1 mm change
  within one LiDAR sweep; none for the static roadside unit, whose "INS" is a surveyed pose),
  plus an optional linear drift ``v_d * t`` (``ins_drift_mps``, a seeded horizontal direction,
  on the agents of ``ins_drift_agents`` or every vehicle;
  none for the roadside unit), plus an optional step ``s * [t >= t_s]`` (``ins_step_m`` at
  ``ins_step_at_s`` on the agents of ``ins_step_agents``: a sudden jump such as a GNSS
  re-convergence, part of ``b(t)`` so truth and eq. 1a see it), plus optional white noise
  ``ins_noise_m``;
* attitude: ``R_ins = R_bias @ R_true`` with a constant world-frame rotation ``R_bias``
  (roll, pitch, yaw each +-``ins_att_bias_deg``);
* velocity: the true world velocity (central differences of the analytic path).
Reported as WGS84 lat/lon (deg) and ellipsoidal altitude through
``LocalFrame(origin_lat, origin_lon).to_geodetic`` and roll/pitch/azimuth through
``matrix_to_attitude(R_local_enu(lat, lon)^T @ R_world_body)``, east/north/up velocity in the
local-level ENU at the vehicle. ``rtk_status`` is 2 (fixed).

IMU: body angular rate and specific force ``R^T (a + [0, 0, g])`` of the TRUE motion, plus
white noise (``imu_gyro_noise`` rad/s, ``imu_accel_noise`` m/s^2); orientation field = the INS
attitude as a quaternion of ``R_enu_body``. GNSS: the INS position error plus white noise
``gnss_noise_m`` (antenna at the INS origin).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from v2xlake.tasks.geodesy import LocalFrame, matrix_to_attitude
from v2xlake.tasks.simulate.config import AGENT_NAMES, SimConfig
from v2xlake.tasks.simulate.trajectory import Trajectory

INS_PERIOD_NS = 8_000_000
GNSS_PERIOD_NS = 100_000_000


@dataclass(frozen=True)
class InsError:
    b0: np.ndarray  # (3,) m
    b1: np.ndarray  # (3,) m
    phase: float
    period_s: float
    R_bias: np.ndarray  # (3, 3) world-frame attitude bias
    att_bias_rpy: np.ndarray  # (3,) rad
    drift: np.ndarray = field(default_factory=lambda: np.zeros(3))  # (3,) m/s
    step: np.ndarray = field(default_factory=lambda: np.zeros(3))  # (3,) m
    step_at_s: float = 0.0

    def bias(self, tau: np.ndarray) -> np.ndarray:
        tau = np.asarray(tau, float)
        return (self.b0 + self.b1 * np.sin(2 * np.pi * tau / self.period_s + self.phase)[..., None]
                + self.drift * tau[..., None]
                + self.step * (tau >= self.step_at_s)[..., None])


def ins_error(cfg: SimConfig, agent: str) -> InsError:
    rng = np.random.default_rng([cfg.seed, 1337, AGENT_NAMES.index(agent)])
    d = rng.normal(size=3) * np.array([1.0, 1.0, 0.3])
    d /= np.linalg.norm(d)
    d1 = rng.normal(size=3) * np.array([1.0, 1.0, 0.3])
    d1 /= np.linalg.norm(d1)
    rpy = rng.choice([-1.0, 1.0], 3) * np.radians(cfg.ins_att_bias_deg)
    rb = Rotation.from_euler("ZYX", rpy[::-1]).as_matrix()
    drift = 0.0 if agent == "rsu" else cfg.ins_bias_drift_m  # a surveyed mast does not wander
    phase = float(rng.uniform(0, 2 * np.pi))
    rate = np.zeros(3)
    if cfg.ins_drift_mps > 0 and agent != "rsu":  # drawn last: other errors keep their values
        a = rng.uniform(0, 2 * np.pi)
        if cfg.ins_drift_agents is None or agent in cfg.ins_drift_agents:
            rate = cfg.ins_drift_mps * np.array([np.cos(a), np.sin(a), 0.0])
    step = np.zeros(3)
    if cfg.ins_step_m is not None and agent in cfg.ins_step_agents and agent != "rsu":
        step = np.asarray(cfg.ins_step_m, float)
    return InsError(d * cfg.ins_bias_m, d1 * drift, phase, cfg.ins_bias_period_s, rb, rpy, rate,
                    step, cfg.ins_step_at_s)


@dataclass
class InsSamples:
    t_ns: np.ndarray
    lat: np.ndarray
    lon: np.ndarray
    alt: np.ndarray
    roll: np.ndarray
    pitch: np.ndarray
    azimuth: np.ndarray
    vel_enu: np.ndarray  # (N, 3)
    quat_enu_xyzw: np.ndarray  # (N, 4) INS attitude as quaternion (x, y, z, w)
    gyro: np.ndarray  # (N, 3) body rad/s
    accel: np.ndarray  # (N, 3) body m/s^2


def ins_samples(cfg: SimConfig, traj: Trajectory, err: InsError, frame: LocalFrame,
                t_ns: np.ndarray, rng: np.random.Generator) -> InsSamples:
    start_ns = cfg.start_s * 1_000_000_000
    tau = (t_ns - start_ns) / 1e9
    p, r = traj.pose(tau)
    pm = p + err.bias(tau)
    if cfg.ins_noise_m > 0:
        pm = pm + rng.normal(0.0, cfg.ins_noise_m, pm.shape)
    rm = err.R_bias @ r
    lat, lon, alt = frame.to_geodetic(pm)
    r_le = frame.R_local_enu(lat, lon)  # ENU at vehicle -> world axes
    r_enu_body = np.einsum("nji,njk->nik", r_le, rm)
    roll, pitch, az = matrix_to_attitude(r_enu_body)
    v = traj.velocity(tau)
    v_enu = np.einsum("nji,nj->ni", r_le, v)
    gyro = traj.body_rates(tau) + rng.normal(0.0, cfg.imu_gyro_noise, (len(tau), 3))
    acc = traj.specific_force(tau) + rng.normal(0.0, cfg.imu_accel_noise, (len(tau), 3))
    q = Rotation.from_matrix(r_enu_body).as_quat()
    return InsSamples(t_ns, lat, lon, alt, roll, pitch, az, v_enu, q, gyro, acc)


def gnss_fixes(cfg: SimConfig, traj: Trajectory, err: InsError, frame: LocalFrame,
               t_ns: np.ndarray, rng: np.random.Generator
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    tau = (t_ns - cfg.start_s * 1_000_000_000) / 1e9
    p, _ = traj.pose(tau)
    pm = p + err.bias(tau) + rng.normal(0.0, cfg.gnss_noise_m, p.shape) * np.array([1, 1, 1.5])
    return frame.to_geodetic(pm)
