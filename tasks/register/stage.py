"""Register stage: cross-agent ``T_L1_L2`` per frame pair (main paper eq. 1a, refined by eq. 1b).

For every scan of the reference agent and the other agent's scan that started at the same
instant (PPS sync), the initial transform comes from the INS poses interpolated at each
deskewed scan's reference time and the LiDAR extrinsics (eq. 1a); GICP on the deskewed
scans refines it, warm-started from the previous frame's accepted correction. Quality and
the accept / reject decision are recorded per frame in clean ``registrations``; a
before/after bird's-eye view (Fig. 5) goes to ``clean/images/<clip>/registration_bev.png``.
The numeric work lives in :mod:`v2xlake.tasks.register`; this module is lake I/O.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Literal

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
from pydantic import BaseModel, ConfigDict, Field

from v2xlake.schemas.arrow import rows_to_table
from v2xlake.schemas.errors import ClipError
from v2xlake.schemas.stage import OutputFile, Stage, StageReport, tables
from v2xlake.schemas.tables import RegistrationRow
from v2xlake.storage.lake import Lake
from v2xlake.storage.reader import pose_missing, read_extrinsics
from v2xlake.tasks.deskew.stage import OUT_TABLE as DESKEWED
from v2xlake.tasks.geometry import matrix_to_quat, transform
from v2xlake.tasks.interpolate import PoseTrack
from v2xlake.tasks.reader import load_pose_track
from v2xlake.tasks.register.backends import GicpParams, Prepared, RegistrationBackend, make_backend
from v2xlake.tasks.register.bev import render_registration_bev
from v2xlake.tasks.register.core import PairResult, QualityLimits, initial_transform_at, refine

log = logging.getLogger(__name__)

STAGE = "register"


class RegisterConfig(BaseModel):
    """Parameters of the register stage (hashed into the manifest)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    backend: Literal["small_gicp", "open3d"] = Field(
        "small_gicp", description="GICP implementation; small_gicp is ~1.4x faster here")
    sensor: str | None = Field(None, description="LiDAR to register; default LIDAR_TOP or the "
                                                 "agent's only LiDAR")
    voxel_m: float = Field(0.6, gt=0, description="target (reference scan) voxel size")
    source_voxel_m: float = Field(1.0, gt=0, description="source (other scan) voxel size")
    max_range_m: float = Field(80.0, gt=0)
    num_neighbors: int = Field(10, ge=5, description="neighbours per covariance")
    max_correspondence_m: float = Field(1.0, gt=0)
    max_iterations: int = Field(30, ge=1)
    fitness_distance_m: float = Field(0.5, gt=0)
    min_fitness: float = Field(0.2, ge=0, le=1)
    min_inliers: int = Field(300, ge=0)
    max_correction_m: float = Field(1.5, gt=0)
    max_correction_deg: float = Field(5.0, gt=0)
    min_observability: float = Field(
        0.02, ge=0, le=1, description="reject when the overlapping surfaces leave a translation "
                                      "direction unconstrained (corridor, open road)")
    warm_start: bool = True
    pair_tolerance_ns: int = Field(1_000_000, ge=0,
                                   description="scan starts closer than this are one pair")
    bev_frame: int | None = Field(None, description="reference frame of the BEV picture "
                                                    "(default: the middle pair)")
    write_bev: bool = True

    def gicp(self) -> GicpParams:
        return GicpParams(voxel_m=self.voxel_m, source_voxel_m=self.source_voxel_m,
                          max_range_m=self.max_range_m, num_neighbors=self.num_neighbors,
                          max_correspondence_m=self.max_correspondence_m,
                          max_iterations=self.max_iterations, num_threads=1)

    def limits(self) -> QualityLimits:
        return QualityLimits(fitness_distance_m=self.fitness_distance_m,
                             min_fitness=self.min_fitness, min_inliers=self.min_inliers,
                             max_correction_m=self.max_correction_m,
                             max_correction_deg=self.max_correction_deg,
                             min_observability=self.min_observability)


def _fail(clip_id: str, reason: str, agent_id: str | None = None) -> ClipError:
    return ClipError(clip_id, reason, agent_id=agent_id, stage=STAGE)


