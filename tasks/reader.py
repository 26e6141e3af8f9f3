"""The one clean-zone reader: a clip as typed in-memory structures, its points per frame.

Every stage after anonymize and every export reads the clean zone through this module
(anonymized, relative time, local ENU), so nothing here ever touches ``raw``. Small tables
(poses, calibration, frames, annotations) are loaded whole; point tables are streamed frame
by frame (one Parquet row group per frame in the lake), so a 30 s clip with 225k-point scans
never has to sit in memory at once. A box's ``num_lidar_pts`` is the annotate stage's count
(``annotations_world``), whatever the delivered annotation file said.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from v2xlake.schemas.errors import ClipError
from v2xlake.storage.lake import Lake
from v2xlake.tasks.geometry import transform
from v2xlake.tasks.interpolate import PoseCoverageError, PoseTrack


@dataclass(frozen=True)
class SensorCalib:
    """``T_ego_sensor`` of one sensor (4x4) and its modality."""

    sensor: str
    modality: str
    T_ego_sensor: np.ndarray


@dataclass(frozen=True)
class CameraCalib(SensorCalib):
    width: int = 0
    height: int = 0
    K: np.ndarray = field(default_factory=lambda: np.eye(3))
    distortion_model: str = "none"
    distortion: tuple[float, ...] = ()


@dataclass(frozen=True)
class LidarFrames:
    """Per-frame LiDAR metadata of one sensor, sorted by frame index."""

    sensor: str
    frame_idx: np.ndarray  # int64
    t_start_ns: np.ndarray
    t_end_ns: np.ndarray
    n_points: np.ndarray

    def __len__(self) -> int:
        return len(self.frame_idx)


@dataclass(frozen=True)
class CameraFrames:
    sensor: str
    frame_idx: np.ndarray
    stamp_ns: np.ndarray
    width: np.ndarray
    height: np.ndarray
    blob: list[str]

    def __len__(self) -> int:
        return len(self.frame_idx)


@dataclass
class AgentData:
    agent_id: str
    kind: str
    role: str
    poses: PoseTrack
    sensors: dict[str, SensorCalib]
    lidar: dict[str, LidarFrames]
    cameras: dict[str, CameraFrames]
    annotations: pa.Table  # clean ``annotations`` rows of this agent (may be empty)
    velocity: np.ndarray  # (N, 3) world velocity at the pose samples

    def cameras_calib(self) -> dict[str, CameraCalib]:
        return {k: v for k, v in self.sensors.items() if isinstance(v, CameraCalib)}

    def T_world_ego(self, t_ns: np.ndarray | int, *, clip_id: str = "") -> np.ndarray:
        """(N, 4, 4) interpolated ego poses (eq. 2a-2c), never extrapolated."""
        try:
            return self.poses.matrices(t_ns)
        except PoseCoverageError as e:
            raise ClipError(clip_id, f"ego pose interpolation: {e}", agent_id=self.agent_id,
                            stage="export") from e

    def lidar_sensor(self, preferred: str = "LIDAR_TOP") -> str:
        if preferred in self.lidar:
            return preferred
        if not self.lidar:
            raise ClipError("", "agent has no LiDAR frames", agent_id=self.agent_id)
        return sorted(self.lidar)[0]


@dataclass
class ClipData:
    clip_id: str
    info: dict[str, Any]  # the ``clips`` row
    agents: dict[str, AgentData]  # reference agent first
    instances: pa.Table
    registrations: pa.Table

    @property
    def reference_agent(self) -> str:
        return next(iter(self.agents))


def _read(lake: Lake, table: str, clip_id: str) -> pa.Table:
    return lake.read_table("clean", table, clip_id=clip_id)


def _rows(t: pa.Table) -> list[dict[str, Any]]:
    return t.to_pylist() if t.num_rows else []


def _require(lake: Lake, table: str, clip_id: str) -> pa.Table:
    t = _read(lake, table, clip_id)
    if t.num_rows == 0:
        raise ClipError(clip_id, f"clean table {table!r} is missing or empty for this clip",
                        path=lake.table_dir("clean", table, clip_id), stage="export")
    return t


def with_point_counts(ann: pa.Table, world: pa.Table) -> pa.Table:
    """``num_lidar_pts`` as the annotate stage counted it (its ``annotations_world``): the one
    definition of a box's point count, which every export reads instead of recounting."""
    if ann.num_rows == 0 or world.num_rows == 0:
        return ann
    key = ("agent_id", "frame_idx", "instance_id")
    counted = {tuple(r[k] for k in key): r["num_lidar_pts"]
               for r in world.select([*key, "num_lidar_pts"]).to_pylist()}
    rows = ann.select(list(key)).to_pylist()
    old = ann["num_lidar_pts"].to_pylist()
    new = [counted.get(tuple(r[k] for k in key), o) for r, o in zip(rows, old, strict=True)]
    i = ann.schema.get_field_index("num_lidar_pts")
    return ann.set_column(i, ann.schema.field(i), pa.array(new, ann.schema.field(i).type))


