"""IMU and GNSS messages -> rows of the raw ``imu`` / ``gnss`` tables.

Pose messages (a vendor INS, Odometry, ...) become the raw ``ins`` / ``ego_poses`` track
through ``tasks.ingest.pose``.
"""

from __future__ import annotations

import math
from typing import Any

from v2xlake.tasks.ingest.bagopen import header_stamp_ns


class ImuDecoder:
    def __init__(self) -> None:
        self.cols: dict[str, list[Any]] = {c: [] for c in
                                           ("t_ns", "wx", "wy", "wz", "ax", "ay", "az")}

    def add(self, msg: Any) -> None:
        w, a = msg.angular_velocity, msg.linear_acceleration
        for k, v in (("t_ns", header_stamp_ns(msg)), ("wx", w.x), ("wy", w.y), ("wz", w.z),
                     ("ax", a.x), ("ay", a.y), ("az", a.z)):
            self.cols[k].append(v)


class GnssDecoder:
    """``sensor_msgs/NavSatFix``; ``sigma_h`` from the horizontal covariance when known."""

    def __init__(self) -> None:
        self.cols: dict[str, list[Any]] = {c: [] for c in
                                           ("t_ns", "lat", "lon", "alt", "status", "sigma_h")}

    def add(self, msg: Any) -> None:
        cov = list(msg.position_covariance)
        known = int(msg.position_covariance_type) != 0 and len(cov) == 9
        sigma = math.sqrt(max(0.5 * (cov[0] + cov[4]), 0.0)) if known else None
        for k, v in (("t_ns", header_stamp_ns(msg)), ("lat", msg.latitude),
                     ("lon", msg.longitude), ("alt", msg.altitude),
                     ("status", int(msg.status.status)), ("sigma_h", sigma)):
            self.cols[k].append(v)