class _AgentScans:
    """One agent's deskewed scans, poses and extrinsic; reads one frame (row group) at a time."""

    def __init__(self, lake: Lake, clip_id: str, agent: str, sensor: str | None) -> None:
        self.agent = agent
        self.track: PoseTrack = load_pose_track(lake, clip_id, agent)
        extr = read_extrinsics(lake, clip_id, agent)
        if not extr:
            raise _fail(clip_id, "no LiDAR in calibrated_sensors", agent)
        if sensor is None:
            sensor = "LIDAR_TOP" if "LIDAR_TOP" in extr else sorted(extr)[0]
        if sensor not in extr:
            raise _fail(clip_id, f"LiDAR {sensor} has no calibrated_sensors row", agent)
        self.sensor, self.T_ego_lidar = sensor, extr[sensor]
        frames = lake.read_table("clean", "lidar_frames", clip_id=clip_id, agent_id=agent)
        desk = lake.read_table("clean", "deskew_frames", clip_id=clip_id, agent_id=agent)
        if frames.num_rows and not desk.num_rows:
            raise _fail(clip_id, "no deskew_frames: run deskew first", agent)
        ref_of = {(str(s), int(f)): r for s, f, r in zip(
            desk.column("sensor").to_pylist(), desk.column("frame_idx").to_pylist(),
            desk.column("deskew_ref_ns").to_pylist(), strict=True)} if desk.num_rows else {}
        # frame_idx -> (scan start, deskew reference time); frames deskew skipped are left out
        self.frames: dict[int, tuple[int, int]] = {}
        if frames.num_rows:
            for s, f, t0 in zip(frames.column("sensor").to_pylist(),
                                frames.column("frame_idx").to_pylist(),
                                frames.column("t_start_ns").to_pylist(), strict=True):
                tr = ref_of.get((str(s), int(f)))
                if s == sensor and tr is not None:
                    self.frames[int(f)] = (int(t0), int(tr))
        self._lake = lake
        self._groups: dict[int, list[tuple[str, int]]] = {}
        for path in lake.list_files(lake.table_dir("clean", DESKEWED, clip_id, agent), ".parquet"):
            pf = pq.ParquetFile(path, filesystem=lake.fs)
            col = pf.schema_arrow.get_field_index("frame_idx")
            for rg in range(pf.num_row_groups):
                st = pf.metadata.row_group(rg).column(col).statistics
                if st is not None and st.has_min_max and st.min == st.max:
                    self._groups.setdefault(int(st.min), []).append((path, rg))
                else:
                    for f in np.unique(pf.read_row_group(rg, columns=["frame_idx"])
                                       .column(0).to_numpy()):
                        self._groups.setdefault(int(f), []).append((path, rg))
        if not self._groups:
            raise _fail(clip_id, f"no {DESKEWED} rows: run deskew first", agent)

    def points(self, frame_idx: int) -> np.ndarray:
        parts = []
        for path, rg in self._groups.get(frame_idx, []):
            t = pq.ParquetFile(path, filesystem=self._lake.fs).read_row_group(
                rg, columns=["sensor", "frame_idx", "x", "y", "z"])
            keep = pc.and_(pc.equal(t.column("frame_idx"), frame_idx),
                           pc.equal(t.column("sensor").cast(pa.string()), self.sensor))
            t = t.filter(keep)
            parts.append(np.stack([t.column(c).to_numpy() for c in ("x", "y", "z")], axis=1))
        return np.concatenate(parts) if parts else np.zeros((0, 3), np.float32)


def _pairs(ref: _AgentScans, other: _AgentScans, tol: int) -> list[tuple[int, int]]:
    """(ref frame, other frame) with scan starts within ``tol`` (PPS: equal)."""
    if not other.frames:
        return []
    of = sorted(other.frames.items(), key=lambda kv: kv[1][0])
    starts = np.array([v[0] for _, v in of], dtype=np.int64)
    out = []
    for f, (t0, _) in sorted(ref.frames.items()):
        k = int(np.searchsorted(starts, t0))
        best = min((j for j in (k - 1, k) if 0 <= j < len(starts)),
                   key=lambda j: abs(int(starts[j]) - t0))
        if abs(int(starts[best]) - t0) <= tol:
            out.append((f, of[best][0]))
    return out


