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
from pydantic import BaseModel, ConfigDict, Field

from v2xlake.schemas.arrow import rows_to_table
from v2xlake.schemas.stage import OutputFile, Stage, StageReport, tables
from v2xlake.schemas.tables import RegistrationRow
from v2xlake.storage.lake import Lake
from v2xlake.storage.reader import pose_missing
from v2xlake.tasks.geometry import matrix_to_quat, transform
from v2xlake.tasks.register.backends import GicpParams, Prepared, RegistrationBackend, make_backend
from v2xlake.tasks.register.bev import render_registration_bev
from v2xlake.tasks.register.core import (
    PairResult,
    QualityLimits,
    failed_pair,
    initial_transform_at,
    refine,
)
from v2xlake.tasks.register.scans import (
    AgentScans,
    Body,
    StaticScans,
    StaticSettings,
    _fail,
)
from v2xlake.tasks.register.static import RemovalCounts

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
    # static scene only (issue #13): what moves is removed before GICP
    static_only: bool = Field(True, description="remove moving things before GICP")
    use_annotations: bool = Field(True, description="remove the scan's annotated boxes")
    box_margin_m: float = Field(0.3, ge=0, description="annotated boxes are grown by this")
    body_margin_m: float = Field(0.6, ge=0, description="other agents' declared bodies, placed "
                                 "by their INS poses, are grown by this")
    dynamic_filter: Literal["auto", "on", "off"] = Field(
        "auto", description="remove points inconsistent with the neighbouring scans of the same "
                            "agent; auto: in frames without annotations")
    dynamic_residual_m: float = Field(0.5, gt=0, description="a point farther than this from "
                                      "the earlier AND the later neighbouring scans is moving")
    dynamic_neighbours: int = Field(2, ge=1, description="scans on each side compared")
    dynamic_voxel_m: float = Field(0.25, gt=0, description="voxel of the neighbouring scans")
    dynamic_object_fraction: float = Field(
        0.25, gt=0, le=1, description="an above-ground object (connected in bird's-eye view) "
        "with this fraction of moving points is removed whole (1: per point only)")

    def gicp(self) -> GicpParams:
        return GicpParams(voxel_m=self.voxel_m, source_voxel_m=self.source_voxel_m,
                          max_range_m=self.max_range_m, num_neighbors=self.num_neighbors,
                          max_correspondence_m=self.max_correspondence_m,
                          max_iterations=self.max_iterations, num_threads=1)

    def static(self) -> StaticSettings:
        return StaticSettings(enabled=self.static_only, use_annotations=self.use_annotations,
                              box_margin_m=self.box_margin_m, body_margin_m=self.body_margin_m,
                              dynamic=self.dynamic_filter,
                              dynamic_residual_m=self.dynamic_residual_m,
                              dynamic_neighbours=self.dynamic_neighbours,
                              dynamic_voxel_m=self.dynamic_voxel_m,
                              dynamic_object_fraction=self.dynamic_object_fraction,
                              max_range_m=self.max_range_m)

    def limits(self) -> QualityLimits:
        return QualityLimits(fitness_distance_m=self.fitness_distance_m,
                             min_fitness=self.min_fitness, min_inliers=self.min_inliers,
                             max_correction_m=self.max_correction_m,
                             max_correction_deg=self.max_correction_deg,
                             min_observability=self.min_observability)


def _pairs(ref: AgentScans, other: AgentScans, tol: int) -> list[tuple[int, int]]:
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
         method: str, n_ref: int, n_oth: int, c_ref: RemovalCounts, c_oth: RemovalCounts
         ) -> RegistrationRow:
    qi, qf = matrix_to_quat(r.T_init[:3, :3]), matrix_to_quat(r.T_final[:3, :3])
    ti, tf = r.T_init[:3, 3], r.T_final[:3, 3]
    return RegistrationRow(
        clip_id=clip_id, agent_ref=ref, agent_other=other, frame_idx=frame, t_ns=t_ns,
        init_tx=ti[0], init_ty=ti[1], init_tz=ti[2], init_qw=qi[0], init_qx=qi[1],
        init_qy=qi[2], init_qz=qi[3], tx=tf[0], ty=tf[1], tz=tf[2], qw=qf[0], qx=qf[1],
        qy=qf[2], qz=qf[3], fitness=r.fitness, inlier_rmse=r.inlier_rmse,
        correction_m=r.correction_m, correction_deg=r.correction_deg, accepted=r.accepted,
        method=method, reason=r.reason, n_points_ref=n_ref, n_points_other=n_oth,
        removed_boxes=c_ref.boxes + c_oth.boxes, removed_bodies=c_ref.bodies + c_oth.bodies,
        removed_dynamic=c_ref.dynamic + c_oth.dynamic)


