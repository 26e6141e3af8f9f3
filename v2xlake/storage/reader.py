"""The one clean-zone reader: a clip's tables as typed records, its points frame by frame.

Every stage after anonymize, every export and the Python API (``v2xlake.open``) read the
clean zone through this module (anonymized, relative time, local ENU), so the lake's layout
(which table holds what, how partitions and row groups are cut, which later table joins
which earlier one) is known in one place and nothing here ever touches ``raw``.

What it returns is data, not math: arrays and 4x4 matrices converted once from the stored
(translation, quaternion) form. Interpolating poses, moving points and boxes between frames
is the tasks' business (``v2xlake.tasks.reader`` builds pose tracks on these records).

Small tables (poses, calibration, frames, annotations) are read whole for one clip; point
tables are streamed frame by frame (one Parquet row group per frame in the lake), so a 30 s
clip of 225k-point scans never sits in memory at once. Radar scans (hundreds of detections) are
read whole per radar.

Two tables are joins of two writers' rows, as the catalog's views join them (one writer per
table, issue #15): ``lidar_frames`` (ingest/anonymize) gets deskew's reference time per frame
from ``deskew_frames``, and a box's ``num_lidar_pts`` is annotate's count
(``annotations_world``), whatever the delivered annotation file said.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from v2xlake.schemas.errors import ClipError
from v2xlake.schemas.geometry import transform
from v2xlake.schemas.stage import StageReport
from v2xlake.storage.lake import Lake

DESKEWED = "lidar_points_deskewed"
NOT_DESKEWED = -1  # LidarFrames.ref_ns of a frame the deskew stage left out


@dataclass(frozen=True, eq=False)
class PoseSamples:
    """The agent's clean ``T_world_ego`` samples, sorted, one per distinct time."""

    t_ns: np.ndarray  # int64
    xyz: np.ndarray  # float64 (N, 3)
    quat_wxyz: np.ndarray  # float64 (N, 4)
    velocity: np.ndarray  # float64 (N, 3) world velocity (zeros where the table has none)

    def __len__(self) -> int:
        return len(self.t_ns)


@dataclass(frozen=True, eq=False)
class SensorCalib:
    """``T_ego_sensor`` of one sensor (4x4) and its modality."""

    sensor: str
    modality: str
    T_ego_sensor: np.ndarray


@dataclass(frozen=True, eq=False)
class CameraCalib(SensorCalib):
    width: int = 0
    height: int = 0
    K: np.ndarray = field(default_factory=lambda: np.eye(3))
    distortion_model: str = "none"
    distortion: tuple[float, ...] = ()


@dataclass(frozen=True, eq=False)
class LidarFrames:
    """Per-frame LiDAR metadata of one sensor, sorted by frame index.

    ``ref_ns`` is the time the frame's deskewed points are expressed at (eq. 3's t_r, from
    deskew's ``deskew_frames``; ``NOT_DESKEWED`` where deskew left the frame out or has not
    run). A consumer of deskewed points uses it, not ``t_start_ns``: deskew may reference a
    scan to its first point instead of its start (``DeskewConfig.reference``).
    """

    sensor: str
    frame_idx: np.ndarray  # int64
    t_start_ns: np.ndarray
    t_end_ns: np.ndarray
    n_points: np.ndarray
    ref_ns: np.ndarray  # int64, NOT_DESKEWED where not deskewed

    def __len__(self) -> int:
        return len(self.frame_idx)

    @property
    def deskewed(self) -> np.ndarray:
        """Mask of the frames that have deskewed points."""
        return self.ref_ns != NOT_DESKEWED

    @property
    def points_t_ns(self) -> np.ndarray:
        """The time of each frame's deskewed points (``ref_ns``; scan start where the frame
        was not deskewed): where a consumer places the frame's LiDAR in the world."""
        return np.where(self.deskewed, self.ref_ns, self.t_start_ns)


@dataclass(frozen=True, eq=False)
class CameraFrames:
    sensor: str
    frame_idx: np.ndarray
    stamp_ns: np.ndarray
    width: np.ndarray
    height: np.ndarray
    blob: list[str]

    def __len__(self) -> int:
        return len(self.frame_idx)