def load_clip(lake: Lake, clip_id: str) -> ClipData:
    """Everything but the points of one clip, from the clean zone only."""
    clips = _require(lake, "clips", clip_id)
    info = clips.to_pylist()[0]
    agents_t = _require(lake, "agents", clip_id)
    poses_t = _require(lake, "ego_poses", clip_id)
    calib_t = _require(lake, "calibrated_sensors", clip_id)
    lidar_t = _require(lake, "lidar_frames", clip_id)
    cam_t = _read(lake, "camera_frames", clip_id)
    ann_t = with_point_counts(_read(lake, "annotations", clip_id),
                              _read(lake, "annotations_world", clip_id))
    inst_t = _read(lake, "instances", clip_id)
    reg_t = _read(lake, "registrations", clip_id)

    agent_rows = _rows(agents_t)
    ref = info.get("reference_agent")
    agent_rows.sort(key=lambda r: (r["agent_id"] != ref, r.get("role") != "reference",
                                   r["agent_id"]))
    agents: dict[str, AgentData] = {}
    for row in agent_rows:
        aid = row["agent_id"]
        p = poses_t.filter(pa.compute.equal(poses_t["agent_id"], aid))
        if p.num_rows < 2:
            raise ClipError(clip_id, "fewer than 2 ego poses", agent_id=aid, stage="export")
        p = p.sort_by("t_ns")
        col = {c: p[c].to_numpy() for c in ("t_ns", "x", "y", "z", "qw", "qx", "qy", "qz")}
        try:
            track = PoseTrack.create(
                col["t_ns"], np.stack([col["x"], col["y"], col["z"]], 1),
                np.stack([col["qw"], col["qx"], col["qy"], col["qz"]], 1))
        except ValueError as e:
            raise ClipError(clip_id, f"ego_poses: {e}", agent_id=aid, stage="export") from e
        vel = np.stack([p[c].to_numpy(zero_copy_only=False) for c in ("vx", "vy", "vz")], 1) \
            if "vx" in p.column_names else np.zeros((p.num_rows, 3))
        sensors: dict[str, SensorCalib] = {}
        for c in _rows(calib_t.filter(pa.compute.equal(calib_t["agent_id"], aid))):
            T = transform(np.array([c["tx"], c["ty"], c["tz"]]),
                          np.array([c["qw"], c["qx"], c["qy"], c["qz"]]))
            if c["modality"] == "camera":
                if c.get("fx") is None or c.get("width") is None:
                    raise ClipError(clip_id, f"camera {c['sensor']} has no intrinsics",
                                    agent_id=aid, stage="export")
                K = np.array([[c["fx"], 0.0, c["cx"]], [0.0, c["fy"], c["cy"]], [0, 0, 1.0]])
                sensors[c["sensor"]] = CameraCalib(
                    c["sensor"], "camera", T, int(c["width"]), int(c["height"]), K,
                    c.get("distortion_model") or "none", tuple(c.get("distortion") or ()))
            else:
                sensors[c["sensor"]] = SensorCalib(c["sensor"], c["modality"], T)
        lidar: dict[str, LidarFrames] = {}
        lf = lidar_t.filter(pa.compute.equal(lidar_t["agent_id"], aid))
        for s in sorted(set(lf["sensor"].to_pylist())):
            f = lf.filter(pa.compute.equal(lf["sensor"], s)).sort_by("frame_idx")
            lidar[s] = LidarFrames(s, f["frame_idx"].to_numpy().astype(np.int64),
                                   f["t_start_ns"].to_numpy(), f["t_end_ns"].to_numpy(),
                                   f["n_points"].to_numpy())
        cameras: dict[str, CameraFrames] = {}
        if cam_t.num_rows:
            cf = cam_t.filter(pa.compute.equal(cam_t["agent_id"], aid))
            for s in sorted(set(cf["sensor"].to_pylist())):
                f = cf.filter(pa.compute.equal(cf["sensor"], s)).sort_by("stamp_ns")
                cameras[s] = CameraFrames(s, f["frame_idx"].to_numpy().astype(np.int64),
                                          f["stamp_ns"].to_numpy(), f["width"].to_numpy(),
                                          f["height"].to_numpy(), f["blob"].to_pylist())
        ann = ann_t.filter(pa.compute.equal(ann_t["agent_id"], aid)) if ann_t.num_rows \
            else ann_t
        agents[aid] = AgentData(aid, row.get("kind", "vehicle"), row.get("role", ""), track,
                                sensors, lidar, cameras, ann, vel)
    return ClipData(clip_id, info, agents, inst_t, reg_t)


