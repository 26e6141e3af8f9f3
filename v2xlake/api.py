"""The Python API over a processed lake: ``v2xlake.open(path)``.

Lazy and read-only. Opening a lake reads nothing; lake-wide questions (which clips, which
frames) are one SQL query each on DuckDB views over just the tables they read, and
``Lake.sql`` runs user SELECTs on the full catalog (both in memory and locked down so that
they can only read the lake's files);
a clip's small tables are read when the clip is first touched (one clip, not the lake), and
points, images and boxes when a frame asks for them (points: only the Parquet row groups that
hold that frame). Only the clean zone is read: anonymized images, relative time, local ENU.

Vocabulary, as in the rest of v2xlake: ``T_a_b`` maps points from frame b into frame a;
times are int64 nanoseconds on the clip's relative axis; quaternions are (w, x, y, z).

    import v2xlake
    lake = v2xlake.open("demo-lake/lake")
    clip = lake.clip(lake.clips[0])
    s = clip.sample(10)                         # every agent at the reference frame 10
    pts = s.points(frame="red")                 # {agent: Points}, all in red's LiDAR frame
    boxes = s["black"].boxes(frame="world")     # black's boxes, global instance ids
    img = s["red"].images()[0]; rgb = img.read(); img.K, img.T_world_cam
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from os import PathLike
from typing import Any

import numpy as np
import pyarrow as pa

from v2xlake.collate import collate_fn as _collate_fn
from v2xlake.storage.catalog import Catalog
from v2xlake.storage.lake import Lake as _LakeIO
from v2xlake.storage.lake import checked_clip_id
from v2xlake.storage.reader import DESKEWED, read_point_frame
from v2xlake.tasks.geometry import apply, invert, quat_wxyz_of
from v2xlake.tasks.reader import (
    INS,
    REFERENCE,
    AgentData,
    ClipData,
    RelativeTransform,
    TransformSource,
    boxes_matrices,
    compare_calibration,
    load_clip,
    match_agents,
    nearest_index,
    relative_transform,
)

__all__ = ["AgentFrame", "Boxes", "CameraImage", "Clip", "CoopDataset", "CoopSample", "Lake",
           "Points", "open"]

WORLD = "world"


# ---------------------------------------------------------------------------------- values
@dataclass(frozen=True, eq=False)
class Points:
    """One agent's deskewed LiDAR points of one frame, expressed in ``frame``."""

    xyz: np.ndarray  # float32 (N, 3)
    intensity: np.ndarray  # float32 (N,)
    ring: np.ndarray  # uint16 (N,)
    t_ns: np.ndarray  # int64 (N,) each point's own time (before deskew)
    frame: str

    def __len__(self) -> int:
        return len(self.xyz)

    def numpy(self) -> np.ndarray:
        """(N, 4) float32 x, y, z, intensity: the array most detectors take."""
        return np.concatenate([self.xyz, self.intensity[:, None]], 1).astype(np.float32)

    def to_arrow(self) -> pa.Table:
        return pa.table({"x": self.xyz[:, 0], "y": self.xyz[:, 1], "z": self.xyz[:, 2],
                         "intensity": self.intensity, "ring": self.ring, "t_ns": self.t_ns})


@dataclass(frozen=True, eq=False)
class Boxes:
    """Annotated 3D boxes of one agent's frame, expressed in ``frame``.

    ``instance_id`` is the clip's global instance id: the same object seen by two agents has
    the same id in both agents' boxes. ``size`` is (w, l, h) like nuScenes; ``links`` the
    instances it is attached to (e.g. car <-> trailer).
    """

    instance_id: list[str]
    category: list[str]
    center: np.ndarray  # (N, 3)
    size: np.ndarray  # (N, 3) w, l, h
    quat_wxyz: np.ndarray  # (N, 4)
    velocity: np.ndarray  # (N, 3) in ``frame`` (NaN where unknown)
    num_lidar_pts: np.ndarray  # (N,) int64, annotate's count in the agent's own scan
    links: list[list[str]]
    frame: str

    def __len__(self) -> int:
        return len(self.instance_id)

    def matrices(self) -> np.ndarray:
        """(N, 4, 4) ``T_frame_box``."""
        from v2xlake.tasks.geometry import transform

        return transform(self.center, self.quat_wxyz)

    def corners(self) -> np.ndarray:
        """(N, 8, 3) box corners in ``frame``."""
        from v2xlake.tasks.geometry import box_corners

        return box_corners(self.center, self.size, self.quat_wxyz)

    def to_arrow(self) -> pa.Table:
        c, s, q, v = self.center, self.size, self.quat_wxyz, self.velocity
        return pa.table({
            "instance_id": self.instance_id, "category": self.category,
            "cx": c[:, 0], "cy": c[:, 1], "cz": c[:, 2], "w": s[:, 0], "l": s[:, 1],
            "h": s[:, 2], "qw": q[:, 0], "qx": q[:, 1], "qy": q[:, 2], "qz": q[:, 3],
            "vx": v[:, 0], "vy": v[:, 1], "vz": v[:, 2], "num_lidar_pts": self.num_lidar_pts,
            "links": pa.array(self.links, pa.list_(pa.string()))})