@dataclass(frozen=True, eq=False)
class RadarFrames:
    """Per-scan metadata of one radar, sorted by stamp. A radar scan has one time
    (``stamp_ns``, the message header), as automotive radars report it and as nuScenes
    stores it; its points may still carry their own ``t_ns``."""

    sensor: str
    frame_idx: np.ndarray  # int64
    stamp_ns: np.ndarray  # int64
    n_points: np.ndarray

    def __len__(self) -> int:
        return len(self.frame_idx)


@dataclass(frozen=True, eq=False)
class RadarScan:
    """One radar scan's detections in the radar frame (``radar_points`` rows)."""

    frame_idx: int
    t_ns: np.ndarray  # int64 per point
    xyz: np.ndarray  # float32 (N, 3)
    velocity: np.ndarray  # float32 radial (Doppler) velocity, m/s, positive away
    rcs: np.ndarray  # float32 dBsm, NaN where the radar gives none

    def __len__(self) -> int:
        return len(self.t_ns)


@dataclass(eq=False)
class AgentRecord:
    agent_id: str
    kind: str
    role: str
    pose_samples: PoseSamples
    sensors: dict[str, SensorCalib]
    lidar: dict[str, LidarFrames]
    cameras: dict[str, CameraFrames]
    radar: dict[str, RadarFrames]  # per radar sensor (empty: the agent has no radar)
    annotations: pa.Table  # clean ``annotations`` rows of this agent (may be empty)
    # per sensor: "published" (calibrated_sensors) or "refined" (calibration_refined)
    calibration_source: dict[str, str]

    def cameras_calib(self) -> dict[str, CameraCalib]:
        return {k: v for k, v in self.sensors.items() if isinstance(v, CameraCalib)}

    def lidar_sensor(self, preferred: str = "LIDAR_TOP") -> str:
        if preferred in self.lidar:
            return preferred
        if not self.lidar:
            raise ClipError("", "agent has no LiDAR frames", agent_id=self.agent_id)
        return sorted(self.lidar)[0]


@dataclass(eq=False)
class ClipRecord:
    clip_id: str
    info: dict[str, Any]  # the ``clips`` row
    agents: dict[str, AgentRecord]  # reference agent first
    instances: pa.Table
    registrations: pa.Table

    @property
    def reference_agent(self) -> str:
        return next(iter(self.agents))


def read(lake: Lake, table: str, clip_id: str, agent_id: str | None = None,
         columns: Sequence[str] | None = None) -> pa.Table:
    """One clean table's rows of one clip (and agent); empty table if there are none."""
    return lake.read_table("clean", table, clip_id=clip_id, agent_id=agent_id, columns=columns)


def _rows(t: pa.Table) -> list[dict[str, Any]]:
    return t.to_pylist() if t.num_rows else []


def _np(t: pa.Table, name: str) -> np.ndarray:
    return np.asarray(t.column(name).to_numpy(zero_copy_only=False))


def _of(t: pa.Table, col: str, value: str) -> pa.Table:
    return t.filter(pc.equal(t[col], value)) if t.num_rows else t


def _require(lake: Lake, table: str, clip_id: str) -> pa.Table:
    t = read(lake, table, clip_id)
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


def pose_samples(ego: pa.Table, clip_id: str, agent_id: str) -> PoseSamples:
    """Sorted ``ego_poses`` rows of one agent as arrays; a repeated stamp is one sample."""
    if ego.num_rows < 2:
        raise ClipError(clip_id, "fewer than 2 ego poses", agent_id=agent_id)
    t = _np(ego, "t_ns").astype(np.int64)
    order = np.argsort(t, kind="stable")
    t = t[order]
    keep = np.concatenate([[True], np.diff(t) > 0])
    col = {c: _np(ego, c)[order][keep] for c in ("x", "y", "z", "qw", "qx", "qy", "qz")}
    if "vx" in ego.column_names:
        vel = np.stack([np.nan_to_num(_np(ego, c).astype(np.float64)[order][keep])
                        for c in ("vx", "vy", "vz")], 1)
    else:
        vel = np.zeros((int(keep.sum()), 3))
    return PoseSamples(t[keep], np.stack([col["x"], col["y"], col["z"]], 1).astype(np.float64),
                       np.stack([col["qw"], col["qx"], col["qy"], col["qz"]], 1)
                       .astype(np.float64), vel)