@dataclass(frozen=True)
class PointFrame:
    frame_idx: int
    t_ns: np.ndarray  # int64 per point
    xyz: np.ndarray  # float32 (N, 3)
    intensity: np.ndarray  # float32
    ring: np.ndarray  # uint16


def _point_files(lake: Lake, table: str, clip_id: str, agent_id: str) -> tuple[list[str], bool]:
    files = lake.list_files(lake.table_dir("clean", table, clip_id, agent_id), ".parquet")
    if files:
        return files, False
    return lake.list_files(lake.table_dir("clean", table, clip_id), ".parquet"), True


def iter_point_frames(lake: Lake, clip_id: str, agent_id: str, *,
                      table: str = "lidar_points_deskewed", sensor: str = "LIDAR_TOP",
                      frames: Sequence[int] | None = None) -> Iterator[PointFrame]:
    """Stream one agent's points frame by frame (sorted by frame index, NaNs dropped).

    Reads row group by row group, so memory stays at about one frame. ``frames`` restricts
    which frame indices are decoded (row groups whose statistics exclude them are skipped).
    """
    files, need_filter = _point_files(lake, table, clip_id, agent_id)
    if not files:
        hint = " (run the deskew stage first)" if table == "lidar_points_deskewed" else ""
        raise ClipError(clip_id, f"clean table {table!r} has no points for this agent{hint}",
                        agent_id=agent_id, path=lake.table_dir("clean", table, clip_id),
                        stage="export")
    want = None if frames is None else {int(f) for f in frames}
    cols = ["frame_idx", "t_ns", "x", "y", "z", "intensity", "ring", "sensor"]
    pending: dict[int, list[pa.Table]] = {}
    done: set[int] = set()

    def emit(fi: int) -> PointFrame:
        parts = pending.pop(fi)
        t = parts[0] if len(parts) == 1 else pa.concat_tables(parts)
        done.add(fi)
        n = t.num_rows
        xyz = np.empty((n, 3), np.float32)
        for j, c in enumerate("xyz"):
            xyz[:, j] = t[c].to_numpy()
        ok = np.isfinite(xyz).all(1)
        tt = t["t_ns"].to_numpy()
        inten = t["intensity"].to_numpy().astype(np.float32, copy=False)
        ring = t["ring"].to_numpy().astype(np.uint16, copy=False)
        if ok.all():
            return PointFrame(fi, tt, xyz, inten, ring)
        return PointFrame(fi, tt[ok], xyz[ok], inten[ok], ring[ok])

    for path in files:
        pf = pq.ParquetFile(path, filesystem=lake.fs)
        names = set(pf.schema_arrow.names)
        read_cols = [c for c in cols if c in names] + (["agent_id"] if need_filter
                                                        and "agent_id" in names else [])
        fi_pos = pf.schema_arrow.names.index("frame_idx")
        for rg in range(pf.num_row_groups):
            if want is not None:
                st = pf.metadata.row_group(rg).column(fi_pos).statistics
                if st is not None and st.has_min_max and not any(
                        st.min <= w <= st.max for w in want):
                    continue
            t = pf.read_row_group(rg, columns=read_cols)
            if need_filter and "agent_id" in t.column_names:
                t = t.filter(pa.compute.equal(t["agent_id"], agent_id))
            if "sensor" in t.column_names and t.num_rows:
                s = t["sensor"].combine_chunks()
                if pa.types.is_dictionary(s.type):
                    # one LiDAR per table is the common case: skip the row filter then
                    if s.dictionary.to_pylist() != [sensor]:
                        t = t.filter(pa.compute.equal(s.cast(pa.string()), sensor))
                else:
                    t = t.filter(pa.compute.equal(s, sensor))
            if t.num_rows == 0:
                continue
            fidx = t["frame_idx"].to_numpy()
            uniq = [int(fidx[0])] if fidx[0] == fidx[-1] and (fidx == fidx[0]).all() \
                else [int(f) for f in np.unique(fidx)]
            for fi_i in uniq:
                if want is not None and fi_i not in want:
                    continue
                if fi_i in done:
                    raise ClipError(clip_id, f"{table}: frame {fi_i} is split across "
                                    "non-adjacent row groups (table not sorted by frame)",
                                    agent_id=agent_id, path=path, stage="export")
                part = t if len(uniq) == 1 else t.filter(pa.compute.equal(t["frame_idx"],
                                                                          fi_i))
                pending.setdefault(fi_i, []).append(part)
            # every frame strictly below the last one in this chunk is complete
            last = int(fidx.max())
            for fi_i in sorted(k for k in pending if k < last):
                yield emit(fi_i)
    for fi_i in sorted(pending):
        yield emit(fi_i)