def _bodies(lake: Lake, clip_id: str, agents: list[AgentScans], cfg: RegisterConfig
            ) -> dict[str, Body]:
    """Declared footprints of the agents (clean ``agents``: length, width, height and the box
    centre in the ego frame); agents without one are not removed from the others' scans."""
    t = lake.read_table("clean", "agents", clip_id=clip_id)
    out: dict[str, Body] = {}
    if not cfg.static_only or t.num_rows == 0 or "length_m" not in t.column_names:
        return out
    ids = {a.agent for a in agents}
    for r in t.to_pylist():
        if r["agent_id"] in ids and r.get("length_m") and r.get("width_m") and r.get("height_m"):
            c = tuple(float(r.get(k) or 0.0) for k in ("body_dx", "body_dy", "body_dz"))
            out[r["agent_id"]] = Body(float(r["length_m"]), float(r["width_m"]),
                                      float(r["height_m"]), (c[0], c[1], c[2]))
    return out


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
    ref = AgentScans(lake, clip_id, ref_id, cfg.sensor)
    others = [AgentScans(lake, clip_id, a, cfg.sensor) for a in other_ids]
    backend: RegistrationBackend = make_backend(cfg.backend, cfg.gicp())
    method = f"{cfg.backend}:GICP"
    pairs = {o.agent: dict(_pairs(ref, o, cfg.pair_tolerance_ns)) for o in others}
    ref_frames = sorted({f for p in pairs.values() for f in p})
    if not ref_frames:
        raise _fail(clip_id, "no frame pairs: no scans of the other agents start within "
                             f"{cfg.pair_tolerance_ns} ns of the reference agent's scans")
    static = cfg.static()
    bodies = _bodies(lake, clip_id, [ref, *others], cfg)
    ref_static = StaticScans(ref, static, [(o, bodies[o.agent]) for o in others
                                           if o.agent in bodies])
    oth_static = {o.agent: StaticScans(o, static, [(a, bodies[a.agent]) for a in (ref, *others)
                                                   if a is not o and a.agent in bodies])
                  for o in others}
    bev_frame = cfg.bev_frame if cfg.bev_frame is not None else ref_frames[len(ref_frames) // 2]
    warm: dict[str, np.ndarray | None] = {o.agent: None for o in others}
    rows: list[BaseModel] = []
    results: list[PairResult] = []
    pair_s: list[float] = []
    removed = RemovalCounts()
    for f in ref_frames:
        t0 = time.perf_counter()
        target: Prepared | None = None
        target_error = ""
        ref_scan = ref_static.filtered(f, cfg.voxel_m)
        try:
            target = backend.prepare_points(ref_scan.points)
        except Exception as e:  # per frame, never the clip's end
            target_error = f"{backend.name} could not prepare the reference scan: {e}"
        for o in others:
            if f not in pairs[o.agent]:
                continue
            fo = pairs[o.agent][f]
            T_init = initial_transform_at(ref.track, o.track, ref.T_ego_lidar, o.T_ego_lidar,
                                          ref.frames[f][1], o.frames[fo][1])
            oth_scan = oth_static[o.agent].filtered(fo, cfg.source_voxel_m)
            if target is None:
                res = failed_pair(T_init, target_error)
            else:
                try:
                    source = backend.prepare_points(oth_scan.points)
                    res = refine(backend, target, source, T_init, cfg.limits(),
                                 warm[o.agent] if cfg.warm_start else None)
                except Exception as e:
                    res = failed_pair(T_init, f"{backend.name} failed on the pair: "
                                              f"{type(e).__name__}: {e}")
            warm[o.agent] = res.correction if res.accepted else warm[o.agent]
            c_ref, c_oth = ref_scan.counts, oth_scan.counts
            for k in ("boxes", "bodies", "dynamic"):
                setattr(removed, k, getattr(removed, k) + getattr(c_ref, k) + getattr(c_oth, k))
            rows.append(_row(clip_id, ref_id, o.agent, f, ref.frames[f][0], res, method,
                             len(ref_scan.points), len(oth_scan.points), c_ref, c_oth))
            results.append(res)
            pair_s.append(time.perf_counter() - t0)
            t0 = time.perf_counter()  # the target's preparation is charged to the first pair
            if not res.accepted:
                log.warning("register %s frame %d %s->%s rejected: %s", clip_id, f, o.agent,
                            ref_id, res.reason)
            if cfg.write_bev and f == bev_frame and o is others[0]:
                key = lake.path("clean", "images", clip_id, "registration_bev.png")
                lake.write_bytes(key, render_registration_bev(
                    ref.points(f), o.points(fo), res.T_init, res.T_final,
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
        removed_boxes=float(removed.boxes), removed_bodies=float(removed.bodies),
        removed_dynamic=float(removed.dynamic),
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

    ref = AgentScans(lake, clip_id, r["agent_ref"], cfg.sensor)
    oth = AgentScans(lake, clip_id, r["agent_other"], cfg.sensor)
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