def calibrations(calib: pa.Table, clip_id: str, agent_id: str) -> dict[str, SensorCalib]:
    """``calibrated_sensors`` rows of one agent, a camera with its intrinsics."""
    sensors: dict[str, SensorCalib] = {}
    for c in _rows(calib):
        q = np.array([c["qw"], c["qx"], c["qy"], c["qz"]], dtype=np.float64)
        T = transform(np.array([c["tx"], c["ty"], c["tz"]], dtype=np.float64),
                      q / np.linalg.norm(q))
        if c["modality"] == "camera":
            if c.get("fx") is None or c.get("width") is None:
                raise ClipError(clip_id, f"camera {c['sensor']} has no intrinsics",
                                agent_id=agent_id, stage="export")
            K = np.array([[c["fx"], 0.0, c["cx"]], [0.0, c["fy"], c["cy"]], [0, 0, 1.0]])
            sensors[c["sensor"]] = CameraCalib(
                c["sensor"], "camera", T, int(c["width"]), int(c["height"]), K,
                c.get("distortion_model") or "none", tuple(c.get("distortion") or ()))
        else:
            sensors[c["sensor"]] = SensorCalib(c["sensor"], c["modality"], T)
    return sensors


@dataclass(frozen=True)
class CalibrationChoice:
    """When a refined calibration replaces the published one: register's own decision
    (``usable``, from ``register.calibration.max_std_m/_deg``) unless thresholds are given here;
    ``use_refined=False`` always keeps the published one."""

    use_refined: bool = True
    max_std_m: float | None = None
    max_std_deg: float | None = None

    def accepts(self, row: dict[str, Any]) -> bool:
        if not self.use_refined or not row.get("refined_components"):
            return False
        if self.max_std_m is None and self.max_std_deg is None:
            return bool(row.get("usable"))
        return (row["std_m"] <= (self.max_std_m if self.max_std_m is not None else np.inf)
                and row["std_deg"] <= (self.max_std_deg if self.max_std_deg is not None
                                       else np.inf))


def effective_calibration(published: dict[str, SensorCalib], refined: pa.Table,
                          choice: CalibrationChoice = CalibrationChoice()
                          ) -> tuple[dict[str, SensorCalib], dict[str, str]]:
    """One agent's sensors with the register stage's refined LiDAR extrinsic
    (``calibration_refined``) where ``choice`` accepts it, else the published one
    (``calibrated_sensors``); and per sensor which one it is ("refined" | "published").

    The one place that decides: every consumer after register (annotate, align, the
    exports) reads calibration through ``read_clip``, which calls this."""
    out = dict(published)
    source = {s: "published" for s in published}
    for r in _rows(refined):
        s = r["sensor"]
        if s not in published or not choice.accepts(r):
            continue
        q = np.array([r["qw"], r["qx"], r["qy"], r["qz"]], dtype=np.float64)
        T = transform(np.array([r["tx"], r["ty"], r["tz"]], dtype=np.float64),
                      q / np.linalg.norm(q))
        out[s] = replace(published[s], T_ego_sensor=T)
        source[s] = "refined"
    return out, source


def read_calibration(lake: Lake, clip_id: str, agent_id: str,
                     choice: CalibrationChoice = CalibrationChoice()
                     ) -> tuple[dict[str, SensorCalib], dict[str, str]]:
    """One agent's effective calibration (see ``effective_calibration``); the register stage
    writes ``calibration_refined`` per clip, so its rows are picked by ``agent_id``."""
    return effective_calibration(
        calibrations(read(lake, "calibrated_sensors", clip_id, agent_id), clip_id, agent_id),
        _of(read(lake, "calibration_refined", clip_id), "agent_id", agent_id), choice)