def _row(clip_id: str, ref: str, other: str, frame: int, t_ns: int, r: PairResult,
         method: str) -> RegistrationRow:
    qi, qf = matrix_to_quat(r.T_init[:3, :3]), matrix_to_quat(r.T_final[:3, :3])
    ti, tf = r.T_init[:3, 3], r.T_final[:3, 3]
    return RegistrationRow(
        clip_id=clip_id, agent_ref=ref, agent_other=other, frame_idx=frame, t_ns=t_ns,
        init_tx=ti[0], init_ty=ti[1], init_tz=ti[2], init_qw=qi[0], init_qx=qi[1],
        init_qy=qi[2], init_qz=qi[3], tx=tf[0], ty=tf[1], tz=tf[2], qw=qf[0], qx=qf[1],
        qy=qf[2], qz=qf[3], fitness=r.fitness, inlier_rmse=r.inlier_rmse,
        correction_m=r.correction_m, correction_deg=r.correction_deg, accepted=r.accepted,
        method=method, reason=r.reason)


def _reference_agent(lake: Lake, clip_id: str) -> tuple[str, list[str]]:
    agents = lake.read_table("clean", "agents", clip_id=clip_id)
    if agents.num_rows == 0:
        raise _fail(clip_id, "no clean 'agents' rows: run anonymize first")
    ids = [str(a) for a in agents.column("agent_id").to_pylist()]
    roles = [str(r) for r in agents.column("role").to_pylist()]
    clips = lake.read_table("clean", "clips", clip_id=clip_id)
    ref = str(clips.column("reference_agent")[0].as_py()) if clips.num_rows else None
    if ref not in ids:
        refs = [a for a, r in zip(ids, roles, strict=True) if r == "reference"]
        if not refs:
            raise _fail(clip_id, "no reference agent (clips.reference_agent / role=reference)")
        ref = refs[0]
    return ref, sorted(a for a in ids if a != ref)