@dataclass(frozen=True, eq=False)
class CameraImage:
    """One (anonymized) camera image with its calibration at its own timestamp."""

    agent_id: str
    sensor: str
    frame_idx: int
    stamp_ns: int
    width: int
    height: int
    K: np.ndarray  # 3x3 intrinsics (of the distorted image as recorded)
    distortion_model: str
    distortion: tuple[float, ...]
    T_ego_cam: np.ndarray  # 4x4
    T_world_cam: np.ndarray  # 4x4, the ego pose interpolated at ``stamp_ns``
    _read: Callable[[], bytes] = field(repr=False)

    def png(self) -> bytes:
        return self._read()

    def read(self) -> np.ndarray:
        """(H, W, 3) uint8 RGB."""
        import cv2

        img = cv2.imdecode(np.frombuffer(self._read(), np.uint8), cv2.IMREAD_COLOR)
        if img is None:
            raise ValueError(f"cannot decode image {self.agent_id}/{self.sensor}/"
                             f"{self.frame_idx}")
        return np.ascontiguousarray(img[:, :, ::-1])


# ---------------------------------------------------------------------------------- frames
STANDALONE = "not part of a cooperative sample: the agent's own INS pose"


class AgentFrame:
    """One agent's LiDAR frame: its pose, points, boxes and the images around it.

    ``T_source`` says where ``T_world_lidar`` -- and so every transform to another agent's
    frame -- comes from: ``"registered"`` (the register stage's accepted refined
    ``T_Lref_Lagent``, eq. 1b, composed with the reference agent's pose), ``"ins"`` (the
    agent's own INS pose, eq. 1a: decimetres off between agents) or ``"reference"`` (the
    clip's reference agent, whose INS pose defines the sample's frame). ``T_source_reason``
    says why an ``"ins"`` frame is not registered: the register stage's reason for a
    rejected frame (``"rejected: uncertain: ..."``), no row for the frame, a clip that never
    ran register, or ``use_registration=False``; empty otherwise.
    """

    def __init__(self, clip: Clip, agent_id: str, index: int, *, sensor: str = "LIDAR_TOP",
                 T_world_lidar: np.ndarray | None = None,
                 relative: RelativeTransform | None = None) -> None:
        agent = clip.data.agents[agent_id]
        self.clip = clip
        self.agent_id = agent_id
        self.sensor = agent.lidar_sensor(sensor)
        lf = agent.lidar[self.sensor]
        self.frame_idx = int(lf.frame_idx[index])
        self.t_ns = int(lf.points_t_ns[index])  # the time the deskewed points are at
        self.deskewed = bool(lf.deskewed[index])
        self.T_world_ego = agent.T_world_ego(self.t_ns, clip_id=clip.clip_id)[0]
        # from the agent's own poses, or (cooperative sample) the registered transform
        self.T_world_lidar = T_world_lidar if T_world_lidar is not None else \
            self.T_world_ego @ agent.sensors[self.sensor].T_ego_sensor
        self.sample: CoopSample | None = None  # set when the frame is part of one
        if relative is None:
            relative = RelativeTransform(REFERENCE) if agent_id == clip.reference_agent \
                else RelativeTransform(INS, STANDALONE)
        self.T_source: TransformSource = relative.source
        self.T_source_reason: str = relative.reason

    def __repr__(self) -> str:
        return (f"AgentFrame(clip={self.clip.clip_id!r}, agent={self.agent_id!r}, "
                f"frame={self.frame_idx}, t_ns={self.t_ns}, T_source={self.T_source!r})")

    @property
    def agent(self) -> AgentData:
        return self.clip.data.agents[self.agent_id]

    def T_to(self, frame: str) -> np.ndarray:
        """``T_frame_lidar``: this LiDAR frame into ``frame`` ('lidar', 'ego', 'world', or an
        agent id: that agent's LiDAR frame at the same sample when part of one, else its
        LiDAR at this frame's time)."""
        return self.clip._frame_T(frame, self) @ self.T_world_lidar

    def points(self, frame: str = "lidar", *, table: str = DESKEWED) -> Points:
        """Deskewed points (``table``: e.g. ``lidar_points`` for the raw scan, which is only
        meaningful in the 'lidar' frame). Empty when the frame has none."""
        fr = read_point_frame(self.clip.lake.io, self.clip.clip_id, self.agent_id,
                              self.frame_idx, table=table, sensor=self.sensor)
        if fr is None:
            return Points(np.zeros((0, 3), np.float32), np.zeros(0, np.float32),
                          np.zeros(0, np.uint16), np.zeros(0, np.int64), frame)
        xyz = fr.xyz if frame == "lidar" else \
            apply(self.T_to(frame), fr.xyz.astype(np.float64)).astype(np.float32)
        return Points(xyz, fr.intensity, fr.ring, fr.t_ns, frame)

    def boxes(self, frame: str = "lidar") -> Boxes:
        """This agent's annotated boxes of this frame (annotated in its LiDAR frame)."""
        ann = self.agent.annotations
        if ann.num_rows:
            ann = ann.filter(pa.compute.and_(
                pa.compute.equal(ann["frame_idx"], self.frame_idx),
                pa.compute.equal(ann["sensor"], self.sensor)))
        n = ann.num_rows
        if n == 0:
            z3 = np.zeros((0, 3))
            return Boxes([], [], z3, z3, np.zeros((0, 4)), z3, np.zeros(0, np.int64), [],
                         frame)
        B = boxes_matrices(ann)
        vel = np.stack([np.asarray(ann[c].to_numpy(zero_copy_only=False), np.float64)
                        for c in ("vx", "vy", "vz")], 1)
        T = np.eye(4) if frame == "lidar" else self.T_to(frame)
        B = T @ B
        vel = vel @ T[:3, :3].T
        npts = np.array([-1 if v is None else v for v in ann["num_lidar_pts"].to_pylist()],
                        np.int64)
        return Boxes(ann["instance_id"].to_pylist(), ann["category"].to_pylist(),
                     B[:, :3, 3].copy(), np.stack([ann[c].to_numpy() for c in "wlh"], 1),
                     quat_wxyz_of(B), vel, npts, [list(x or []) for x in
                                                  ann["links"].to_pylist()], frame)

    def images(self, cameras: Sequence[str] | None = None) -> list[CameraImage]:
        """Each camera's image nearest this frame's time, with K and extrinsics at its own
        stamp (a 30 Hz camera is up to ~17 ms off the LiDAR time; see ``alignments`` for
        the stage's target-based association)."""
        agent = self.agent
        calib = agent.cameras_calib()
        out: list[CameraImage] = []
        for ch, frames in sorted(agent.cameras.items()):
            if (cameras is not None and ch not in cameras) or ch not in calib or not len(frames):
                continue
            k = int(nearest_index(frames.stamp_ns, self.t_ns)[0])
            out.append(self.clip._image(agent, ch, k))
        return out