def lidar_frames(frames: pa.Table, deskew: pa.Table) -> dict[str, LidarFrames]:
    """One agent's ``lidar_frames`` per sensor, with deskew's reference time joined in."""
    ref_of: dict[tuple[str, int], int] = {}
    if deskew.num_rows:
        for s, f, r in zip(deskew["sensor"].to_pylist(), deskew["frame_idx"].to_pylist(),
                           deskew["deskew_ref_ns"].to_pylist(), strict=True):
            if r is not None:
                ref_of[(str(s), int(f))] = int(r)
    out: dict[str, LidarFrames] = {}
    for s, f in _per_sensor(frames, "frame_idx"):
        idx = _np(f, "frame_idx").astype(np.int64)
        ref = np.array([ref_of.get((s, int(i)), NOT_DESKEWED) for i in idx], np.int64)
        out[s] = LidarFrames(s, idx, _np(f, "t_start_ns").astype(np.int64),
                             _np(f, "t_end_ns").astype(np.int64), _np(f, "n_points"), ref)
    return out


def _per_sensor(frames: pa.Table, order: str) -> Iterator[tuple[str, pa.Table]]:
    """(sensor, its rows sorted by ``order``) of a frames table, sensors in name order."""
    if not frames.num_rows:
        return
    for s in sorted(set(frames["sensor"].to_pylist())):
        yield s, _of(frames, "sensor", s).sort_by(order)


def camera_frames(frames: pa.Table) -> dict[str, CameraFrames]:
    return {s: CameraFrames(s, _np(f, "frame_idx").astype(np.int64),
                            _np(f, "stamp_ns").astype(np.int64), _np(f, "width"),
                            _np(f, "height"), f["blob"].to_pylist())
            for s, f in _per_sensor(frames, "stamp_ns")}


def radar_frames(frames: pa.Table) -> dict[str, RadarFrames]:
    """One agent's ``radar_frames`` per sensor, sorted by stamp."""
    return {s: RadarFrames(s, _np(f, "frame_idx").astype(np.int64),
                           _np(f, "stamp_ns").astype(np.int64), _np(f, "n_points"))
            for s, f in _per_sensor(frames, "stamp_ns")}


def read_radar_scans(lake: Lake, clip_id: str, agent_id: str, sensor: str
                     ) -> dict[int, RadarScan]:
    """One radar's detections by frame index (clean ``radar_points``).

    Read whole, unlike LiDAR points: a radar scan holds hundreds to a few thousand
    detections, so a clip's worth is a few MB at most.
    """
    t = read(lake, "radar_points", clip_id, agent_id,
             columns=["sensor", "frame_idx", "t_ns", "x", "y", "z", "velocity", "rcs"])
    if t.num_rows == 0:
        return {}
    t = t.filter(pc.equal(t["sensor"].cast(pa.string()), sensor))
    if t.num_rows == 0:
        return {}
    t = t.sort_by([("frame_idx", "ascending"), ("t_ns", "ascending")])
    fidx = _np(t, "frame_idx").astype(np.int64)
    xyz = np.stack([_np(t, c) for c in "xyz"], 1).astype(np.float32, copy=False)
    tt = _np(t, "t_ns").astype(np.int64)
    vel = _np(t, "velocity").astype(np.float32, copy=False)
    rcs = _np(t, "rcs").astype(np.float32, copy=False)
    cuts = np.flatnonzero(np.diff(fidx)) + 1
    out: dict[int, RadarScan] = {}
    for a, b in zip(np.r_[0, cuts], np.r_[cuts, len(fidx)], strict=True):
        out[int(fidx[a])] = RadarScan(int(fidx[a]), tt[a:b], xyz[a:b], vel[a:b], rcs[a:b])
    return out


#: Every clean table ``read_clip`` reads: a stage that loads a clip declares these in its
#: ``Stage.reads`` (less the tables it owns), so its manifest notices a change to any of them.
CLIP_TABLES = ("clips", "agents", "ego_poses", "calibrated_sensors", "lidar_frames",
               "deskew_frames", "calibration_refined", "camera_frames", "radar_frames",
               "annotations", "annotations_world", "instances", "registrations")


