"""WGS84 <-> local ENU, and INS attitude <-> quaternion, exact (no flat-earth shortcut).

The simulator and the anonymizer both go through these functions, so positions survive the
round trip raw (lat, lon, alt) -> clean (local ENU) to float64 precision. INS attitude follows
the common vendor convention: roll, pitch in radians about the body x (forward) and y (left)
axes, ``azimuth`` in radians clockwise from true north, all relative to the local-level ENU
frame at the vehicle's own position. ``T_enu_body = Rz(pi/2 - azimuth) Ry(-pitch) Rx(roll)``
with body x forward, y left, z up (pitch positive nose-up).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

WGS84_A = 6378137.0
WGS84_F = 1.0 / 298.257223563
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)


def geodetic_to_ecef(lat: np.ndarray, lon: np.ndarray, alt: np.ndarray) -> np.ndarray:
    """Degrees, degrees, metres -> (N, 3) ECEF metres."""
    la, lo = np.radians(lat), np.radians(lon)
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * np.sin(la) ** 2)
    x = (n + alt) * np.cos(la) * np.cos(lo)
    y = (n + alt) * np.cos(la) * np.sin(lo)
    z = (n * (1.0 - WGS84_E2) + alt) * np.sin(la)
    return np.stack([x, y, z], axis=-1)


def ecef_to_geodetic(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(N, 3) ECEF -> lat, lon (degrees), alt (m); Bowring start + Newton iterations (sub-mm)."""
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    lon = np.arctan2(y, x)
    r = np.hypot(x, y)
    lat = np.arctan2(z, r * (1.0 - WGS84_E2))
    for _ in range(6):
        n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * np.sin(lat) ** 2)
        alt = r / np.cos(lat) - n
        lat = np.arctan2(z, r * (1.0 - WGS84_E2 * n / (n + alt)))
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * np.sin(lat) ** 2)
    alt = r / np.cos(lat) - n
    return np.degrees(lat), np.degrees(lon), alt


