"""UTM and attitude conventions (tasks.geodesy) against independent references.

The UTM reference values were computed once with PROJ (pyproj 3.7.2, ``+proj=utm
+ellps=WGS84``, ``Proj.get_factors().meridian_convergence``) outside the project, which does
not depend on it; the convergence is also checked against finite differences of the
projection itself, and the attitude conventions against SciPy's Euler angles."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from v2xlake.tasks.geodesy import (
    R_ecef_enu,
    attitude_to_matrix,
    enu_euler_to_matrix,
    geodetic_to_ecef,
    geodetic_to_utm,
    matrix_to_attitude,
    ned_to_enu_attitude,
    rot_z,
    utm_central_meridian,
    utm_to_geodetic,
)

# zone, south, lat, lon -> easting, northing (m), convergence (deg), from PROJ
PROJ = [
    (32, False, 48.137154, 11.576124, 691650.366850, 5334754.246573, 1.919135097743),
    (32, False, 52.520008, 13.404954, 798809.629410, 5828000.598631, 3.498190592477),
    (33, True, -33.86882, 13.209295999999995, 334368.302264, 6250946.121011, 0.998174605611),
    (17, False, 40.0, -84.5, 201208.442973, 4433627.340339, -2.251419264541),
    (10, False, 37.7749, -122.4194, 551130.768481, 4180998.881499, 0.355660529073),
]


@pytest.mark.parametrize(("zone", "south", "lat", "lon", "e", "n", "gamma"), PROJ)
def test_utm_matches_proj(zone: int, south: bool, lat: float, lon: float, e: float, n: float,
                          gamma: float) -> None:
    E, N, g = geodetic_to_utm(np.array([lat]), np.array([lon]), zone, south)
    assert abs(E[0] - e) < 1e-6 and abs(N[0] - n) < 1e-6  # PROJ printed to the micrometre
    assert abs(np.degrees(g[0]) - gamma) < 1e-9
    la, lo, g2 = utm_to_geodetic(E, N, zone, south)
    assert abs(la[0] - lat) * 1.1e5 < 1e-8 and abs(lo[0] - lon) * 1.1e5 < 1e-8
    assert g2[0] == pytest.approx(g[0], abs=1e-15)


@settings(max_examples=50, deadline=None)
@given(st.integers(1, 60), st.floats(-79.0, 83.0), st.floats(-3.5, 3.5))
def test_utm_round_trip_and_convergence(zone: int, lat: float, dlon: float) -> None:
    """Inverse of forward to a nanometre; gamma is grid north's azimuth from true north
    (clockwise), so a step to true north moves the projected point gamma counter-clockwise
    of grid north, and ``R_enu_grid = Rz(-gamma)`` puts grid north at azimuth gamma."""
    lon = utm_central_meridian(zone) + dlon
    south = lat < 0
    E, N, g = geodetic_to_utm(np.array([lat]), np.array([lon]), zone, south)
    la, lo, _ = utm_to_geodetic(E, N, zone, south)
    p0 = geodetic_to_ecef(np.array([lat]), np.array([lon]), np.array([0.0]))
    p1 = geodetic_to_ecef(la, lo, np.array([0.0]))
    assert np.linalg.norm(p1 - p0) < 1e-8
    d = 1e-6  # degrees: ~0.1 m
    E2, N2, _ = geodetic_to_utm(np.array([lat + d]), np.array([lon]), zone, south)
    north_on_grid = np.arctan2(E2[0] - E[0], N2[0] - N[0])  # clockwise from grid north
    assert north_on_grid == pytest.approx(-g[0], abs=1e-7)
    R = rot_z(-g)[0]  # R_enu_grid: grid north in ENU axes
    grid_north_enu = R @ np.array([0.0, 1.0, 0.0])
    assert np.arctan2(grid_north_enu[0], grid_north_enu[1]) == pytest.approx(g[0], abs=1e-12)


@settings(max_examples=50, deadline=None)
@given(st.floats(-1.5, 1.5), st.floats(-1.4, 1.4), st.floats(0.0, 6.28))
def test_attitude_conventions(roll: float, pitch: float, az: float) -> None:
    """Aerospace NED angles (the INS convention of the raw zone) = REP-103 ENU Euler angles
    with yaw = pi/2 - azimuth and the pitch sign flipped; the NED quaternion conversion maps
    one onto the other."""
    R = attitude_to_matrix(roll, pitch, az)
    assert np.allclose(enu_euler_to_matrix(roll, -pitch, np.pi / 2 - az), R, atol=1e-12)
    R_ned = Rotation.from_euler("ZYX", [az, pitch, roll]).as_matrix()
    assert np.allclose(ned_to_enu_attitude(R_ned), R, atol=1e-12)
    r2, p2, a2 = matrix_to_attitude(R)
    assert np.allclose(attitude_to_matrix(r2, p2, a2), R, atol=1e-12)
    # heading 90 deg: the nose points east; pitch up: the nose rises
    assert np.allclose(attitude_to_matrix(0.0, 0.0, np.pi / 2)[:, 0], [1, 0, 0], atol=1e-12)
    assert attitude_to_matrix(0.0, 0.1, 0.0)[2, 0] > 0
    assert np.allclose(R_ecef_enu(np.array(0.0), np.array(0.0))[:, 2], [1, 0, 0])