class CoopSample:
    """Every agent at one time of the reference agent's clock, with relative transforms.

    ``T(a, b)`` maps agent b's LiDAR frame into agent a's. For a cooperative agent with an
    accepted registration (the register stage, eq. 1b) that transform is the refined one;
    otherwise it comes from the two agents' INS poses (eq. 1a), which is typically tens of
    centimetres off. The register stage leaves frames unaccepted (e.g. "uncertain: clip
    estimate 1-sigma 2.5 cm > 2.0 cm") and some clips never run it, so ``source(agent)``
    (``"registered"``, ``"ins"`` or ``"reference"``), ``source_reason(agent)`` and
    ``registered`` say which one each agent got: filter on them when the relative
    transform's accuracy matters (``CoopDataset(require_registered=True)`` does).
    ``T(a, b)`` between two cooperative agents is registered only when both are.
    """

    def __init__(self, clip: Clip, index: int, frames: dict[str, AgentFrame]) -> None:
        self.clip = clip
        self.index = index
        self.frames = frames
        self.reference_agent = clip.reference_agent
        self.t_ns = frames[self.reference_agent].t_ns

    def __repr__(self) -> str:
        return (f"CoopSample(clip={self.clip.clip_id!r}, index={self.index}, t_ns={self.t_ns}, "
                f"agents={list(self.frames)})")

    def __getitem__(self, agent_id: str) -> AgentFrame:
        return self.frames[agent_id]

    def __iter__(self) -> Iterator[str]:
        return iter(self.frames)

    @property
    def agents(self) -> list[str]:
        return list(self.frames)

    def source(self, agent: str) -> TransformSource:
        """Where ``T(reference, agent)`` comes from: "registered", "ins" or "reference"."""
        return self.frames[agent].T_source

    def source_reason(self, agent: str) -> str:
        """Why ``agent`` is not registered at this sample ("" when it is, or is the
        reference): the register stage's reason for a rejected frame, or what is missing."""
        return self.frames[agent].T_source_reason

    @property
    def sources(self) -> dict[str, TransformSource]:
        """``source(agent)`` of every agent, reference first."""
        return {a: f.T_source for a, f in self.frames.items()}

    @property
    def registered(self) -> bool:
        """True when no agent's relative transform fell back to INS poses (a sample with the
        reference agent alone is trivially registered)."""
        return all(f.T_source != INS for f in self.frames.values())

    def T(self, a: str, b: str) -> np.ndarray:
        """``T_La_Lb`` between two agents' LiDAR frames at this sample."""
        return invert(self.frames[a].T_world_lidar) @ self.frames[b].T_world_lidar

    def points(self, frame: str | None = None) -> dict[str, Points]:
        """Every agent's deskewed points in one frame (default: the reference agent's)."""
        f = frame or self.reference_agent
        return {a: fr.points(f) for a, fr in self.frames.items()}

    def boxes(self, frame: str | None = None) -> dict[str, Boxes]:
        f = frame or self.reference_agent
        return {a: fr.boxes(f) for a, fr in self.frames.items()}

    def registration(self) -> pa.Table:
        """The register stage's rows for this reference frame (empty if it has not run)."""
        r = self.clip.data.registrations
        if r.num_rows == 0:
            return r
        return r.filter(pa.compute.equal(r["frame_idx"], self.frames[self.reference_agent]
                                         .frame_idx))


