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