def read_clip(lake: Lake, clip_id: str,
              calibration: CalibrationChoice = CalibrationChoice()) -> ClipRecord:
    """Everything but the points of one clip, from the clean zone only; each agent's
    sensors carry the effective calibration (``effective_calibration``)."""
    info = _require(lake, "clips", clip_id).to_pylist()[0]
    agents_t = _require(lake, "agents", clip_id)
    poses_t = _require(lake, "ego_poses", clip_id)
    calib_t = _require(lake, "calibrated_sensors", clip_id)
    lidar_t = _require(lake, "lidar_frames", clip_id)
    desk_t = read(lake, "deskew_frames", clip_id)
    refined_t = read(lake, "calibration_refined", clip_id)
    cam_t = read(lake, "camera_frames", clip_id)
    radar_t = read(lake, "radar_frames", clip_id)
    ann_t = with_point_counts(read(lake, "annotations", clip_id),
                              read(lake, "annotations_world", clip_id))
    agent_rows = _rows(agents_t)
    ref = info.get("reference_agent")
    agent_rows.sort(key=lambda r: (r["agent_id"] != ref, r.get("role") != "reference",
                                   r["agent_id"]))
    agents: dict[str, AgentRecord] = {}
    for row in agent_rows:
        aid = row["agent_id"]
        try:
            poses = pose_samples(_of(poses_t, "agent_id", aid), clip_id, aid)
        except ClipError as e:
            raise ClipError(clip_id, e.reason, agent_id=aid, stage="export") from e
        sensors, source = effective_calibration(
            calibrations(_of(calib_t, "agent_id", aid), clip_id, aid),
            _of(refined_t, "agent_id", aid), calibration)
        agents[aid] = AgentRecord(
            aid, row.get("kind") or "vehicle", row.get("role") or "", poses, sensors,
            lidar_frames(_of(lidar_t, "agent_id", aid), _of(desk_t, "agent_id", aid)),
            camera_frames(_of(cam_t, "agent_id", aid)), radar_frames(_of(radar_t, "agent_id", aid)),
            _of(ann_t, "agent_id", aid), source)
    return ClipRecord(clip_id, info, agents, read(lake, "instances", clip_id),
                      read(lake, "registrations", clip_id))


# ------------------------------------------------------------------ per-agent pose, LiDARs
def pose_missing(lake: Lake, clip_id: str, agent_id: str) -> str | None:
    """Why the agent has no pose track (None: it has one)."""
    agents = read(lake, "agents", clip_id, agent_id)
    if agents.num_rows and not agents.column("has_ins")[0].as_py():
        return "agents.has_ins is false"
    ego = read(lake, "ego_poses", clip_id, agent_id, columns=["t_ns"])
    return None if ego.num_rows else "no clean ego_poses rows"


def no_pose_report(lake: Lake, clip_id: str, stage: str, why_needed: str,
                   agents: Sequence[str] | None = None) -> StageReport | None:
    """A ``not_applicable`` report when none of the clip's agents (or of ``agents``) has a
    pose track, else None. A recording without an INS is still worth its anonymized images
    and raw scans: the stages that need poses say so instead of quarantining the clip (which
    would delete what the earlier stages made)."""
    if agents is None:
        rows = read(lake, "agents", clip_id)
        agents = rows.column("agent_id").to_pylist() if rows.num_rows else []
    without = poses_missing(lake, clip_id, agents)
    if not agents or len(without) < len(agents):
        return None
    return pose_less_report(stage, clip_id, why_needed, without)


def poses_missing(lake: Lake, clip_id: str, agents: Sequence[str]) -> dict[str, str]:
    """{agent: why it has no pose track} for those of ``agents`` without one."""
    return {a: why for a in agents if (why := pose_missing(lake, clip_id, a))}