# ---------------------------------------------------------------------------------- clips
class Clip:
    """One clip. Its small tables are read on first use; nothing of another clip is read."""

    def __init__(self, lake: Lake, clip_id: str, *, sensor: str = "LIDAR_TOP",
                 tolerance_ms: float = 50.0, use_registration: bool = True) -> None:
        self.lake = lake
        self.clip_id = clip_id
        self.sensor = sensor
        self.tolerance_ns = tolerance_ms * 1e6
        self.use_registration = use_registration

    def __repr__(self) -> str:
        return f"Clip({self.clip_id!r})"

    @cached_property
    def data(self) -> ClipData:
        return load_clip(self.lake.io, self.clip_id)

    @property
    def info(self) -> dict[str, Any]:
        """The ``clips`` row: location, road type, weather, lighting, duration, ..."""
        return dict(self.data.info)

    @property
    def agents(self) -> list[str]:
        """Agent ids, reference agent first."""
        return list(self.data.agents)

    @property
    def reference_agent(self) -> str:
        return self.data.reference_agent

    def frames(self, agent: str) -> pa.Table:
        """One agent's LiDAR frames: frame_idx, scan start/end, points time, deskewed."""
        a = self.data.agents[agent]
        lf = a.lidar[a.lidar_sensor(self.sensor)]
        return pa.table({"frame_idx": lf.frame_idx, "t_start_ns": lf.t_start_ns,
                         "t_end_ns": lf.t_end_ns, "t_ns": lf.points_t_ns,
                         "n_points": lf.n_points, "deskewed": lf.deskewed})

    def frame(self, agent: str, frame_idx: int) -> AgentFrame:
        a = self.data.agents[agent]
        lf = a.lidar[a.lidar_sensor(self.sensor)]
        pos = np.flatnonzero(lf.frame_idx == frame_idx)
        if len(pos) == 0:
            raise KeyError(f"clip {self.clip_id} agent {agent}: no LiDAR frame {frame_idx}")
        return AgentFrame(self, agent, int(pos[0]), sensor=self.sensor)

    @cached_property
    def _samples(self) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        ref = self.data.agents[self.reference_agent]
        lf = ref.lidar[ref.lidar_sensor(self.sensor)]
        keep, nears = match_agents(self.data, lf.points_t_ns, self.tolerance_ns,
                                   sensor=self.sensor)
        rows = np.flatnonzero(keep)
        return rows, {a: n[rows] for a, n in nears.items()}

    @property
    def sample_frames(self) -> np.ndarray:
        """Reference-agent frame index of each cooperative sample."""
        ref = self.data.agents[self.reference_agent]
        return ref.lidar[ref.lidar_sensor(self.sensor)].frame_idx[self._samples[0]]

    def __len__(self) -> int:
        """Number of cooperative samples (reference frames every agent can fill)."""
        return len(self._samples[0])

    def sample(self, i: int) -> CoopSample:
        """The i-th cooperative sample: every agent's frame nearest the reference frame."""
        rows, nears = self._samples
        if not -len(rows) <= i < len(rows):
            raise IndexError(f"clip {self.clip_id} has {len(rows)} samples, not {i}")
        i %= len(rows)
        return self._build(i, {a: int(n[i]) for a, n in nears.items()})

    def sample_at(self, frame_idx: int) -> CoopSample:
        """The sample at one reference LiDAR frame, with the agents that can fill it (a scan
        within the tolerance, deskewed, inside its pose coverage): cooperative datasets have
        a varying number of agents, and this needs no look at the clip's other frames."""
        ref = self.data.agents[self.reference_agent]
        lf = ref.lidar[ref.lidar_sensor(self.sensor)]
        pos = np.flatnonzero(lf.frame_idx == frame_idx)
        if len(pos) == 0:
            raise KeyError(f"clip {self.clip_id}: no reference LiDAR frame {frame_idx}")
        t = int(lf.points_t_ns[pos[0]])
        picks = {self.reference_agent: int(pos[0])}
        for aid, agent in self.data.agents.items():
            if aid == self.reference_agent:
                continue
            alf = agent.lidar[agent.lidar_sensor(self.sensor)]
            j = int(nearest_index(alf.points_t_ns, t)[0])
            tj = int(alf.points_t_ns[j])
            if abs(tj - t) <= self.tolerance_ns and alf.deskewed[j] and \
                    bool(agent.poses.covers(tj)):
                picks[aid] = j
        return self._build(-1, picks)

    def _build(self, index: int, picks: dict[str, int]) -> CoopSample:
        ref = self.reference_agent
        frames = {ref: AgentFrame(self, ref, picks[ref], sensor=self.sensor)}
        for aid, j in picks.items():
            if aid == ref:
                continue
            rel = relative_transform(self.data, aid, frames[ref].frame_idx,
                                     use_registration=self.use_registration)
            T = None if rel.T is None else frames[ref].T_world_lidar @ rel.T
            frames[aid] = AgentFrame(self, aid, j, sensor=self.sensor, T_world_lidar=T,
                                     relative=rel)
        s = CoopSample(self, index, frames)
        for f in frames.values():
            f.sample = s
        return s

    def samples(self) -> Iterator[CoopSample]:
        for i in range(len(self)):
            yield self.sample(i)

    def images(self, agent: str, camera: str) -> pa.Table:
        """One camera's frames (frame_idx, stamp_ns, blob key)."""
        f = self.data.agents[agent].cameras[camera]
        return pa.table({"frame_idx": f.frame_idx, "stamp_ns": f.stamp_ns, "blob": f.blob})

    def image(self, agent: str, camera: str, frame_idx: int) -> CameraImage:
        a = self.data.agents[agent]
        pos = np.flatnonzero(a.cameras[camera].frame_idx == frame_idx)
        if len(pos) == 0:
            raise KeyError(f"clip {self.clip_id} {agent}/{camera}: no frame {frame_idx}")
        return self._image(a, camera, int(pos[0]))

    def _image(self, agent: AgentData, camera: str, k: int) -> CameraImage:
        frames = agent.cameras[camera]
        cal = agent.cameras_calib()[camera]
        stamp = int(frames.stamp_ns[k])
        T_we = agent.T_world_ego(stamp, clip_id=self.clip_id)[0]
        key, io = frames.blob[k], self.lake.io
        return CameraImage(agent.agent_id, camera, int(frames.frame_idx[k]), stamp,
                           int(frames.width[k]), int(frames.height[k]), cal.K.copy(),
                           cal.distortion_model, cal.distortion, cal.T_ego_sensor.copy(),
                           T_we @ cal.T_ego_sensor, lambda: io.read_blob("clean", key))

    def registrations(self) -> pa.Table:
        """Eq. 1a / 1b ``T_L1_L2`` per frame pair with fitness, RMSE and acceptance."""
        return self.data.registrations

    def calibration(self) -> pa.Table:
        """Every LiDAR of every agent: its published extrinsic (``T_ego_sensor`` as ``pub_*``),
        the register stage's refinement (``ref_*``, null where there is none: the clip solve
        for a cooperative agent's primary LiDAR, intra-agent against the primary for the
        others), the correction and its 1-sigma, the components determined, whether it is
        usable, which one every consumer uses (``effective``) and why."""
        rows = []
        for c in compare_calibration(self.lake.io, self.clip_id):
            row: dict[str, Any] = {
                "agent_id": c.agent_id, "sensor": c.sensor, "effective": c.effective,
                "usable": c.usable, "method": c.method, "refined_components": c.refined_components,
                "correction_m": c.correction_m, "correction_deg": c.correction_deg,
                "std_m": c.std_m, "std_deg": c.std_deg, "reason": c.reason}
            for prefix, T in (("pub_", c.published), ("ref_", c.refined)):
                q = None if T is None else quat_wxyz_of(T)
                for k, name in enumerate(("tx", "ty", "tz")):
                    row[prefix + name] = None if T is None else float(T[k, 3])
                for k, name in enumerate(("qw", "qx", "qy", "qz")):
                    row[prefix + name] = None if q is None else float(q[k])
            rows.append(row)
        return pa.Table.from_pylist(rows)

    def alignments(self, agent: str | None = None) -> pa.Table:
        """The align stage's LiDAR-camera associations (Sec. 5)."""
        t = self.lake.io.read_table("clean", "alignments", clip_id=self.clip_id,
                                    agent_id=agent)
        if agent is not None and t.num_rows and "agent_id" not in t.column_names:
            t = t.append_column("agent_id", pa.array([agent] * t.num_rows))
        return t

    def _frame_T(self, frame: str, at: AgentFrame) -> np.ndarray:
        """``T_frame_world`` for a frame name, seen from ``at``."""
        if frame == WORLD:
            return np.eye(4)
        if frame == "lidar":
            return invert(at.T_world_lidar)
        if frame == "ego":
            return invert(at.T_world_ego)
        if frame in self.data.agents:
            if at.sample is not None and frame in at.sample.frames:
                return invert(at.sample.frames[frame].T_world_lidar)
            other = self.data.agents[frame]
            s = other.lidar_sensor(self.sensor)
            T = other.T_world_ego(at.t_ns, clip_id=self.clip_id)[0] @ \
                other.sensors[s].T_ego_sensor
            return invert(T)
        raise ValueError(f"unknown frame {frame!r}: 'lidar', 'ego', 'world' or one of "
                         f"{self.agents}")