def run_register(lake: Lake, clip_id: str, config: RegisterConfig | None = None) -> StageReport:
    """Register every other agent's deskewed scans to the reference agent's, frame by frame."""
    cfg = config or RegisterConfig()
    wall0 = time.perf_counter()
    report = StageReport(stage=STAGE, clip_id=clip_id)
    ref_id, other_ids = _reference_agent(lake, clip_id)
    lake.delete_partition("clean", "registrations", clip_id)
    missing = {a: why for a in (ref_id, *other_ids) if (why := pose_missing(lake, clip_id, a))}
    if ref_id in missing or len(missing) == len(other_ids):
        return StageReport.not_applicable(
            STAGE, clip_id, "registration needs the reference agent and at least one other "
            "agent with a pose track" + (f" ({'; '.join(f'{a}: {w}' for a, w in missing.items())})"
                                         if missing else f"; the clip has {1 + len(other_ids)} "
                                         "agent(s)"))
    other_ids = [a for a in other_ids if a not in missing]
    if not other_ids:
        report.notes.append(f"single agent ({ref_id}): nothing to register")
        return report
    ref = _AgentScans(lake, clip_id, ref_id, cfg.sensor)
    others = [_AgentScans(lake, clip_id, a, cfg.sensor) for a in other_ids]
    backend: RegistrationBackend = make_backend(cfg.backend, cfg.gicp())
    method = f"{cfg.backend}:GICP"
    pairs = {o.agent: dict(_pairs(ref, o, cfg.pair_tolerance_ns)) for o in others}
    ref_frames = sorted({f for p in pairs.values() for f in p})
    if not ref_frames:
        raise _fail(clip_id, "no frame pairs: no scans of the other agents start within "
                             f"{cfg.pair_tolerance_ns} ns of the reference agent's scans")
    bev_frame = cfg.bev_frame if cfg.bev_frame is not None else ref_frames[len(ref_frames) // 2]
    warm: dict[str, np.ndarray | None] = {o.agent: None for o in others}
    rows: list[BaseModel] = []
    results: list[PairResult] = []
    pair_s: list[float] = []
    for f in ref_frames:
        t0 = time.perf_counter()
        ref_xyz = ref.points(f)
        target: Prepared = backend.prepare(ref_xyz, as_target=True)
        for o in others:
            if f not in pairs[o.agent]:
                continue
            fo = pairs[o.agent][f]
            oth_xyz = o.points(fo)
            source = backend.prepare(oth_xyz, as_target=False)
            T_init = initial_transform_at(ref.track, o.track, ref.T_ego_lidar, o.T_ego_lidar,
                                          ref.frames[f][1], o.frames[fo][1])
            res = refine(backend, target, source, T_init, cfg.limits(),
                         warm[o.agent] if cfg.warm_start else None)
            warm[o.agent] = res.correction if res.accepted else warm[o.agent]
            rows.append(_row(clip_id, ref_id, o.agent, f, ref.frames[f][0], res, method))
            results.append(res)
            pair_s.append(time.perf_counter() - t0)
            t0 = time.perf_counter()  # the target's preparation is charged to the first pair
            if not res.accepted:
                log.warning("register %s frame %d %s->%s rejected: %s", clip_id, f, o.agent,
                            ref_id, res.reason)
            if cfg.write_bev and f == bev_frame and o is others[0]:
                key = lake.path("clean", "images", clip_id, "registration_bev.png")
                lake.write_bytes(key, render_registration_bev(
                    ref_xyz, oth_xyz, res.T_init, res.T_final,
                    title=f"{clip_id} frame {f}: {o.agent} -> {ref_id} ({res.reason}, fitness "
                          f"{res.fitness:.2f}, correction {res.correction_m:.2f} m / "
                          f"{res.correction_deg:.2f} deg)"))
                report.images.append(key)
    path, n = lake.write_table("clean", "registrations", rows_to_table(RegistrationRow, rows),
                               clip_id=clip_id, name="registrations")
    report.outputs.append(OutputFile(path=path, rows=n))
    acc = [r for r in results if r.accepted]
    report.metrics.update(
        n_pairs=float(len(results)), n_accepted=float(len(acc)),
        n_rejected=float(len(results) - len(acc)),
        mean_fitness=float(np.mean([r.fitness for r in acc])) if acc else 0.0,
        mean_inlier_rmse_m=float(np.mean([r.inlier_rmse for r in acc])) if acc else 0.0,
        mean_correction_m=float(np.mean([r.correction_m for r in acc])) if acc else 0.0,
        mean_correction_deg=float(np.mean([r.correction_deg for r in acc])) if acc else 0.0,
        median_pair_s=float(np.median(pair_s)) if pair_s else 0.0,
        min_observability=float(np.nanmin([r.observability for r in results]))
        if results and not np.all(np.isnan([r.observability for r in results])) else 0.0,
        seconds=time.perf_counter() - wall0,
    )
    for r in results:
        if not r.accepted:
            report.notes.append(f"rejected: {r.reason}")
    return report


def plot_registration(lake: Lake, clip_id: str, frame_idx: int, out_png: str | Path,
                      agent_other: str | None = None, config: RegisterConfig | None = None
                      ) -> Path:
    """Fig. 5 for one frame from the stored ``registrations`` row and deskewed scans."""
    cfg = config or RegisterConfig()
    regs = lake.read_table("clean", "registrations", clip_id=clip_id)
    rows = [r for r in regs.to_pylist() if r["frame_idx"] == frame_idx
            and (agent_other is None or r["agent_other"] == agent_other)]
    if not rows:
        raise _fail(clip_id, f"no registrations row for frame {frame_idx}"
                             + (f" and agent {agent_other}" if agent_other else ""))
    r = rows[0]

    def mat(prefix: str) -> np.ndarray:
        q = np.array([r[f"{prefix}qw"], r[f"{prefix}qx"], r[f"{prefix}qy"], r[f"{prefix}qz"]])
        return transform(np.array([r[f"{prefix}tx"], r[f"{prefix}ty"], r[f"{prefix}tz"]]),
                         q / np.linalg.norm(q))

    ref = _AgentScans(lake, clip_id, r["agent_ref"], cfg.sensor)
    oth = _AgentScans(lake, clip_id, r["agent_other"], cfg.sensor)
    fo = dict(_pairs(ref, oth, cfg.pair_tolerance_ns)).get(frame_idx, frame_idx)
    out = Path(out_png)
    render_registration_bev(ref.points(frame_idx), oth.points(fo), mat("init_"), mat(""), out,
                            title=f"{clip_id} frame {frame_idx}: {r['agent_other']} -> "
                                  f"{r['agent_ref']} ({r['reason']})")
    return out


REGISTER = Stage(
    name=STAGE, config_model=RegisterConfig,
    reads=tables("clean", "clips", "agents", "ego_poses", "calibrated_sensors", "lidar_frames",
                 "deskew_frames", "lidar_points_deskewed", "annotations"),
    owns=tables("clean", "registrations", "calibration_refined"), run=run_register,
    doc="cross-agent LiDAR transform from poses (eq. 1a) refined by GICP (eq. 1b)")
