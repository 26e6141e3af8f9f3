"""nuScenes radar files: a lake radar scan as the binary PCD nuscenes-devkit reads.

The devkit's ``RadarPointCloud.from_file`` (1.2.0) parses a fixed header (comment, VERSION,
FIELDS, SIZE, TYPE, COUNT, WIDTH, HEIGHT, VIEWPOINT, POINTS, DATA binary, in that order)
and 18 packed fields per point (43 bytes: Continental ARS 408 cluster fields), then keeps
only points whose ``invalid_state`` is in ``[0]``, ``dyn_prop`` in ``range(7)`` and
``ambig_state`` in ``[3]``. The lake's radars give x, y, z, a radial (Doppler) velocity and
RCS per detection and nothing else, so the remaining fields are filled with the values
that mean "valid, measured, unambiguous" and every exported detection survives the
devkit's default filters:

- ``invalid_state`` 0 (valid), ``ambig_state`` 3 (unambiguous: the lake's velocities are
  already resolved), ``is_quality_valid`` 1, ``pdh0`` 1 (false-alarm probability < 25 %);
- ``x_rms``, ``y_rms``, ``vx_rms``, ``vy_rms`` 0 (the ARS code of the smallest spread; the
  lake carries no per-detection uncertainty);
- ``dyn_prop`` from the ego-compensated radial velocity: 1 stationary when its magnitude is
  at most ``moving_mps``, else 0 moving (away) or 2 oncoming (towards the sensor);
- ``id`` the detection's index in the scan (int16, so it wraps past 32767);
- ``rcs`` NaN -> ``RCS_MISSING_DBSM`` (-64 dBsm, the lowest RCS an ARS 408 reports): a NaN
  cannot be written because the devkit reads a NaN anywhere in the first point as "empty
  cloud", and the weakest reportable value is the least misleading finite stand-in.

An empty scan is one all-NaN point (WIDTH 1), the devkit's own convention for an empty
cloud (its parser asserts WIDTH > 0). The data block ends with one newline byte: the
devkit's parser asserts every field ends strictly before the end of the data.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from v2xlake.storage.reader import RadarScan
from v2xlake.tasks.export.common import write_atomic

RADAR_PCD_DTYPE = np.dtype([
    ("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("dyn_prop", "i1"), ("id", "<i2"),
    ("rcs", "<f4"), ("vx", "<f4"), ("vy", "<f4"), ("vx_comp", "<f4"), ("vy_comp", "<f4"),
    ("is_quality_valid", "i1"), ("ambig_state", "i1"), ("x_rms", "i1"), ("y_rms", "i1"),
    ("invalid_state", "i1"), ("pdh0", "i1"), ("vx_rms", "i1"), ("vy_rms", "i1")])
RCS_MISSING_DBSM = -64.0
DYN_MOVING, DYN_STATIONARY, DYN_ONCOMING = 0, 1, 2
_PCD_TYPE = {"f": "F", "i": "I", "u": "U"}


def pcd_header(dtype: np.dtype, n: int) -> bytes:
    """The PCD v0.7 header for ``n`` points of a packed structured ``dtype``."""
    fields = dtype.names or ()
    sizes = [dtype.fields[f][0].itemsize for f in fields]  # type: ignore[index]
    types = [_PCD_TYPE[dtype.fields[f][0].kind] for f in fields]  # type: ignore[index]
    lines = ["# .PCD v0.7 - Point Cloud Data file format", "VERSION 0.7",
             "FIELDS " + " ".join(fields), "SIZE " + " ".join(map(str, sizes)),
             "TYPE " + " ".join(types), "COUNT " + " ".join("1" for _ in fields),
             f"WIDTH {n}", "HEIGHT 1", "VIEWPOINT 0 0 0 1 0 0 0", f"POINTS {n}",
             "DATA binary"]
    return ("\n".join(lines) + "\n").encode("ascii")


def _radial(xyz: np.ndarray, v_r: np.ndarray, v_sensor: np.ndarray | None
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit lines of sight (N, 3), raw and ego-compensated radial velocities (N,)."""
    x = xyz.astype(np.float64)
    rng = np.linalg.norm(x, axis=1, keepdims=True)
    u = np.divide(x, rng, out=np.zeros_like(x), where=rng > 0)
    v = v_r.astype(np.float64)
    return u, v, (v + u @ np.asarray(v_sensor, np.float64) if v_sensor is not None else v)