def R_ecef_enu(lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation taking ENU vectors at (lat, lon) into ECEF."""
    la, lo = np.radians(np.asarray(lat, float)), np.radians(np.asarray(lon, float))
    sl, cl, so, co = np.sin(la), np.cos(la), np.sin(lo), np.cos(lo)
    r = np.empty((*la.shape, 3, 3))
    r[..., 0, 0], r[..., 0, 1], r[..., 0, 2] = -so, -sl * co, cl * co
    r[..., 1, 0], r[..., 1, 1], r[..., 1, 2] = co, -sl * so, cl * so
    r[..., 2, 0], r[..., 2, 1], r[..., 2, 2] = 0.0, cl, sl
    return r


class LocalFrame:
    """The clip world frame: ENU tangent at ``origin`` (lat, lon, 0 m), shifted in xy only.

    The tangent plane touches the ellipsoid under the reference agent's first fix, and z keeps
    the ellipsoidal height, so x = y = 0 at that fix and z is its altitude (CATS-V2V A.3:
    "offset within the xy-plane").
    """

    def __init__(self, lat0: float, lon0: float) -> None:
        self.lat0, self.lon0 = float(lat0), float(lon0)
        self._o = geodetic_to_ecef(np.array(lat0), np.array(lon0), np.array(0.0))
        self._R = R_ecef_enu(np.array(lat0), np.array(lon0))  # ENU0 -> ECEF

    def to_local(self, lat: np.ndarray, lon: np.ndarray, alt: np.ndarray) -> np.ndarray:
        e = geodetic_to_ecef(np.asarray(lat, float), np.asarray(lon, float), np.asarray(alt, float))
        return (e - self._o) @ self._R

    def to_geodetic(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        e = np.asarray(xyz, float) @ self._R.T + self._o
        return ecef_to_geodetic(e)

    def R_local_enu(self, lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
        """Rotation from the local-level ENU at (lat, lon) into this frame's axes."""
        return self._R.T @ R_ecef_enu(lat, lon)


def attitude_to_matrix(roll: np.ndarray, pitch: np.ndarray, azimuth: np.ndarray) -> np.ndarray:
    """INS attitude (radians) -> (..., 3, 3) ``R_enu_body`` at the vehicle's position."""
    yaw = np.pi / 2 - np.asarray(azimuth, float)
    eul = np.stack(np.broadcast_arrays(yaw, -np.asarray(pitch, float), np.asarray(roll, float)), -1)
    return Rotation.from_euler("ZYX", eul.reshape(-1, 3)).as_matrix().reshape(*eul.shape[:-1], 3, 3)


def matrix_to_attitude(r: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inverse of :func:`attitude_to_matrix`; azimuth wrapped to [0, 2 pi)."""
    r = np.asarray(r, float)
    eul = Rotation.from_matrix(r.reshape(-1, 3, 3)).as_euler("ZYX").reshape(*r.shape[:-2], 3)
    yaw, negpitch, roll = eul[..., 0], eul[..., 1], eul[..., 2]
    return roll, -negpitch, np.mod(np.pi / 2 - yaw, 2 * np.pi)


# --------------------------------------------------------------------------- conventions
# ENU <-> NED axes (its own inverse) and body FLU <-> FRD (x forward; y left/right; z up/down)
R_ENU_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
R_FLU_FRD = np.diag([1.0, -1.0, -1.0])


def enu_euler_to_matrix(roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """ROS REP-103 Euler angles (radians; yaw counter-clockwise from east) -> ``R_enu_body``
    (body x forward, y left, z up): ``Rz(yaw) Ry(pitch) Rx(roll)``."""
    eul = np.stack(np.broadcast_arrays(np.asarray(yaw, float), np.asarray(pitch, float),
                                       np.asarray(roll, float)), -1)
    return Rotation.from_euler("ZYX", eul.reshape(-1, 3)).as_matrix().reshape(*eul.shape[:-1], 3, 3)


def ned_to_enu_attitude(r_ned_frd: np.ndarray) -> np.ndarray:
    """``R_ned_frd`` (aerospace attitude of a forward-right-down body) -> ``R_enu_flu``."""
    return R_ENU_NED @ np.asarray(r_ned_frd, float) @ R_FLU_FRD


# --------------------------------------------------------------------------- UTM
# Transverse Mercator after Krueger's series to sixth order in n (Karney 2011, "Transverse
# Mercator with an accuracy of a few nanometers", J. Geodesy 85): better than 5 nm within
# 4000 km of the central meridian, so a localisation stack's UTM map frame is converted
# without adding error to sub-millimetre poses.
UTM_K0 = 0.9996
UTM_FALSE_EASTING = 500_000.0
UTM_FALSE_NORTHING_SOUTH = 10_000_000.0
_N = WGS84_F / (2.0 - WGS84_F)
_E = float(np.sqrt(WGS84_E2))
_A_RECT = WGS84_A / (1.0 + _N) * (1.0 + _N**2 / 4 + _N**4 / 64 + _N**6 / 256)
_ALPHA = np.array([
    _N / 2 - 2 * _N**2 / 3 + 5 * _N**3 / 16 + 41 * _N**4 / 180 - 127 * _N**5 / 288
    + 7891 * _N**6 / 37800,
    13 * _N**2 / 48 - 3 * _N**3 / 5 + 557 * _N**4 / 1440 + 281 * _N**5 / 630
    - 1983433 * _N**6 / 1935360,
    61 * _N**3 / 240 - 103 * _N**4 / 140 + 15061 * _N**5 / 26880 + 167603 * _N**6 / 181440,
    49561 * _N**4 / 161280 - 179 * _N**5 / 168 + 6601661 * _N**6 / 7257600,
    34729 * _N**5 / 80640 - 3418889 * _N**6 / 1995840,
    212378941 * _N**6 / 319334400,
])
_BETA = np.array([
    _N / 2 - 2 * _N**2 / 3 + 37 * _N**3 / 96 - _N**4 / 360 - 81 * _N**5 / 512
    + 96199 * _N**6 / 604800,
    _N**2 / 48 + _N**3 / 15 - 437 * _N**4 / 1440 + 46 * _N**5 / 105 - 1118711 * _N**6 / 3870720,
    17 * _N**3 / 480 - 37 * _N**4 / 840 - 209 * _N**5 / 4480 + 5569 * _N**6 / 90720,
    4397 * _N**4 / 161280 - 11 * _N**5 / 504 - 830251 * _N**6 / 7257600,
    4583 * _N**5 / 161280 - 108847 * _N**6 / 3991680,
    20648693 * _N**6 / 638668800,
])
_J2 = 2.0 * np.arange(1, 7)


def utm_central_meridian(zone: int) -> float:
    return 6.0 * zone - 183.0


def _conformal_tan(tau: np.ndarray) -> np.ndarray:
    """tau' (tangent of the conformal latitude) from tau = tan(latitude)."""
    sig = np.sinh(_E * np.arctanh(_E * tau / np.hypot(1.0, tau)))
    return tau * np.hypot(1.0, sig) - sig * np.hypot(1.0, tau)


def geodetic_to_utm(lat: np.ndarray, lon: np.ndarray, zone: int, south: bool = False
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Degrees -> (easting, northing, grid convergence gamma in radians) in ``zone``.

    ``gamma`` is the angle from true north to grid north, positive clockwise seen from above
    (east of the central meridian in the north): a true azimuth ``a`` has grid azimuth
    ``a - gamma``, so ``R_enu_grid = Rz(-gamma)`` about the local vertical."""
    phi = np.radians(np.asarray(lat, float))
    lam = np.radians(np.asarray(lon, float) - utm_central_meridian(zone))
    lam = (lam + np.pi) % (2 * np.pi) - np.pi
    tp = _conformal_tan(np.tan(phi))
    xi_p = np.arctan2(tp, np.cos(lam))
    eta_p = np.arcsinh(np.sin(lam) / np.hypot(tp, np.cos(lam)))
    j2xi = _J2 * xi_p[..., None]
    j2eta = _J2 * eta_p[..., None]
    xi = xi_p + np.sum(_ALPHA * np.sin(j2xi) * np.cosh(j2eta), -1)
    eta = eta_p + np.sum(_ALPHA * np.cos(j2xi) * np.sinh(j2eta), -1)
    p = 1.0 + np.sum(_J2 * _ALPHA * np.cos(j2xi) * np.cosh(j2eta), -1)
    q = np.sum(_J2 * _ALPHA * np.sin(j2xi) * np.sinh(j2eta), -1)
    gamma = np.arctan(tp / np.hypot(1.0, tp) * np.tan(lam)) + np.arctan2(q, p)
    easting = UTM_FALSE_EASTING + UTM_K0 * _A_RECT * eta
    northing = UTM_K0 * _A_RECT * xi + (UTM_FALSE_NORTHING_SOUTH if south else 0.0)
    return easting, northing, gamma


def utm_to_geodetic(easting: np.ndarray, northing: np.ndarray, zone: int, south: bool = False
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(easting, northing) in ``zone`` -> (lat, lon in degrees, convergence gamma in radians),
    the exact inverse of :func:`geodetic_to_utm` (Newton on the conformal latitude)."""
    n0 = UTM_FALSE_NORTHING_SOUTH if south else 0.0
    xi = (np.asarray(northing, float) - n0) / (UTM_K0 * _A_RECT)
    eta = (np.asarray(easting, float) - UTM_FALSE_EASTING) / (UTM_K0 * _A_RECT)
    j2xi = _J2 * xi[..., None]
    j2eta = _J2 * eta[..., None]
    xi_p = xi - np.sum(_BETA * np.sin(j2xi) * np.cosh(j2eta), -1)
    eta_p = eta - np.sum(_BETA * np.cos(j2xi) * np.sinh(j2eta), -1)
    tp = np.sin(xi_p) / np.hypot(np.sinh(eta_p), np.cos(xi_p))
    lam = np.arctan2(np.sinh(eta_p), np.cos(xi_p))
    tau = tp.copy()
    for _ in range(5):  # quadratic convergence: 2 iterations reach 1e-15 here, 5 to be safe
        tpi = _conformal_tan(tau)
        dtau = ((tp - tpi) * (1.0 + (1.0 - WGS84_E2) * tau**2)
                / ((1.0 - WGS84_E2) * np.hypot(1.0, tpi) * np.hypot(1.0, tau)))
        tau = tau + dtau
    lat = np.degrees(np.arctan(tau))
    lon = np.degrees(lam) + utm_central_meridian(zone)
    _, _, gamma = geodetic_to_utm(lat, lon, zone, south)
    return lat, lon, gamma


def rot_z(angle: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations by ``angle`` (radians, counter-clockwise) about z."""
    a = np.asarray(angle, float)
    c, s = np.cos(a), np.sin(a)
    r = np.zeros((*a.shape, 3, 3))
    r[..., 0, 0], r[..., 0, 1], r[..., 1, 0], r[..., 1, 1], r[..., 2, 2] = c, -s, s, c, 1.0
    return r