# ---------------------------------------------------------------------------------- lake
class Lake:
    """A processed lake, read-only. ``v2xlake.open(path)`` returns one."""

    def __init__(self, uri: str | PathLike[str], *, sensor: str = "LIDAR_TOP",
                 tolerance_ms: float = 50.0, use_registration: bool = True,
                 cache_clips: int = 8) -> None:
        self.uri = str(uri)
        self.io = _LakeIO(uri, create=False)
        if not self.io.looks_like_lake():
            raise FileNotFoundError(f"not a v2xlake lake: {uri}")
        self._opts = dict(sensor=sensor, tolerance_ms=tolerance_ms,
                          use_registration=use_registration)
        self._cache: OrderedDict[str, Clip] = OrderedDict()
        self._cache_size = cache_clips
        self._catalog: Catalog | None = None
        self._con: Any = None  # the lean connection of ``_query``
        self._lock = threading.Lock()

    def __repr__(self) -> str:
        return f"v2xlake.Lake({self.uri!r})"

    # pickling (DataLoader workers): the catalog connection and caches stay behind
    def __getstate__(self) -> dict[str, Any]:
        return {"uri": self.uri, "opts": self._opts, "cache_size": self._cache_size}

    def __setstate__(self, st: dict[str, Any]) -> None:
        self.__init__(st["uri"], cache_clips=st["cache_size"], **st["opts"])  # type: ignore[misc]

    @property
    def catalog(self) -> Catalog:
        """The DuckDB catalog, opened on first use: in memory, never writing the lake, and
        locked down (it reads the lake's files and nothing else)."""
        with self._lock:
            if self._catalog is None:
                cat = Catalog(self.io, read_only=True)
                cat.lock_down()
                self._catalog = cat
            return self._catalog

    def _query(self, sql: str, params: list[object] | None = None) -> pa.Table:
        """The API's own fixed queries over ``clips`` and ``frames`` (clean zone), on a lean
        connection: the full catalog binds every table's view at start (reading every
        file's footer: ~1 s on a nuScenes-sized lake), these two bind only what they read.
        Locked down like the catalog: it reads the lake's files and nothing else."""
        import duckdb

        if not self.io.is_local:  # S3 settings and the same clean.* names, bound on demand
            return self.catalog.query(sql, params)
        with self._lock:
            if self._con is None:
                con = duckdb.connect()
                con.execute("CREATE SCHEMA clean")
                for table in ("clips", "lidar_frames", "deskew_frames"):
                    glob = self.io.table_glob("clean", table).replace("'", "''")
                    con.execute(f"CREATE VIEW clean.{table} AS SELECT * FROM read_parquet("
                                f"'{glob}', hive_partitioning=true, "
                                "hive_types_autocast=false, union_by_name=true)")
                root = self.io.path("clean").replace("'", "''")  # all these views read
                for stmt in (f"SET allowed_directories = ['{root}/']",
                             "SET enable_external_access = false",
                             "SET lock_configuration = true"):
                    con.execute(stmt)
                self._con = con
        return self._con.execute(sql, params or []).fetch_arrow_table()

    def sql(self, query: str) -> pa.Table:
        """One SELECT over the catalog's views (``clean.<table>``, ``clips``, ...)."""
        return self.catalog.user_query(query)

    @property
    def clips(self) -> list[str]:
        """Clip ids with status ok, sorted."""
        t = self._query("SELECT clip_id FROM clean.clips WHERE status = 'ok' ORDER BY clip_id")
        return [str(c) for c in t["clip_id"].to_pylist()]

    def clip(self, clip_id: str) -> Clip:
        with self._lock:
            if clip_id in self._cache:
                self._cache.move_to_end(clip_id)
                return self._cache[clip_id]
        checked_clip_id(self.io, clip_id)
        if not self.io.exists(self.io.table_dir("clean", "clips", clip_id)):
            raise KeyError(f"no clip {clip_id!r} in the clean zone of {self.uri}")
        c = Clip(self, clip_id, **self._opts)  # type: ignore[arg-type]
        with self._lock:
            self._cache[clip_id] = c
            while len(self._cache) > self._cache_size:
                self._cache.popitem(last=False)
        return c

    def __getitem__(self, clip_id: str) -> Clip:
        return self.clip(clip_id)

    def __iter__(self) -> Iterator[Clip]:
        for cid in self.clips:
            yield self.clip(cid)

    def frame_index(self, clips: Sequence[str] | None = None) -> pa.Table:
        """Every reference-agent LiDAR frame with deskewed points, lake-wide, from one
        query: clip_id, frame_idx, t_ns. What a sampler or dataset indexes."""
        q = ("SELECT f.clip_id, f.frame_idx, d.deskew_ref_ns AS t_ns "
             "FROM clean.lidar_frames f JOIN clean.clips c ON c.clip_id = f.clip_id "
             "AND f.agent_id = c.reference_agent JOIN clean.deskew_frames d "
             "ON d.clip_id = f.clip_id AND d.agent_id = f.agent_id AND d.sensor = f.sensor "
             "AND d.frame_idx = f.frame_idx "
             "WHERE c.status = 'ok' AND f.sensor = ? AND d.deskew_ref_ns IS NOT NULL ")
        params: list[object] = [self._opts["sensor"]]
        if clips is not None:
            q += "AND f.clip_id IN (SELECT unnest(?)) "
            params.append(list(clips))
        return self._query(q + "ORDER BY f.clip_id, f.frame_idx", params)

    def close(self) -> None:
        if self._con is not None and self._catalog is None:
            self._con.close()
        self._con = None
        if self._catalog is not None:
            self._catalog.close()
            self._catalog = None

    def __enter__(self) -> Lake:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open(path: str | PathLike[str], **options: Any) -> Lake:
    """Open a processed lake read-only (see :class:`Lake` for ``options``)."""
    return Lake(path, **options)