def available_frames(lake: Lake, clip_id: str, agent_id: str, *,
                     table: str = "lidar_points_deskewed", sensor: str = "LIDAR_TOP") -> set[int]:
    """Frame indices that have points in ``table`` (a stage may skip frames, e.g. deskew
    when INS does not cover a scan); reads only the frame_idx / sensor columns."""
    files, need_filter = _point_files(lake, table, clip_id, agent_id)
    out: set[int] = set()
    for path in files:
        pf = pq.ParquetFile(path, filesystem=lake.fs)
        names = set(pf.schema_arrow.names)
        cols = ["frame_idx"] + [c for c in ("sensor",) if c in names] + \
            (["agent_id"] if need_filter and "agent_id" in names else [])
        t = pf.read(columns=cols)
        mask = np.ones(t.num_rows, bool)
        if "sensor" in t.column_names:
            mask &= np.asarray(t["sensor"].cast(pa.string()).to_numpy(zero_copy_only=False)
                               == sensor)
        if "agent_id" in t.column_names:
            mask &= np.asarray(t["agent_id"].to_numpy(zero_copy_only=False) == agent_id)
        out |= {int(f) for f in np.unique(t["frame_idx"].to_numpy()[mask])}
    return out


def boxes_matrices(ann: pa.Table) -> np.ndarray:
    """(N, 4, 4) ``T_frame_box`` of annotation rows."""
    c = {k: ann[k].to_numpy() for k in ("cx", "cy", "cz", "qw", "qx", "qy", "qz")}
    q = np.stack([c["qw"], c["qx"], c["qy"], c["qz"]], 1)
    return transform(np.stack([c["cx"], c["cy"], c["cz"]], 1), q)


