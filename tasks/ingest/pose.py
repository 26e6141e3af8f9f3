"""Pose sources -> the one pose track: rows of the raw ``ins`` table.

Whatever an agent's pose is delivered as (``schemas.clip.PoseSource``: a vendor INS, an
Odometry / PoseStamped in a local map frame, NavSatFix + Imu orientation, a surveyed fixed
pose), ingest turns it into the same columns: WGS84 ``lat``/``lon`` (degrees) and ``alt``,
the attitude relative to the local level at the vehicle (``roll``, ``pitch``, ``azimuth``
from north clockwise, radians, body x forward / y left / z up) and ENU velocities. Anonymize
turns that into local-ENU ``ego_poses``; nothing downstream knows which source it was.

The numeric core is pure functions on arrays; the ``*Collector`` classes gather message
fields during ingest's single pass over a bag.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from v2xlake.schemas.clip import Datum, PoseSource
from v2xlake.tasks.geodesy import LocalFrame, matrix_to_attitude
from v2xlake.tasks.geometry import quat_to_matrix
from v2xlake.tasks.ingest.bagopen import header_stamp_ns
from v2xlake.tasks.ingest.ins import INS_ALIASES
from v2xlake.tasks.interpolate import interpolate_poses

INS_COLUMNS = ("t_ns", "lat", "lon", "alt", "roll", "pitch", "azimuth", "ve", "vn", "vu",
               "rtk_status")
FIELD_OF = {"lat": "lat", "lon": "lon", "alt": "height", "roll": "roll", "pitch": "pitch",
            "azimuth": "heading", "ve": "v_east", "vn": "v_north", "vu": "v_up",
            "rtk_status": "status"}


class PoseSourceError(ValueError):
    """A pose source the messages do not fit (missing field, too few samples)."""


# ------------------------------------------------------------------ numeric core
def local_to_ins(t_ns: np.ndarray, xyz_map: np.ndarray, R_map_body: np.ndarray,
                 v_map: np.ndarray | None, datum: Datum | None) -> dict[str, np.ndarray]:
    """Poses in a local ENU map frame -> ``ins`` columns.

    The map frame is ENU at the datum's geodetic origin (after removing its false-origin
    ``offset``); without an origin it is taken as already local (nominal origin 0°, 0°). The
    attitude becomes relative to the local level at each position (the INS convention), so
    anonymize's local frame rebuilds exactly these poses up to one rigid transform.
    Velocities: given (map axes), or central differences of the positions.
    """
    d = datum or Datum()
    lat0 = d.lat if d.lat is not None else 0.0
    lon0 = d.lon if d.lon is not None else 0.0
    frame = LocalFrame(lat0, lon0)
    local = np.asarray(xyz_map, float) - np.asarray(d.offset, float)
    local = local + np.array([0.0, 0.0, d.alt])
    lat, lon, alt = frame.to_geodetic(local)
    R_enu_map = np.swapaxes(frame.R_local_enu(lat, lon), -1, -2)  # map axes -> local level
    R_enu_body = R_enu_map @ R_map_body
    roll, pitch, azimuth = matrix_to_attitude(R_enu_body)
    if v_map is None:
        v_map = _finite_velocity(np.asarray(t_ns, np.int64), local)
    v = np.einsum("nij,nj->ni", R_enu_map, np.asarray(v_map, float))
    return _columns(t_ns, lat, lon, alt, roll, pitch, azimuth, v)


def navsat_imu_to_ins(t_fix: np.ndarray, lat: np.ndarray, lon: np.ndarray, alt: np.ndarray,
                      status: np.ndarray, t_att: np.ndarray, q_att_wxyz: np.ndarray
                      ) -> dict[str, np.ndarray]:
    """NavSatFix positions + Imu orientations (ENU, body FLU) -> ``ins`` columns at the fix
    times, the attitude SLERPed between the two nearest orientations (fixes outside the
    attitude span are dropped: no extrapolation)."""
    t_fix, t_att = np.asarray(t_fix, np.int64), np.asarray(t_att, np.int64)
    order = np.argsort(t_att, kind="stable")
    t_att, q = t_att[order], np.asarray(q_att_wxyz, float)[order]
    keep_att = np.concatenate([[True], np.diff(t_att) > 0])
    t_att, q = t_att[keep_att], q[keep_att]
    if len(t_att) < 2:
        raise PoseSourceError(f"{len(t_att)} attitude sample(s): at least 2 are needed")
    inside = (t_fix >= t_att[0]) & (t_fix <= t_att[-1])
    if inside.sum() < 2:
        raise PoseSourceError("fewer than 2 position fixes inside the attitude's time span")
    t = t_fix[inside]
    _, q_t = interpolate_poses(t_att, np.zeros((len(t_att), 3)), q, t)  # the one SLERP
    R = quat_to_matrix(q_t)
    roll, pitch, azimuth = matrix_to_attitude(R)
    la, lo, al = (np.asarray(a, float)[inside] for a in (lat, lon, alt))
    frame = LocalFrame(float(la[0]), float(lo[0]))
    v = _finite_velocity(t, frame.to_local(la, lo, al).reshape(-1, 3))
    v = np.einsum("nij,nj->ni", np.swapaxes(frame.R_local_enu(la, lo), -1, -2), v)
    cols = _columns(t, la, lo, al, roll, pitch, azimuth, v)
    cols["rtk_status"] = np.asarray(status, np.int64)[inside]
    return cols


def fixed_to_ins(t_ns: np.ndarray, position: list[float], attitude_deg: list[float]
                 ) -> dict[str, np.ndarray]:
    """A surveyed, constant pose (lat/lon degrees, alt; roll/pitch/heading degrees)."""
    n = len(t_ns)
    roll, pitch, heading = (math.radians(a) for a in attitude_deg)
    return _columns(np.asarray(t_ns, np.int64), np.full(n, position[0]),
                    np.full(n, position[1]), np.full(n, position[2]), np.full(n, roll),
                    np.full(n, pitch), np.full(n, heading % (2 * math.pi)), np.zeros((n, 3)))


def vendor_ins(cols: dict[str, list[Any]], src: PoseSource) -> dict[str, np.ndarray]:
    """A vendor INS's values in its own units and conventions -> ``ins`` columns."""
    out: dict[str, np.ndarray] = {
        k: np.asarray(v, dtype=np.int64 if k in ("t_ns", "rtk_status") else np.float64)
        for k, v in cols.items()}
    if src.angle_unit == "deg":
        for k in ("roll", "pitch", "azimuth"):
            out[k] = np.radians(out[k])
    if src.heading == "east_ccw":  # a yaw from east, counter-clockwise -> azimuth
        out["azimuth"] = np.pi / 2 - out["azimuth"]
    out["azimuth"] = np.mod(out["azimuth"], 2 * np.pi)
    if src.velocity_axes == "ned":  # the third velocity is down
        out["vu"] = -out["vu"]
    return out


