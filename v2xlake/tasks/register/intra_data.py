"""Readers for the real lidar2lidar recordings' calibration files (issue #27): the published
``initial_extrinsic.txt`` (roll pitch yaw deg, tx ty tz m per device, side LiDAR -> top) and
a 4x4 JSON extrinsic (SensorsCalibration's ``param.sensor_calib.data``), plus the points of a
PCD file (Open3D reads ``binary_compressed``)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from v2xlake.tasks.register.intra import euler_zyx


def read_initial_extrinsics(path: str | Path) -> dict[int, np.ndarray]:
    """``device_id -> T_top_device`` (4x4) from an ``initial_extrinsic.txt``."""
    out: dict[int, np.ndarray] = {}
    device: int | None = None
    for line in Path(path).read_text().splitlines():
        key, _, val = line.partition(":")
        if key.strip() == "device_id":
            device = int(val)
        elif key.strip().startswith("(Roll") and device is not None:
            roll, pitch, yaw, tx, ty, tz = (float(v) for v in val.split())
            T = np.eye(4)
            T[:3, :3] = euler_zyx(roll, pitch, yaw)
            T[:3, 3] = (tx, ty, tz)
            out[device] = T
    return out


def read_json_extrinsic(path: str | Path) -> np.ndarray:
    """The first 4x4 ``sensor_calib`` matrix of a calibration JSON, as written (not
    necessarily rigid: ``intra.nearest_rigid`` says how far it is and gives the nearest rigid
    transform, which is what ``geometry.invert`` and a registration need)."""
    doc = json.loads(Path(path).read_text())
    entry = next(iter(doc.values()))
    return np.asarray(entry["param"]["sensor_calib"]["data"], dtype=np.float64).reshape(4, 4)


def read_pcd_xyz(path: str | Path) -> np.ndarray:
    """(N, 3) finite float64 points of a PCD file."""
    import open3d as o3d

    pc = o3d.t.io.read_point_cloud(Path(path))
    xyz = pc.point.positions.numpy().astype(np.float64)
    return np.ascontiguousarray(xyz[np.isfinite(xyz).all(axis=1)])