def radar_velocities(xyz: np.ndarray, v_r: np.ndarray, v_sensor: np.ndarray | None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Cartesian (vx, vy) and ego-compensated (vx_comp, vy_comp) in the radar frame, (N, 2)
    each.

    A radar measures only the component of a target's velocity along the line of sight
    ``u = xyz / |xyz|``; nuScenes stores Cartesian velocities, so the measured component is
    written as the vector ``v_r * u`` and (vx, vy) are its x, y parts: the projection of the
    target's relative velocity onto the line of sight, not its full velocity (a crossing
    target reads ~0, as it does on a real radar). The lake's ``v_r`` is relative to the
    moving sensor, ``v_r = (v_target - v_sensor) . u``; compensation adds back the sensor's
    own velocity along the line of sight, ``v_comp = v_r + v_sensor . u``, so static targets
    read ~0. ``v_sensor`` (3,) is the radar origin's velocity in radar axes at the scan time;
    None (no ego motion known) leaves the compensated velocities equal to the raw ones.
    """
    u, v, vc = _radial(xyz, v_r, v_sensor)
    return v[:, None] * u[:, :2], vc[:, None] * u[:, :2]


def radar_pcd_points(scan: RadarScan, v_sensor: np.ndarray | None, moving_mps: float
                     ) -> np.ndarray:
    """A scan as a ``RADAR_PCD_DTYPE`` array (see the module docstring for each field);
    ``v_sensor`` as in :func:`radar_velocities`."""
    n = len(scan)
    if n == 0:
        empty = np.zeros(1, RADAR_PCD_DTYPE)
        for f in ("x", "y", "z"):
            empty[f] = np.nan
        return empty
    v, vc = radar_velocities(scan.xyz, scan.velocity, v_sensor)
    v_rad = _radial(scan.xyz, scan.velocity, v_sensor)[2]
    arr = np.zeros(n, RADAR_PCD_DTYPE)
    arr["x"], arr["y"], arr["z"] = scan.xyz[:, 0], scan.xyz[:, 1], scan.xyz[:, 2]
    arr["rcs"] = np.where(np.isfinite(scan.rcs), scan.rcs, RCS_MISSING_DBSM)
    arr["vx"], arr["vy"] = v[:, 0], v[:, 1]
    arr["vx_comp"], arr["vy_comp"] = vc[:, 0], vc[:, 1]
    arr["dyn_prop"] = np.where(np.abs(v_rad) <= moving_mps, DYN_STATIONARY,
                               np.where(v_rad > 0, DYN_MOVING, DYN_ONCOMING))
    arr["id"] = (np.arange(n) % 32768).astype(np.int16)
    arr["is_quality_valid"] = 1
    arr["ambig_state"] = 3
    arr["invalid_state"] = 0
    arr["pdh0"] = 1
    return arr


def write_radar_pcd(path: Path, points: np.ndarray) -> int:
    """Write ``RADAR_PCD_DTYPE`` points as a devkit-readable binary PCD, atomically; returns
    the number of detections (0 for the one-NaN-point empty cloud)."""
    if points.dtype != RADAR_PCD_DTYPE:
        raise ValueError(f"radar PCD points must be {RADAR_PCD_DTYPE}, got {points.dtype}")
    write_atomic(path, pcd_header(RADAR_PCD_DTYPE, len(points)) + points.tobytes() + b"\n")
    return 0 if len(points) == 1 and np.isnan(points["x"][0]) else len(points)
