"""Pose sources -> the one pose track of an agent (``clip.yaml`` ``pose:`` block).

Whatever the recording carries — a vendor INS message, ``nav_msgs/Odometry`` /
``PoseStamped`` / ``PoseWithCovarianceStamped`` in a map frame, ``NavSatFix`` + ``Imu``, dynamic
``/tf``, a surveyed fixed pose — ingest turns it into one :class:`Track`: samples of
``T_frame_ego`` (the agent's ego frame, not the INS box or the antenna) with velocity and a
status, where ``frame`` is ECEF when the source is georeferenced and the shared local map
otherwise. A georeferenced track is written as the raw ``ins`` table (WGS84 + attitude to the
local level, as an INS reports it, so the existing anonymize -> ``ego_poses`` path is the one
path); a local-map track as the raw ``ego_poses`` table in map coordinates. Nothing
downstream of ingest knows which source it was.

Every conversion is exact to float64 (no flat-earth shortcut): datum -> ECEF through
``tasks.geodesy`` (UTM by Krueger's series, nm-accurate), attitude through the local-level
rotation at each sample's own position, lever arms applied in the source frame.

The numeric core (``build_*``) works on arrays; :class:`PoseCollector` gathers them from
messages during ingest's single pass.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from v2xlake.schemas.clip import (
    AgentConfig,
    AngleUnit,
    AttitudeConvention,
    Datum,
    DatumKind,
    FixedPose,
    Heading,
    InsFields,
    InsPose,
    NoPose,
    OdometryPose,
    PitchSign,
    RollSign,
    SplitPose,
    TfPose,
    Vec3Paths,
    VelocityFrame,
)
from v2xlake.tasks.geodesy import (
    R_ENU_NED,
    R_ecef_enu,
    attitude_to_matrix,
    ecef_to_geodetic,
    geodetic_to_ecef,
    matrix_to_attitude,
    ned_to_enu_attitude,
    rot_z,
    utm_to_geodetic,
)
from v2xlake.tasks.geometry import matrix_to_quat, quat_to_matrix
from v2xlake.tasks.ingest.bagopen import header_stamp_ns
from v2xlake.tasks.interpolate import interpolate_poses

STATUS_UNKNOWN = -2  # the source reports no solution status (NavSatFix uses -1..2)

ODOMETRY_TYPES = ("nav_msgs/msg/Odometry", "geometry_msgs/msg/PoseStamped",
                  "geometry_msgs/msg/PoseWithCovarianceStamped")
TF_TYPE = "tf2_msgs/msg/TFMessage"
NAVSATFIX = "sensor_msgs/msg/NavSatFix"
IMU = "sensor_msgs/msg/Imu"
# velocity messages with a fixed layout: path of the linear velocity vector
VELOCITY_PATHS = {
    "geometry_msgs/msg/TwistStamped": "twist.linear",
    "geometry_msgs/msg/TwistWithCovarianceStamped": "twist.twist.linear",
    "geometry_msgs/msg/Vector3Stamped": "vector",
    "nav_msgs/msg/Odometry": "twist.twist.linear",
}
# legacy INS messages without a field mapping: column -> names vendors use, first match wins
INS_ALIASES: dict[str, tuple[str, ...]] = {
    "latitude": ("latitude", "lat"),
    "longitude": ("longitude", "lon"),
    "height": ("altitude", "height", "alt"),
    "roll": ("roll",),
    "pitch": ("pitch",),
    "heading": ("azimuth", "heading", "yaw"),
}
VEL_ALIASES = (("east_velocity", "ve", "velocity_east"), ("north_velocity", "vn", "velocity_north"),
               ("up_velocity", "vu", "velocity_up"))
STATUS_ALIASES = ("rtk_status", "status", "solution_status")


class PoseError(ValueError):
    """A pose source that cannot be turned into a track; ``sensor`` names where."""

    def __init__(self, reason: str, sensor: str | None = None) -> None:
        self.sensor = sensor
        super().__init__(reason)


# --------------------------------------------------------------------------- the track
@dataclass(frozen=True, eq=False)
class Track:
    """Samples of ``T_frame_ego``: ``frame`` is "ecef" (georeferenced) or "map" (local)."""

    frame: str
    t_ns: np.ndarray  # (N,) int64, strictly increasing
    p: np.ndarray  # (N, 3)
    R: np.ndarray  # (N, 3, 3) R_frame_ego
    v: np.ndarray  # (N, 3) velocity of the ego origin in frame axes
    status: np.ndarray  # (N,) int64

    def __len__(self) -> int:
        return len(self.t_ns)


def ins_columns(track: Track) -> dict[str, np.ndarray]:
    """A georeferenced track as raw ``ins`` columns (WGS84, attitude to the local level at
    each sample's position, ENU velocity)."""
    if track.frame != "ecef":
        raise ValueError("only a georeferenced track has WGS84 columns")
    lat, lon, alt = ecef_to_geodetic(track.p)
    r_e = R_ecef_enu(lat, lon)  # ENU -> ECEF
    r_enu_ego = np.einsum("nji,njk->nik", r_e, track.R)
    roll, pitch, az = matrix_to_attitude(r_enu_ego)
    v_enu = np.einsum("nji,nj->ni", r_e, track.v)
    return {"t_ns": track.t_ns, "lat": lat, "lon": lon, "alt": alt, "roll": roll,
            "pitch": pitch, "azimuth": az, "ve": v_enu[:, 0], "vn": v_enu[:, 1],
            "vu": v_enu[:, 2], "rtk_status": track.status}


def map_columns(track: Track) -> dict[str, np.ndarray]:
    """A local-map track as raw ``ego_poses`` columns (absolute time, map coordinates)."""
    q = matrix_to_quat(track.R).reshape(-1, 4)
    return {"t_ns": track.t_ns, "x": track.p[:, 0], "y": track.p[:, 1], "z": track.p[:, 2],
            "qw": q[:, 0], "qx": q[:, 1], "qy": q[:, 2], "qz": q[:, 3], "vx": track.v[:, 0],
            "vy": track.v[:, 1], "vz": track.v[:, 2], "rtk_status": track.status}


# --------------------------------------------------------------------------- numeric core
def angle_scale(unit: AngleUnit) -> float:
    return math.pi / 180.0 if unit is AngleUnit.DEG else 1.0


def euler_to_enu(roll: np.ndarray, pitch: np.ndarray, heading: np.ndarray, conv: Any
                 ) -> np.ndarray:
    """Euler angles as the source gives them (``conv``: a pose block's angle_unit, heading,
    pitch, roll) -> ``R_enu_body`` (body x forward, y left, z up)."""
    k = angle_scale(conv.angle_unit)
    h = np.asarray(heading, float) * k
    az = h if conv.heading is Heading.NORTH_CW else np.pi / 2 - h
    up = np.asarray(pitch, float) * k * (1.0 if conv.pitch is PitchSign.NOSE_UP else -1.0)
    rd = np.asarray(roll, float) * k * (1.0 if conv.roll is RollSign.RIGHT_DOWN else -1.0)
    return attitude_to_matrix(rd, up, az)


def quat_to_enu(q_xyzw: np.ndarray, convention: AttitudeConvention, tolerance: float
                ) -> np.ndarray:
    """Orientation quaternions (x, y, z, w as ROS stores them) -> ``R_enu_body``; a quaternion
    of norm further than ``tolerance`` from one is an error (never silently normalised)."""
    q = np.asarray(q_xyzw, float).reshape(-1, 4)
    r = Rotation.from_quat(unit_quaternions(q, tolerance)).as_matrix()
    return ned_to_enu_attitude(r) if convention is AttitudeConvention.NED else r


def velocity_to_frame(v: np.ndarray, frame: VelocityFrame, r_frame_enu: np.ndarray,
                      r_frame_body: np.ndarray) -> np.ndarray:
    """Velocity vectors in ``frame`` -> the track frame's axes."""
    v = np.asarray(v, float)
    if frame is VelocityFrame.BODY:
        return np.einsum("nij,nj->ni", r_frame_body, v)
    if frame is VelocityFrame.NED:
        v = v @ R_ENU_NED.T
    return np.einsum("nij,nj->ni", r_frame_enu, v)


def differentiate(t_ns: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Velocity by central differences (one-sided at the ends) where the source gives none."""
    if len(t_ns) < 2:
        return np.zeros_like(p)
    t = (t_ns - t_ns[0]) * 1e-9
    return np.gradient(p, t, axis=0)


def apply_lever(p_body: np.ndarray, R_f_body: np.ndarray, T_body_ego: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """``T_frame_ego = T_frame_body T_body_ego`` for every sample."""
    R = R_f_body @ T_body_ego[:3, :3]
    p = p_body + np.einsum("nij,j->ni", R_f_body, T_body_ego[:3, 3])
    return p, R


def datum_to_frame(datum: Datum, xyz_map: np.ndarray, R_map_body: np.ndarray
                   ) -> tuple[str, np.ndarray, np.ndarray, np.ndarray]:
    """Map-frame poses -> (frame, position, R_frame_body, R_frame_enu at each position).

    UTM: map axes are grid east/north/up; the grid is rotated against true ENU by the
    convergence gamma at each point (``R_enu_grid = Rz(-gamma)``). Geodetic: the map is the
    ENU tangent frame at the origin. Local: the map itself is the frame (R_frame_enu = I)."""
    d = np.asarray(xyz_map, float) + np.asarray(datum.offset, float)
    n = len(d)
    if datum.kind is DatumKind.LOCAL:
        return "map", d, R_map_body, np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
    if datum.kind is DatumKind.UTM:
        assert datum.utm_zone is not None
        lat, lon, gamma = utm_to_geodetic(d[:, 0], d[:, 1], datum.utm_zone,
                                          datum.hemisphere == "south")
        p = geodetic_to_ecef(lat, lon, d[:, 2])
        r_ecef_enu = R_ecef_enu(lat, lon)
        r_ecef_map = r_ecef_enu @ rot_z(-gamma)
        return "ecef", p, r_ecef_map @ R_map_body, r_ecef_enu
    assert datum.origin is not None
    o = datum.origin
    r0 = R_ecef_enu(np.array(o.latitude), np.array(o.longitude))
    p0 = geodetic_to_ecef(np.array(o.latitude), np.array(o.longitude), np.array(o.height))
    p = p0 + d @ r0.T
    lat, lon, _ = ecef_to_geodetic(p)
    return "ecef", p, r0 @ R_map_body, R_ecef_enu(lat, lon)


def geodetic_frame(lat_deg: np.ndarray, lon_deg: np.ndarray, h: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """ECEF positions and ``R_ecef_enu`` (local level) at each geodetic point."""
    return geodetic_to_ecef(lat_deg, lon_deg, h), R_ecef_enu(lat_deg, lon_deg)


def sorted_unique(t_ns: np.ndarray, *arrays: np.ndarray) -> tuple[np.ndarray, ...]:
    """Samples in time order, one per stamp (the first of a repeated stamp)."""
    order = np.argsort(t_ns, kind="stable")
    t = t_ns[order]
    keep = np.concatenate([[True], np.diff(t) > 0]) if len(t) else np.zeros(0, bool)
    return (t[keep], *(a[order][keep] for a in arrays))


def resample_indices(t_src: np.ndarray, t_q: np.ndarray, max_gap_ns: int
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each query: bracketing source indices (k, k+1), alpha, and whether it is covered
    (inside the source span, bracket no longer than ``max_gap_ns``)."""
    k = np.searchsorted(t_src, t_q, side="right") - 1
    k = np.clip(k, 0, max(len(t_src) - 2, 0))
    inside = (t_q >= t_src[0]) & (t_q <= t_src[-1]) if len(t_src) >= 2 else np.zeros(
        len(t_q), bool)
    dt = (t_src[k + 1] - t_src[k]) if len(t_src) >= 2 else np.ones(len(t_q), np.int64)
    ok = inside & (dt <= max_gap_ns)
    alpha = np.where(dt > 0, (t_q - t_src[k]) / np.maximum(dt, 1), 0.0)
    return k, np.clip(alpha, 0.0, 1.0), ok


def lerp(values: np.ndarray, k: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    a = alpha.reshape(-1, *([1] * (values.ndim - 1)))
    return (1.0 - a) * values[k] + a * values[k + 1]


def slerp_matrices(t_src: np.ndarray, R: np.ndarray, t_q: np.ndarray) -> np.ndarray:
    """Rotation matrices at ``t_q`` (inside the source span) by the project's one SLERP
    (``tasks.interpolate.interpolate_poses``)."""
    if len(t_q) == 0:
        return np.zeros((0, 3, 3))
    _, q = interpolate_poses(t_src, np.zeros((len(t_src), 3)), matrix_to_quat(R),
                             np.asarray(t_q, np.int64))
    return quat_to_matrix(q)


# --------------------------------------------------------------------------- field access
def get_path(msg: Any, path: str) -> Any:
    obj = msg
    for part in path.split("."):
        obj = getattr(obj, part)
    return obj


def has_path(msg: Any, path: str) -> bool:
    try:
        get_path(msg, path)
    except AttributeError:
        return False
    return True


def _vec(msg: Any, path: str) -> tuple[float, float, float]:
    v = get_path(msg, path)
    return float(v.x), float(v.y), float(v.z)


def _status_value(v: Any) -> int:
    return int(getattr(v, "status", v))


# --------------------------------------------------------------------------- collection
@dataclass
class Samples:
    """Values one pose sensor delivered, in message order."""

    t: list[int] = field(default_factory=list)
    cols: dict[str, list[Any]] = field(default_factory=dict)
    frame_ids: set[str] = field(default_factory=set)
    child_frame_ids: set[str] = field(default_factory=set)

    def put(self, t: int, **values: Any) -> None:
        self.t.append(t)
        for k, v in values.items():
            self.cols.setdefault(k, []).append(v)

    def array(self, name: str) -> np.ndarray:
        return np.asarray(self.cols.get(name, []), dtype=np.float64)

    @property
    def t_ns(self) -> np.ndarray:
        return np.asarray(self.t, dtype=np.int64)


Extractor = Callable[[Any, Samples], None]


class PoseCollector:
    """Gathers one agent's pose messages during ingest's pass, then builds its track."""

    def __init__(self, agent: AgentConfig, quat_tolerance: float) -> None:
        self.agent = agent
        self.quat_tolerance = quat_tolerance  # ingest.quat_tolerance
        self.pose = agent.effective_pose
        self.samples: dict[str, Samples] = {}
        self._extract: dict[str, Extractor] = {}
        self.tf_edges: dict[tuple[str, str], Samples] = {}

    @property
    def sensors(self) -> list[str]:
        return self.agent.pose_sensor_names()

    # -- plan: one extractor per pose sensor, chosen from the pose block and its msg_type
    def plan(self) -> None:
        p = self.pose
        for name in self.sensors:
            s = self.agent.sensor(name)
            self.samples[name] = Samples()
            self._extract[name] = self._extractor(p, name, s.msg_type)

    def _extractor(self, p: Any, name: str, msg_type: str) -> Extractor:
        if isinstance(p, InsPose):
            return self._ins_extractor(p)
        if isinstance(p, OdometryPose):
            if msg_type not in ODOMETRY_TYPES:
                raise PoseError(f"pose source 'odometry' reads {list(ODOMETRY_TYPES)}, the "
                                f"sensor carries {msg_type}", name)
            return _odometry_extractor(msg_type)
        if isinstance(p, TfPose):
            if msg_type != TF_TYPE:
                raise PoseError(f"pose source 'tf' reads {TF_TYPE}, the sensor carries "
                                f"{msg_type}", name)
            return self._tf_extractor
        assert isinstance(p, SplitPose)
        ex: list[Extractor] = []
        if name == p.position:
            ex.append(_geo_extractor(p.position_fields, msg_type, name))
        if name == p.attitude:
            ex.append(_attitude_extractor(p.attitude_fields, msg_type, name))
        if name == p.velocity:
            ex.append(_velocity_extractor(p.velocity_fields, msg_type, name))

        def both(msg: Any, out: Samples) -> None:
            t = header_stamp_ns(msg)
            out.t.append(t)
            for e in ex:
                e(msg, out)
        return both

    def _ins_extractor(self, p: InsPose) -> Extractor:
        fields: list[InsFields | None] = [p.fields]

        def ex(msg: Any, out: Samples) -> None:
            if fields[0] is None:
                fields[0] = _ins_fields_by_name(msg)
            f = fields[0]
            assert f is not None
            vals = {k: float(get_path(msg, getattr(f, k))) for k in
                    ("latitude", "longitude", "height", "roll", "pitch", "heading")}
            if f.undulation:  # height above mean sea level + undulation = ellipsoidal
                vals["height"] += float(get_path(msg, f.undulation))
            if f.velocity is not None:
                v = f.velocity
                vals.update(v0=float(get_path(msg, v.x)), v1=float(get_path(msg, v.y)),
                            v2=float(get_path(msg, v.z)))
            vals["status"] = (_status_value(get_path(msg, f.status)) if f.status
                              else STATUS_UNKNOWN)
            out.put(header_stamp_ns(msg), **vals)
        return ex

    def _tf_extractor(self, msg: Any, out: Samples) -> None:
        for ts in msg.transforms:
            key = (str(ts.header.frame_id).lstrip("/"), str(ts.child_frame_id).lstrip("/"))
            tr, q = ts.transform.translation, ts.transform.rotation
            self.tf_edges.setdefault(key, Samples()).put(
                header_stamp_ns(ts), x=tr.x, y=tr.y, z=tr.z, qx=q.x, qy=q.y, qz=q.z, qw=q.w)
        out.t.append(0)  # counted as one message; times are per edge

    def add(self, name: str, msg: Any) -> None:
        """Keep one pose message, and the frame names it carries. An empty frame name is no
        frame: drivers leave ``child_frame_id`` / ``header.frame_id`` empty when they have
        none to give (docs/recordings.md: ``body_frame`` defaults to Odometry's
        child_frame_id, else the ego frame), so it must not count as a frame called ''
        that no transform connects to the ego frame."""
        out = self.samples[name]
        if hasattr(msg, "header") and (frame := str(msg.header.frame_id).lstrip("/")):
            out.frame_ids.add(frame)
        if hasattr(msg, "child_frame_id") and (child := str(msg.child_frame_id).lstrip("/")):
            out.child_frame_ids.add(child)
        self._extract[name](msg, out)

    # -- build
    def build(self, lookup: Callable[[str, str], np.ndarray | None], t_span: tuple[int, int]
              ) -> Track | None:
        """The agent's track; ``lookup(a, b)`` gives static ``T_a_b`` (tf_static or a
        sensor's extrinsic), ``t_span`` the agent's recording span (for a fixed pose)."""
        p = self.pose
        if isinstance(p, NoPose):
            return None
        if isinstance(p, FixedPose):
            return build_fixed(p, t_span)
        ego = self.agent.ego_frame.lstrip("/")

        def body_to_ego(body: str | None, sensor: str | None) -> np.ndarray:
            if body is None or body == ego:
                return np.eye(4)
            T = lookup(body, ego)
            if T is None:
                raise PoseError(f"pose is of frame {body!r} but no static transform connects "
                                f"it to ego frame {ego!r} (tf_static or an extrinsic of the "
                                "pose sensor)", sensor)
            return T

        if isinstance(p, InsPose):
            s = self.samples[p.sensor]
            return build_ins(p, s, body_to_ego(p.body_frame, p.sensor))
        if isinstance(p, OdometryPose):
            s = self.samples[p.sensor]
            _check_frame(s, p.map_frame, p.sensor)
            body = p.body_frame or (_one(s.child_frame_ids, "child_frame_id", p.sensor)
                                    if s.child_frame_ids else ego)
            return build_odometry(p, s, body_to_ego(body, p.sensor), self.quat_tolerance)
        if isinstance(p, TfPose):
            child = (p.child_frame or ego).lstrip("/")
            return build_tf(p, self.tf_edges, child, lookup,
                            body_to_ego(p.body_frame or child, p.sensor), self.quat_tolerance)
        assert isinstance(p, SplitPose)
        pos, att = self.samples[p.position], self.samples[p.attitude]
        vel = self.samples[p.velocity] if p.velocity else None
        ant = p.position_frame or (_one(pos.frame_ids, "frame_id", p.position)
                                   if pos.frame_ids else ego)
        imu = p.body_frame or (_one(att.frame_ids, "frame_id", p.attitude)
                               if att.frame_ids else ego)
        return build_split(p, pos, att, vel, body_to_ego(ant, p.position),
                           body_to_ego(imu, p.attitude), self.quat_tolerance)


def _one(values: set[str], what: str, sensor: str) -> str:
    if len(values) != 1:
        raise PoseError(f"the pose messages carry several {what}s {sorted(values)}; name the "
                        "one meant in the pose block", sensor)
    return next(iter(values))


def _check_frame(s: Samples, expected: str | None, sensor: str) -> None:
    if expected is not None and s.frame_ids and s.frame_ids != {expected.lstrip("/")}:
        raise PoseError(f"pose messages are in frame(s) {sorted(s.frame_ids)}, clip.yaml says "
                        f"map_frame {expected!r}", sensor)
    if len(s.frame_ids) > 1:
        raise PoseError(f"pose messages switch between frames {sorted(s.frame_ids)}", sensor)


def _ins_fields_by_name(msg: Any) -> InsFields:
    found: dict[str, Any] = {}
    for col, names in INS_ALIASES.items():
        hit = next((n for n in names if hasattr(msg, n)), None)
        if hit is None:
            raise PoseError(f"INS message {type(msg).__name__} has none of the fields "
                            f"{list(names)} (needed for {col!r}); map the fields in the "
                            "agent's pose block (pose: {kind: ins, fields: ...})")
        found[col] = hit
    vel = [next((n for n in names if hasattr(msg, n)), None) for names in VEL_ALIASES]
    if all(vel):
        found["velocity"] = Vec3Paths(x=str(vel[0]), y=str(vel[1]), z=str(vel[2]))
    found["status"] = next((n for n in STATUS_ALIASES if hasattr(msg, n)), None)
    return InsFields(**found)


def _odometry_extractor(msg_type: str) -> Extractor:
    pose_path = "pose" if msg_type.endswith("PoseStamped") else "pose.pose"
    twist = msg_type == "nav_msgs/msg/Odometry"

    def ex(msg: Any, out: Samples) -> None:
        pose = get_path(msg, pose_path)
        pp, q = pose.position, pose.orientation
        vals = dict(x=pp.x, y=pp.y, z=pp.z, qx=q.x, qy=q.y, qz=q.z, qw=q.w)
        if twist:
            lin, ang = msg.twist.twist.linear, msg.twist.twist.angular
            vals.update(v0=lin.x, v1=lin.y, v2=lin.z, w0=ang.x, w1=ang.y, w2=ang.z)
        out.put(header_stamp_ns(msg), **vals)
    return ex


def _geo_extractor(fields: Any, msg_type: str, name: str) -> Extractor:
    if fields is None and msg_type != NAVSATFIX:
        raise PoseError(f"position sensor carries {msg_type}: give position_fields "
                        "(latitude, longitude, height paths) or use a NavSatFix", name)

    def ex(msg: Any, out: Samples) -> None:
        if fields is None:
            vals = dict(latitude=msg.latitude, longitude=msg.longitude, height=msg.altitude,
                        status=int(msg.status.status))
        else:
            vals = {k: float(get_path(msg, getattr(fields, k)))
                    for k in ("latitude", "longitude", "height")}
            if fields.undulation:
                vals["height"] += float(get_path(msg, fields.undulation))
            vals["status"] = STATUS_UNKNOWN
        for k, v in vals.items():
            out.cols.setdefault(k, []).append(v)
    return ex


def _attitude_extractor(fields: Any, msg_type: str, name: str) -> Extractor:
    if fields is None and msg_type != IMU and not msg_type.endswith("QuaternionStamped"):
        raise PoseError(f"attitude sensor carries {msg_type}: give attitude_fields (roll, "
                        "pitch, heading paths) or use sensor_msgs/Imu orientation", name)
    qpath = "orientation" if fields is None and msg_type == IMU else "quaternion"

    def ex(msg: Any, out: Samples) -> None:
        if fields is None:
            q = get_path(msg, qpath)
            vals = dict(qx=q.x, qy=q.y, qz=q.z, qw=q.w)
        else:
            vals = {k: float(get_path(msg, getattr(fields, k)))
                    for k in ("roll", "pitch", "heading")}
        for k, v in vals.items():
            out.cols.setdefault(k, []).append(v)
    return ex


def _velocity_extractor(fields: Vec3Paths | None, msg_type: str, name: str) -> Extractor:
    path = VELOCITY_PATHS.get(msg_type)
    if fields is None and path is None:
        raise PoseError(f"velocity sensor carries {msg_type}: give velocity_fields (x, y, z "
                        f"paths) or use one of {sorted(VELOCITY_PATHS)}", name)

    def ex(msg: Any, out: Samples) -> None:
        if fields is None:
            assert path is not None
            v = _vec(msg, path)
        else:
            v = (float(get_path(msg, fields.x)), float(get_path(msg, fields.y)),
                 float(get_path(msg, fields.z)))
        for k, c in zip(("v0", "v1", "v2"), v, strict=True):
            out.cols.setdefault(k, []).append(c)
    return ex


# --------------------------------------------------------------------------- builders
def _finite_rows(name: str, t: np.ndarray, *arrays: np.ndarray
                 ) -> tuple[np.ndarray, list[np.ndarray]]:
    """Drop samples with a non-finite value (an invalid solution); at least two must stay."""
    ok = np.ones(len(t), bool)
    for a in arrays:
        ok &= np.all(np.isfinite(a.reshape(len(t), -1)), axis=1)
    if np.count_nonzero(ok) < 2:
        raise PoseError(f"fewer than 2 pose samples with finite values ({np.count_nonzero(ok)} "
                        f"of {len(t)})", name)
    return t[ok], [a[ok] for a in arrays]


def build_ins(p: InsPose, s: Samples, T_body_ego: np.ndarray) -> Track:
    """Vendor INS: geodetic position, Euler attitude (``p.attitude`` convention), velocity."""
    kl = 180.0 / math.pi if p.latlon_unit is AngleUnit.RAD else 1.0
    lat, lon, h = (s.array(c) for c in ("latitude", "longitude", "height"))
    att = np.stack([s.array(c) for c in ("roll", "pitch", "heading")], 1)
    has_v = "v0" in s.cols
    v = np.stack([s.array(c) for c in ("v0", "v1", "v2")], 1) if has_v else np.zeros((len(
        s.t), 3))
    status = np.asarray(s.cols.get("status", []), np.int64)
    t, (lat, lon, h, att, v, status) = _finite_rows(p.sensor, *sorted_unique(
        s.t_ns, lat * kl, lon * kl, h, att, v, status))
    pe, r_e = geodetic_frame(lat, lon, h)
    R_body = r_e @ euler_to_enu(att[:, 0], att[:, 1], att[:, 2], p)
    pos, R = apply_lever(pe, R_body, T_body_ego)
    vel = (velocity_to_frame(v, p.velocity_frame, r_e, R_body) if has_v
           else differentiate(t, pos))
    return Track("ecef", t, pos, R, vel, status)


def build_odometry(p: OdometryPose, s: Samples, T_body_ego: np.ndarray, quat_tolerance: float
                   ) -> Track:
    xyz = np.stack([s.array(c) for c in ("x", "y", "z")], 1)
    q = np.stack([s.array(c) for c in ("qx", "qy", "qz", "qw")], 1)
    has_v = "v0" in s.cols
    v = np.stack([s.array(c) for c in ("v0", "v1", "v2")], 1) if has_v else np.zeros_like(xyz)
    w = np.stack([s.array(c) for c in ("w0", "w1", "w2")], 1) if has_v else np.zeros_like(xyz)
    t, (xyz, q, v, w) = _finite_rows(p.sensor, *sorted_unique(s.t_ns, xyz, q, v, w))
    R_map_body = Rotation.from_quat(unit_quaternions(q, quat_tolerance, p.sensor)).as_matrix()
    frame, pos_b, R_body, _r_enu = datum_to_frame(p.datum, xyz, R_map_body)
    pos, R = apply_lever(pos_b, R_body, T_body_ego)
    if has_v:  # body twist of the child frame; the ego origin adds w x r
        v_ego_body = v + np.cross(w, T_body_ego[:3, 3])
        vel = np.einsum("nij,nj->ni", R_body, v_ego_body)
    else:
        vel = differentiate(t, pos)
    return Track(frame, t, pos, R, vel, np.full(len(t), STATUS_UNKNOWN, np.int64))


def unit_quaternions(q_xyzw: np.ndarray, tolerance: float, sensor: str | None = None
                     ) -> np.ndarray:
    """(N, 4) quaternions divided by their norms; one whose norm is further than
    ``tolerance`` (``ingest.quat_tolerance``) from one is an error, never normalised."""
    n = np.linalg.norm(q_xyzw, axis=1)
    if n.size and np.max(np.abs(n - 1.0)) > tolerance:
        i = int(np.argmax(np.abs(n - 1.0)))
        raise PoseError(f"orientation quaternion {q_xyzw[i].tolist()} (x, y, z, w) has norm "
                        f"{n[i]:.6f}, not 1 (tolerance {tolerance:g}: ingest.quat_tolerance)",
                        sensor)
    return q_xyzw / n[:, None]


def build_split(p: SplitPose, pos: Samples, att: Samples, vel: Samples | None,
                T_ant_ego: np.ndarray, T_att_ego: np.ndarray, quat_tolerance: float) -> Track:
    """Position and attitude from different topics, resampled onto one set of stamps."""
    kl = 180.0 / math.pi if p.latlon_unit is AngleUnit.RAD else 1.0
    gap = int(p.max_gap_ms * 1e6)
    geo = np.stack([pos.array("latitude") * kl, pos.array("longitude") * kl,
                    pos.array("height")], 1)
    status = np.asarray(pos.cols.get("status", []), np.int64)
    tp, (geo, status) = _finite_rows(p.position, *sorted_unique(pos.t_ns, geo, status))
    if p.attitude_fields is None:
        q = np.stack([att.array(c) for c in ("qx", "qy", "qz", "qw")], 1)
        ta, (q,) = _finite_rows(p.attitude, *sorted_unique(att.t_ns, q))
        try:
            r_enu_att = quat_to_enu(q, p.quaternion_frame, quat_tolerance)
        except PoseError as e:
            raise PoseError(str(e), p.attitude) from e
    else:
        eul = np.stack([att.array(c) for c in ("roll", "pitch", "heading")], 1)
        ta, (eul,) = _finite_rows(p.attitude, *sorted_unique(att.t_ns, eul))
        r_enu_att = euler_to_enu(eul[:, 0], eul[:, 1], eul[:, 2], p)
    t_q = ta if p.sample_at == "attitude" else tp
    ki, al, ok_p = resample_indices(tp, t_q, gap)
    _, _, ok_a = resample_indices(ta, t_q, gap)
    ok = ok_p & ok_a
    if np.count_nonzero(ok) < 2:
        raise PoseError(f"position ({len(tp)} samples, {_span(tp)}) and attitude "
                        f"({len(ta)} samples, {_span(ta)}) do not overlap in time (gaps of at "
                        f"most {p.max_gap_ms:g} ms)", p.position)
    t_q, ki, al = t_q[ok], ki[ok], al[ok]
    pe_ant = lerp(geodetic_to_ecef(geo[:, 0], geo[:, 1], geo[:, 2]), ki, al)
    lat, lon, _ = ecef_to_geodetic(pe_ant)
    r_e = R_ecef_enu(lat, lon)
    R_att = r_e @ slerp_matrices(ta, r_enu_att, t_q)
    R = R_att @ T_att_ego[:3, :3]
    # lever arm of the antenna: p_ant = p_ego + R_ecef_ego t_ego_ant
    T_ego_ant = np.linalg.inv(T_ant_ego)
    pe = pe_ant - np.einsum("nij,j->ni", R, T_ego_ant[:3, 3])
    st = status[np.where(al < 0.5, ki, ki + 1)]
    if vel is not None:
        v = np.stack([vel.array(c) for c in ("v0", "v1", "v2")], 1)
        tv, (v,) = _finite_rows(p.velocity or "", *sorted_unique(vel.t_ns, v))
        kv, av, ok_v = resample_indices(tv, t_q, gap)
        if not ok_v.all():
            raise PoseError(f"velocity does not cover the pose samples ({_span(tv)} vs "
                            f"{_span(t_q)})", p.velocity)
        vel_q = lerp(v, kv, av)
        vv = velocity_to_frame(vel_q, p.velocity_frame, r_e, R_att)
    else:
        vv = differentiate(t_q, pe)
    return Track("ecef", t_q, pe, R, vv, st)


def _span(t: np.ndarray) -> str:
    return f"[{int(t[0])}, {int(t[-1])}] ns" if len(t) else "no samples"


def build_tf(p: TfPose, edges: dict[tuple[str, str], Samples], child: str,
             lookup: Callable[[str, str], np.ndarray | None], T_body_ego: np.ndarray,
             quat_tolerance: float) -> Track:
    """``parent -> child`` through the dynamic edges of ``/tf`` (each interpolated) and
    static ones (``lookup``), sampled at the stamps of the densest dynamic edge."""
    parent = p.parent_frame.lstrip("/")
    chain = _tf_chain(edges, parent, child, lookup)
    if chain is None:
        have = sorted(f"{a}->{b}" for a, b in edges)
        raise PoseError(f"/tf has no chain of transforms from {parent!r} to {child!r} "
                        f"(dynamic edges: {have})", p.sensor)
    dyn = [e for e in chain if isinstance(e, tuple)]
    if not dyn:
        raise PoseError(f"the chain {parent!r} -> {child!r} has no dynamic transform", p.sensor)
    tracks: dict[tuple[str, str], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    for key in dyn:
        s = edges[key]
        xyz = np.stack([s.array(c) for c in ("x", "y", "z")], 1)
        q = np.stack([s.array(c) for c in ("qx", "qy", "qz", "qw")], 1)
        t, (xyz, q) = _finite_rows(p.sensor, *sorted_unique(s.t_ns, xyz, q))
        tracks[key] = (t, xyz, Rotation.from_quat(
            unit_quaternions(q, quat_tolerance, p.sensor)).as_matrix())
    t_q = max(tracks.values(), key=lambda v: len(v[0]))[0]
    lo = max(v[0][0] for v in tracks.values())
    hi = min(v[0][-1] for v in tracks.values())
    t_q = t_q[(t_q >= lo) & (t_q <= hi)]
    T = np.broadcast_to(np.eye(4), (len(t_q), 4, 4)).copy()
    for e in chain:
        if isinstance(e, tuple):
            t, xyz, R = tracks[e]
            k, a, _ = resample_indices(t, t_q, np.iinfo(np.int64).max)
            M = np.broadcast_to(np.eye(4), (len(t_q), 4, 4)).copy()
            M[:, :3, :3] = slerp_matrices(t, R, t_q)
            M[:, :3, 3] = lerp(xyz, k, a)
        else:
            M = e
        T = T @ M
    frame, pos_b, R_body, _ = datum_to_frame(p.datum, T[:, :3, 3], T[:, :3, :3])
    pos, R = apply_lever(pos_b, R_body, T_body_ego)
    return Track(frame, t_q, pos, R, differentiate(t_q, pos),
                 np.full(len(t_q), STATUS_UNKNOWN, np.int64))


def _tf_chain(edges: dict[tuple[str, str], Samples], parent: str, child: str,
              lookup: Callable[[str, str], np.ndarray | None]
              ) -> list[tuple[str, str] | np.ndarray] | None:
    """Path parent -> child along dynamic edges (forward only, as tf trees are) with static
    transforms (``lookup``) allowed to bridge from any frame reached to the child."""
    from collections import deque

    todo: deque[tuple[str, list[tuple[str, str] | np.ndarray]]] = deque([(parent, [])])
    seen = {parent}
    while todo:
        frame, path = todo.popleft()
        if frame == child:
            return path
        static = lookup(frame, child) if path else None
        if static is not None:
            return [*path, static]
        for a, b in edges:
            if a == frame and b not in seen:
                seen.add(b)
                todo.append((b, [*path, (a, b)]))
    return None


def build_fixed(p: FixedPose, t_span: tuple[int, int]) -> Track:
    """A constant pose sampled at ``rate_hz`` over the agent's recording, both ends included
    (interpolation between equal samples is exact everywhere in between)."""
    t0, t1 = t_span
    step = max(int(1e9 / p.rate_hz), 1)
    t = np.append(np.arange(t0, t1, step, dtype=np.int64), np.int64(max(t1, t0 + 1)))
    n = len(t)
    if p.local is not None:
        M = p.local.matrix()
        pos, R = np.repeat(M[None, :3, 3], n, 0), np.repeat(M[None, :3, :3], n, 0)
        return Track("map", t, pos, R, np.zeros((n, 3)), np.full(n, STATUS_UNKNOWN, np.int64))
    g = p.geodetic
    assert g is not None
    a = p.attitude
    pe, r_e = geodetic_frame(np.array([g.latitude]), np.array([g.longitude]),
                             np.array([g.height]))
    R = r_e @ euler_to_enu(np.array([a.roll]), np.array([a.pitch]), np.array([a.heading]), p)
    return Track("ecef", t, np.repeat(pe, n, 0), np.repeat(R, n, 0), np.zeros((n, 3)),
                 np.full(n, STATUS_UNKNOWN, np.int64))