# ---------------------------------------------------------------------------------- dataset
class CoopDataset:
    """Map-style dataset of cooperative samples, for PyTorch's ``DataLoader`` (or anything
    that calls ``len`` and ``[i]``); v2xlake itself never imports torch.

    Item ``i`` is a dict of NumPy arrays. Point clouds and boxes differ in size, so torch's
    default collate fails on them: pass ``collate_fn=v2xlake.collate.collate_fn`` (also
    ``CoopDataset.collate_fn``: per-sample lists plus every point of the batch in one
    ``points_cat`` array with sample and agent index), or a ``transform`` that voxelises.
    The item: ``clip_id``, ``frame_idx`` (reference), ``t_ns``,
    ``agents`` (reference first), ``points`` {agent: (N, 4) x y z intensity in ``frame``},
    ``boxes`` {agent: Boxes as arrays}, ``T`` {agent: ``T_frame_Lagent``}, ``T_source``
    {agent: "registered" | "ins" | "reference"} and ``T_source_reason`` {agent: why not
    registered, "" if it is} (see :class:`CoopSample`: an "ins" agent's points sit where its
    INS pose puts them, typically tens of centimetres off the reference's) and, with
    ``images=True``, ``images`` {agent: [{"camera", "rgb", "K", "T_frame_cam"}]}.
    ``transform(item) -> item`` runs last (augmentation, voxelisation, target encoding).

    The index is every deskewed reference frame (``stride``: every n-th per clip), from the
    lake-wide frame index in one query; an item holds the agents that can fill that frame
    (``Clip.sample_at``). ``require_all_agents=True`` keeps only frames every agent fills
    (``Clip.sample``), which reads each clip's tables once while building the index.
    ``require_registered=True`` keeps only samples where no agent fell back to INS poses
    (``CoopSample.registered``: every cooperative agent's transform is the register stage's
    accepted one); it too reads each clip's tables once while building the index, and a
    clip that never ran register contributes only frames the reference agent fills alone.
    ``clips`` must name clips with status ok (KeyError otherwise, as ``Lake.clip``). A
    worker process re-opens the lake lazily.
    """

    def __init__(self, lake: Lake | str | PathLike[str], clips: Sequence[str] | None = None,
                 *, frame: str = "reference", stride: int = 1, images: bool = False,
                 require_all_agents: bool = False, require_registered: bool = False,
                 transform: Callable[[dict[str, Any]], Any] | None = None) -> None:
        self.lake = lake if isinstance(lake, Lake) else open(lake)
        self.frame = frame
        self.images = images
        self.transform = transform
        self.require_all = require_all_agents
        self.require_registered = require_registered
        if clips is not None:
            clips = list(clips)
            # the frame index query would just match nothing: an empty dataset from a typo
            missing = sorted(set(clips) - set(self.lake.clips))
            if missing:
                raise KeyError(f"no clip(s) {missing} with status ok in the clean zone of "
                               f"{self.lake.uri}")
        step = max(1, stride)
        index: list[tuple[str, int]] = []
        if require_all_agents:
            for cid in list(clips) if clips is not None else self.lake.clips:
                index.extend((cid, i) for i in range(0, len(self.lake.clip(cid)), step))
        else:
            t = self.lake.frame_index(clips)
            ids, fis = t["clip_id"].to_pylist(), t["frame_idx"].to_pylist()
            k, last = 0, None
            for cid, fi in zip(ids, fis, strict=True):
                k = 0 if cid != last else k + 1
                last = cid
                if k % step == 0:
                    index.append((str(cid), int(fi)))
        if require_registered:
            index = [(cid, k) for cid, k in index if self._sample(cid, k).registered]
        self.index = index

    #: ``DataLoader(ds, collate_fn=ds.collate_fn)``: see :mod:`v2xlake.collate`
    collate_fn = staticmethod(_collate_fn)

    def _sample(self, cid: str, k: int) -> CoopSample:
        clip = self.lake.clip(cid)
        return clip.sample(k) if self.require_all else clip.sample_at(k)

    def __len__(self) -> int:
        return len(self.index)

    def __getitem__(self, i: int) -> Any:
        cid, k = self.index[i]
        s = self._sample(cid, k)
        f = s.reference_agent if self.frame == "reference" else self.frame
        item: dict[str, Any] = {
            "clip_id": cid, "frame_idx": s[s.reference_agent].frame_idx, "t_ns": s.t_ns,
            "agents": s.agents, "points": {}, "boxes": {}, "T": {},
            "T_source": dict(s.sources),
            "T_source_reason": {a: fr.T_source_reason for a, fr in s.frames.items()}}
        for a, fr in s.frames.items():
            item["points"][a] = fr.points(f).numpy()
            b = fr.boxes(f)
            item["boxes"][a] = {"instance_id": b.instance_id, "category": b.category,
                                "center": b.center, "size": b.size, "quat_wxyz": b.quat_wxyz,
                                "velocity": b.velocity, "num_lidar_pts": b.num_lidar_pts}
            item["T"][a] = fr.T_to(f)
            if self.images:
                T_f_world = s.clip._frame_T(f, fr)
                item.setdefault("images", {})[a] = [
                    {"camera": im.sensor, "rgb": im.read(), "K": im.K, "stamp_ns": im.stamp_ns,
                     "T_frame_cam": T_f_world @ im.T_world_cam} for im in fr.images()]
        return self.transform(item) if self.transform is not None else item