def _finite_velocity(t_ns: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    if len(t_ns) < 2:
        return np.zeros_like(xyz)
    return np.gradient(xyz, t_ns.astype(np.float64) * 1e-9, axis=0)


def _columns(t: np.ndarray, lat: np.ndarray, lon: np.ndarray, alt: np.ndarray,
             roll: np.ndarray, pitch: np.ndarray, azimuth: np.ndarray, v_enu: np.ndarray
             ) -> dict[str, np.ndarray]:
    n = len(t)
    return {"t_ns": np.asarray(t, np.int64), "lat": np.asarray(lat, float).reshape(n),
            "lon": np.asarray(lon, float).reshape(n), "alt": np.asarray(alt, float).reshape(n),
            "roll": np.asarray(roll, float).reshape(n),
            "pitch": np.asarray(pitch, float).reshape(n),
            "azimuth": np.asarray(azimuth, float).reshape(n),
            "ve": v_enu[:, 0], "vn": v_enu[:, 1], "vu": v_enu[:, 2],
            "rtk_status": np.zeros(n, np.int64)}


# ------------------------------------------------------------------ message collectors
def _vec(v: Any) -> list[float]:
    return [float(v.x), float(v.y), float(v.z)]


def _quat(q: Any) -> list[float]:
    return [float(q.w), float(q.x), float(q.y), float(q.z)]


@dataclass
class PoseCollector:
    """Gathers one agent's pose messages during ingest, then gives the ``ins`` columns."""

    src: PoseSource
    t: list[int] = field(default_factory=list)
    xyz: list[list[float]] = field(default_factory=list)
    quat: list[list[float]] = field(default_factory=list)
    vel: list[list[float]] = field(default_factory=list)
    fix: list[tuple[int, float, float, float, int]] = field(default_factory=list)
    att: list[tuple[int, list[float]]] = field(default_factory=list)
    vendor: dict[str, list[Any]] = field(default_factory=lambda: {c: [] for c in INS_COLUMNS})
    _names: dict[str, str] | None = None

    def topics(self) -> dict[str, str]:
        """{topic: role} this source reads."""
        out: dict[str, str] = {}
        if self.src.topic and self.src.kind in ("ins", "odometry", "navsat_imu"):
            out[self.src.topic] = self.src.kind
        if self.src.attitude_topic:
            out[self.src.attitude_topic] = "attitude"
        return out

    def add(self, role: str, msg: Any) -> None:
        t = header_stamp_ns(msg)
        if role == "odometry":
            pose = msg.pose.pose if hasattr(msg.pose, "pose") else msg.pose
            self.t.append(t)
            self.xyz.append(_vec(pose.position))
            self.quat.append(_quat(pose.orientation))
            if hasattr(msg, "twist"):  # Odometry: twist in the child (body) frame
                self.vel.append(_vec(msg.twist.twist.linear))
        elif role == "navsat_imu":
            self.fix.append((t, float(msg.latitude), float(msg.longitude), float(msg.altitude),
                             int(msg.status.status)))
        elif role == "attitude":
            self.att.append((t, _quat(msg.orientation)))
        else:
            self._vendor(t, msg)

    def _vendor(self, t: int, msg: Any) -> None:
        if self._names is None:
            given = self.src.fields
            names: dict[str, str] = {}
            for col, key in FIELD_OF.items():
                name = getattr(given, key) if given is not None else None
                cands = (name,) if name else INS_ALIASES[col]
                hit = next((n for n in cands if hasattr(msg, n)), None)
                if hit is None:
                    raise PoseSourceError(
                        f"INS message {type(msg).__name__} has none of the fields "
                        f"{list(cands)} (needed for column {col!r}; map it in clip.yaml "
                        f"pose.fields.{key})")
                names[col] = hit
            self._names = names
        self.vendor["t_ns"].append(t)
        for col, name in self._names.items():
            v = getattr(msg, name)
            if col == "rtk_status" and not isinstance(v, int | float):
                v = getattr(v, "status", v)
            self.vendor[col].append(v)

    def columns(self, t_span: tuple[int, int] | None) -> dict[str, np.ndarray] | None:
        """The ``ins`` columns (None: no pose). ``t_span`` (first, last sensor stamp) bounds
        a fixed pose's samples."""
        kind = self.src.kind
        if kind == "none":
            return None
        if kind == "ins":
            return vendor_ins(self.vendor, self.src) if self.vendor["t_ns"] else None
        if kind == "odometry":
            if not self.t:
                return None
            t = np.asarray(self.t, np.int64)
            R = quat_to_matrix(_unit(np.asarray(self.quat, float)))
            v = None
            if self.vel and len(self.vel) == len(self.t):
                v = np.einsum("nij,nj->ni", R, np.asarray(self.vel, float))
            return local_to_ins(t, np.asarray(self.xyz, float), R, v, self.src.datum)
        if kind == "navsat_imu":
            if not self.fix or not self.att:
                return None
            f = np.asarray([x[:4] for x in self.fix], float)
            return navsat_imu_to_ins(
                np.asarray([x[0] for x in self.fix], np.int64), f[:, 1], f[:, 2], f[:, 3],
                np.asarray([x[4] for x in self.fix], np.int64),
                np.asarray([a[0] for a in self.att], np.int64),
                _unit(np.asarray([a[1] for a in self.att], float)))
        # fixed: samples over the recording (and a little beyond) at rate_hz
        if t_span is None:
            return None
        step = int(1e9 / (self.src.rate_hz or 10.0))
        t = np.arange(t_span[0] - step, t_span[1] + 2 * step, step, dtype=np.int64)
        assert self.src.position is not None and self.src.attitude is not None
        return fixed_to_ins(t, list(self.src.position), list(self.src.attitude))


def _unit(q: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(np.abs(n - 1.0) > 1e-3):
        raise PoseSourceError("orientation quaternions are not unit length (|q| off by more "
                              f"than 1e-3, worst {float(np.abs(n - 1).max()):.3g})")
    return q / n


__all__ = ["PoseCollector", "PoseSourceError", "fixed_to_ins", "local_to_ins",
           "navsat_imu_to_ins", "vendor_ins"]