def nearest_index(sorted_t: np.ndarray, t: np.ndarray | int) -> np.ndarray:
    """Index of the nearest value in a sorted array, for each query."""
    t = np.atleast_1d(np.asarray(t, dtype=np.int64))
    i = np.clip(np.searchsorted(sorted_t, t), 1, max(len(sorted_t) - 1, 1))
    left = sorted_t[i - 1]
    right = sorted_t[np.minimum(i, len(sorted_t) - 1)]
    return np.where(np.abs(t - left) <= np.abs(right - t), i - 1, i).astype(np.int64)


def lidar_world_poses(agent: AgentData, sensor: str, t_ns: np.ndarray, clip_id: str) -> np.ndarray:
    """``T_world_lidar(t) = T_world_ego(t) @ T_ego_lidar`` for each time."""
    return agent.T_world_ego(t_ns, clip_id=clip_id) @ agent.sensors[sensor].T_ego_sensor


# ------------------------------------------------------------------ per-agent pose and LiDARs
def _np(t: pa.Table, name: str) -> np.ndarray:
    return np.asarray(t.column(name).to_numpy(zero_copy_only=False))


def pose_missing(lake: Lake, clip_id: str, agent_id: str) -> str | None:
    """Why the agent has no pose track (None: it has one)."""
    agents = lake.read_table("clean", "agents", clip_id=clip_id, agent_id=agent_id)
    if agents.num_rows and not agents.column("has_ins")[0].as_py():
        return "agents.has_ins is false"
    ego = lake.read_table("clean", "ego_poses", clip_id=clip_id, agent_id=agent_id,
                          columns=["t_ns"])
    return None if ego.num_rows else "no clean ego_poses rows"


def load_pose_track(lake: Lake, clip_id: str, agent_id: str) -> PoseTrack:
    """The agent's clean ``T_world_ego`` samples; ClipError if the agent has no INS."""
    why = pose_missing(lake, clip_id, agent_id)
    if why:
        raise ClipError(clip_id, f"agent {agent_id} has no INS ({why}): per-point motion "
                        "compensation and registration need poses", agent_id=agent_id)
    ego = lake.read_table("clean", "ego_poses", clip_id=clip_id, agent_id=agent_id)
    order = np.argsort(_np(ego, "t_ns"), kind="stable")
    t = _np(ego, "t_ns")[order]
    keep = np.concatenate([[True], np.diff(t) > 0])  # a repeated stamp is one sample
    xyz = np.stack([_np(ego, c)[order] for c in ("x", "y", "z")], axis=1)[keep]
    q = np.stack([_np(ego, c)[order] for c in ("qw", "qx", "qy", "qz")], axis=1)[keep]
    try:
        return PoseTrack.create(t[keep], xyz, q)
    except ValueError as e:
        raise ClipError(clip_id, f"ego_poses unusable: {e}", agent_id=agent_id) from e


def load_extrinsics(lake: Lake, clip_id: str, agent_id: str) -> dict[str, np.ndarray]:
    """``T_ego_sensor`` 4x4 of every LiDAR of the agent, from clean ``calibrated_sensors``."""
    cal = lake.read_table("clean", "calibrated_sensors", clip_id=clip_id, agent_id=agent_id)
    out: dict[str, np.ndarray] = {}
    for row in cal.to_pylist():
        if row.get("modality") != "lidar":
            continue
        q = np.array([row["qw"], row["qx"], row["qy"], row["qz"]], dtype=np.float64)
        out[str(row["sensor"])] = transform(
            np.array([row["tx"], row["ty"], row["tz"]]), q / np.linalg.norm(q))
    return out
