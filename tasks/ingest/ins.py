"""INS, IMU and GNSS messages -> rows of the raw ``ins`` / ``imu`` / ``gnss`` tables.

The INS is usually a vendor type (registered from clip.yaml's ``message_definitions``), so
fields are found by name with the aliases vendors use; a type that lacks one is rejected with
the missing field named rather than ingested with zeros.
"""

from __future__ import annotations

import math
from typing import Any

from v2xlake.tasks.ingest.bagopen import header_stamp_ns

# table column -> accepted message field names, first match wins
INS_ALIASES: dict[str, tuple[str, ...]] = {
    "lat": ("latitude", "lat"),
    "lon": ("longitude", "lon"),
    "alt": ("altitude", "height", "alt"),
    "roll": ("roll",),
    "pitch": ("pitch",),
    "azimuth": ("azimuth", "heading", "yaw"),
    "ve": ("east_velocity", "ve", "velocity_east"),
    "vn": ("north_velocity", "vn", "velocity_north"),
    "vu": ("up_velocity", "vu", "velocity_up"),
    "rtk_status": ("rtk_status", "status", "solution_status"),
}


class InsFieldError(KeyError):
    pass


def _field_map(msg: Any) -> dict[str, str]:
    out = {}
    for col, names in INS_ALIASES.items():
        hit = next((n for n in names if hasattr(msg, n)), None)
        if hit is None:
            raise InsFieldError(f"INS message {type(msg).__name__} has none of the fields "
                                f"{list(names)} (needed for column {col!r})")
        out[col] = hit
    return out


class InsDecoder:
    """Collects INS rows; resolves the field mapping on the first message."""

    def __init__(self) -> None:
        self.cols: dict[str, list[Any]] = {c: [] for c in ("t_ns", *INS_ALIASES)}
        self._map: dict[str, str] | None = None

    def add(self, msg: Any) -> None:
        if self._map is None:
            self._map = _field_map(msg)
        self.cols["t_ns"].append(header_stamp_ns(msg))
        for col, name in self._map.items():
            v = getattr(msg, name)
            if col == "rtk_status" and not isinstance(v, int | float):
                v = getattr(v, "status", v)
            self.cols[col].append(v)


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