def pose_less_report(stage: str, clip_id: str, why_needed: str,
                     without: dict[str, str]) -> StageReport:
    """The ``not_applicable`` report of a stage on a clip where no agent has a pose."""
    return StageReport.not_applicable(
        stage, clip_id, "no agent has a pose track (" + "; ".join(
            f"{a}: {w}" for a, w in without.items()) + f"): {why_needed}")


def read_pose_samples(lake: Lake, clip_id: str, agent_id: str) -> PoseSamples:
    """The agent's clean ``T_world_ego`` samples; ClipError if the agent has no INS."""
    why = pose_missing(lake, clip_id, agent_id)
    if why:
        raise ClipError(clip_id, f"agent {agent_id} has no INS ({why}): per-point motion "
                        "compensation and registration need poses", agent_id=agent_id)
    return pose_samples(read(lake, "ego_poses", clip_id, agent_id), clip_id, agent_id)


def read_extrinsics(lake: Lake, clip_id: str, agent_id: str,
                    modality: str = "lidar") -> dict[str, np.ndarray]:
    """``T_ego_sensor`` 4x4 of every sensor of one modality of the agent."""
    cal = calibrations(_of(read(lake, "calibrated_sensors", clip_id, agent_id), "modality",
                           modality), clip_id, agent_id)
    return {s: c.T_ego_sensor for s, c in cal.items()}


# ------------------------------------------------------------------ points per frame
@dataclass(frozen=True, eq=False)
class PointFrame:
    frame_idx: int
    t_ns: np.ndarray  # int64 per point
    xyz: np.ndarray  # float32 (N, 3)
    intensity: np.ndarray  # float32
    ring: np.ndarray  # uint16


def _point_files(lake: Lake, table: str, clip_id: str, agent_id: str) -> tuple[list[str], bool]:
    lake.check_read("clean", table)
    files = lake.list_files(lake.table_dir("clean", table, clip_id, agent_id), ".parquet")
    if files:
        return files, False
    return lake.list_files(lake.table_dir("clean", table, clip_id), ".parquet"), True


def iter_point_frames(lake: Lake, clip_id: str, agent_id: str, *,
                      table: str = DESKEWED, sensor: str = "LIDAR_TOP",
                      frames: Sequence[int] | None = None) -> Iterator[PointFrame]:
    """Stream one agent's points frame by frame (sorted by frame index, NaNs dropped).

    Reads row group by row group, so memory stays at about one frame. ``frames`` restricts
    which frame indices are decoded (row groups whose statistics exclude them are skipped).
    """
    files, need_filter = _point_files(lake, table, clip_id, agent_id)
    if not files:
        hint = " (run the deskew stage first)" if table == DESKEWED else ""
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
                t = t.filter(pc.equal(t["agent_id"], agent_id))
            if "sensor" in t.column_names and t.num_rows:
                s = t["sensor"].combine_chunks()
                if pa.types.is_dictionary(s.type):
                    # one LiDAR per table is the common case: skip the row filter then
                    if s.dictionary.to_pylist() != [sensor]:
                        t = t.filter(pc.equal(s.cast(pa.string()), sensor))
                else:
                    t = t.filter(pc.equal(s, sensor))
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
                part = t if len(uniq) == 1 else t.filter(pc.equal(t["frame_idx"], fi_i))
                pending.setdefault(fi_i, []).append(part)
            # every frame strictly below the last one in this chunk is complete
            last = int(fidx.max())
            for fi_i in sorted(k for k in pending if k < last):
                yield emit(fi_i)
    for fi_i in sorted(pending):
        yield emit(fi_i)


def read_point_frame(lake: Lake, clip_id: str, agent_id: str, frame_idx: int, *,
                     table: str = DESKEWED, sensor: str = "LIDAR_TOP") -> PointFrame | None:
    """One frame's points (None if the table has none for it); decodes only the row groups
    whose statistics may hold it."""
    for fr in iter_point_frames(lake, clip_id, agent_id, table=table, sensor=sensor,
                                frames=[frame_idx]):
        return fr
    return None


def available_frames(lake: Lake, clip_id: str, agent_id: str, *,
                     table: str = DESKEWED, sensor: str = "LIDAR_TOP") -> set[int]:
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
