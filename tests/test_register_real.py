"""The GICP backends on real scans, read straight from real drivers' bags with ``rosbags``
(not through our ingest, not from our simulator).

The default backend (``sparse``: a spread sample of the source, surfaces computed where
correspondences land) was chosen on the simulated cooperative boulevard; here it must land
where small_gicp (every point of both clouds) lands on consecutive scans of a moving Ouster
OS-1-128 (~2.5 m between scans, raw: not deskewed) and a standing Velodyne VLP-16, both
started 37 cm / 0 deg off. The true motion is not known, so the check is agreement of two
implementations of the same cost, plus the motion's plausibility.
"""

from __future__ import annotations

from itertools import pairwise
from typing import Any

import numpy as np
import pytest

from tests.fixtures.real import SHARED_REAL, requires_real_data
from v2xlake.tasks.geometry import rotation_angle
from v2xlake.tasks.register.backends import BackendName, make_backend
from v2xlake.tasks.register.config import GicpSection
from v2xlake.tasks.register.voxel import voxel_downsample

OUSTER = "bags/ouster_os1_128_3frames_ros2"
VLP16 = "bags/velodyne_vlp16_pointcloud2_ros2"


def _scans(bag: str, topic: str) -> list[np.ndarray]:
    """Every PointCloud2 on ``topic`` as (N, 3) float64, invalid and sub-metre returns out."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    out = []
    with AnyReader([SHARED_REAL / bag],
                   default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        conns = [c for c in reader.connections if c.topic == topic]
        for conn, _, raw in reader.messages(conns):
            msg: Any = reader.deserialize(raw, conn.msgtype)
            off = {f.name: f.offset for f in msg.fields}
            dt = np.dtype({"names": ["x", "y", "z"], "formats": ["<f4"] * 3,
                           "offsets": [off["x"], off["y"], off["z"]],
                           "itemsize": msg.point_step})
            a: Any = np.frombuffer(bytes(msg.data), dt, count=msg.width * msg.height)
            p = np.stack([a["x"], a["y"], a["z"]], axis=1).astype(np.float64)
            out.append(p[np.isfinite(p).all(axis=1) & (np.linalg.norm(p, axis=1) > 1.0)])
    return out


@requires_real_data(OUSTER, VLP16)
@pytest.mark.parametrize(("bag", "topic", "max_motion_m"),
                         [(OUSTER, "/ouster/points", 0.5), (VLP16, "/points_raw", 0.01)])
def test_sparse_lands_where_small_gicp_lands_on_real_scans(bag: str, topic: str,
                                                           max_motion_m: float) -> None:
    scans = _scans(bag, topic)
    assert len(scans) >= 3
    p = GicpSection()
    init = np.eye(4)
    init[:3, 3] = (0.3, -0.2, 0.05)
    for a, b in pairwise(scans):
        found = {}
        names: tuple[BackendName, ...] = ("small_gicp", "sparse")
        for name in names:
            be = make_backend(name, p)
            tgt = be.prepare_points(voxel_downsample(a, p.voxel_m, p.max_range_m))
            src = be.prepare_points(voxel_downsample(b, p.source_voxel_m, p.max_range_m))
            r = be.align(tgt, src, init)
            assert r.converged, name
            found[name] = r.T
        assert np.linalg.norm(found["small_gicp"][:3, 3]) < max_motion_m
        D = np.linalg.inv(found["small_gicp"]) @ found["sparse"]
        assert np.linalg.norm(D[:3, 3]) < 0.005, D
        assert np.degrees(rotation_angle(D)) < 0.03, D
