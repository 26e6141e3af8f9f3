"""Register stage: cross-agent ``T_L1_L2`` per frame pair (main paper eq. 1a, refined by eq. 1b).

For every scan of the reference agent and the other agent's scan that started at the same
instant (PPS sync), the initial transform comes from the INS poses interpolated at each
deskewed scan's reference time and the LiDAR extrinsics (eq. 1a); GICP on the deskewed
scans refines it, warm-started from the previous frame's accepted correction. Quality and
the accept / reject decision are recorded per frame in clean ``registrations``; a
before/after bird's-eye view (Fig. 5) goes to ``clean/images/<clip>/registration_bev.png``.
This module is the package's only lake I/O (docs/architecture.md, Stage package shape): it
reads the agents, their scans (``read_agent_scans``: one frame at a time through the frame
index), bodies and annotations, hands arrays and records to the pure modules the package
docstring names, and writes ``registrations``, ``calibration_refined`` and the figures. The
readers behind the tools (the plots, ``frame_rows`` of ``v2xlake calibration --frames``) are
here for the same reason.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict, deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from v2xlake.schemas.arrow import rows_to_table
from v2xlake.schemas.errors import ClipError
from v2xlake.schemas.stage import OutputFile, Stage, StageReport, tables
from v2xlake.schemas.tables import CalibrationRefinedRow, RegistrationRow
from v2xlake.storage.frames import PointFrameIndex
from v2xlake.storage.lake import Lake
from v2xlake.storage.reader import (
    DESKEWED,
    lidar_frames,
    pose_missing,
    read,
    read_extrinsics,
)
from v2xlake.tasks.cores import available_cores
from v2xlake.tasks.geometry import invert, matrix_to_quat, rotation_angle, transform
from v2xlake.tasks.interpolate import PoseTrack
from v2xlake.tasks.reader import CalibrationComparison, compare_calibration, load_pose_track
from v2xlake.tasks.register.backends import Prepared, RegistrationBackend, make_backend
from v2xlake.tasks.register.bev import render_registration_bev
from v2xlake.tasks.register.calibration import frame_table
from v2xlake.tasks.register.config import RegisterConfig
from v2xlake.tasks.register.core import (
    PairResult,
    failed_pair,
    initial_transform,
    refine,
    transform_delta,
)
from v2xlake.tasks.register.intra_stage import IntraStageSettings, refine_secondaries, split_lidars
from v2xlake.tasks.register.scans import (
    AgentScans,
    AnnotationColumns,
    Body,
    StaticScans,
    boxes_per_frame,
    is_stationary,
)
from v2xlake.tasks.register.solve import (
    ClipSolution,
    CrossMeasurement,
    OdoMeasurement,
    chi2_isf,
    normal_sf,
    se3_exp,
    solve_clip,
)
from v2xlake.tasks.register.static import RemovalCounts
from v2xlake.tasks.register.timeline import render_registration_timeline

log = logging.getLogger(__name__)

STAGE = "register"
#: at most this many threads for the per-frame work when ``workers`` is 0 (auto): beyond
#: it the in-order cross-agent GICP on the calling thread is the bottleneck anyway
MAX_WORKERS = 8

__all__ = ["REGISTER", "CalibrationComparison", "compare_calibration", "frame_rows",
           "plot_registration", "plot_registration_timeline", "read_agent_scans",
           "refine_agent_lidars", "run_register"]


def _fail(clip_id: str, reason: str, agent_id: str | None = None) -> ClipError:
    return ClipError(clip_id, reason, agent_id=agent_id, stage=STAGE)


# ---------------------------------------------------------------- reading the lake
@dataclass(frozen=True)
class _AgentTables:
    """What every LiDAR of one agent reads from the lake, read once per agent: its pose track,
    extrinsics, ``lidar_frames`` and ``deskew_frames`` rows, the frame index of its deskewed
    points (one footer read per file) and its ``annotations``. WHY: the side-LiDAR
    refinement reads the primary's and each secondary's scans; per LiDAR these were
    read again (15 table reads and 2 index builds for a two-LiDAR agent, 7 and 1 now)."""

    clip_id: str
    agent: str
    track: PoseTrack
    extr: dict[str, np.ndarray]
    frames: pa.Table
    desk: pa.Table
    index: PointFrameIndex
    annotations: pa.Table


def _read_agent(lake: Lake, clip_id: str, agent: str,
                extr: dict[str, np.ndarray] | None = None) -> _AgentTables:
    """The agent's tables (``extr``: its extrinsics when the caller has read them)."""
    track: PoseTrack = load_pose_track(lake, clip_id, agent)
    extr = read_extrinsics(lake, clip_id, agent) if extr is None else extr
    if not extr:
        raise _fail(clip_id, "no LiDAR in calibrated_sensors", agent)
    return _AgentTables(
        clip_id, agent, track, extr,
        frames=lake.read_table("clean", "lidar_frames", clip_id=clip_id, agent_id=agent),
        desk=lake.read_table("clean", "deskew_frames", clip_id=clip_id, agent_id=agent),
        index=PointFrameIndex.build(lake, "clean", DESKEWED, clip_id, agent),
        annotations=lake.read_table("clean", "annotations", clip_id=clip_id, agent_id=agent))


def read_agent_scans(lake: Lake, clip_id: str, agent: str, sensor: str | None) -> AgentScans:
    """One agent's deskewed scans of one LiDAR (``sensor``; None: ``LIDAR_TOP``, else its
    first LiDAR): pose track, extrinsic, each deskewed frame's scan start and deskew
    reference time (``lidar_frames`` joined with ``deskew_frames``), its annotated boxes,
    and a reader of one frame's points (one row group, through the frame index)."""
    return _lidar_scans(_read_agent(lake, clip_id, agent), sensor)


def _lidar_scans(a: _AgentTables, sensor: str | None) -> AgentScans:
    """``read_agent_scans`` of one LiDAR from its agent's tables, read once."""
    clip_id, agent, extr = a.clip_id, a.agent, a.extr
    if sensor is None:
        sensor = "LIDAR_TOP" if "LIDAR_TOP" in extr else sorted(extr)[0]
    if sensor not in extr:
        raise _fail(clip_id, f"LiDAR {sensor} has no calibrated_sensors row", agent)
    if a.frames.num_rows and not a.desk.num_rows:
        raise _fail(clip_id, "no deskew_frames: run deskew first", agent)
    # frame_idx -> (scan start, deskew reference time); frames deskew skipped are left out
    times: dict[int, tuple[int, int]] = {}
    if (lf := lidar_frames(a.frames, a.desk).get(sensor)) is not None:
        times = {int(f): (int(t0), int(r)) for f, t0, r, ok in zip(
            lf.frame_idx, lf.t_start_ns, lf.ref_ns, lf.deskewed, strict=True) if ok}
    if not a.index:
        raise _fail(clip_id, f"no {DESKEWED} rows: run deskew first", agent)
    lidar = sensor
    index = a.index  # read from the register stage's threads: one open file set per thread

    def read_frame(frame_idx: int) -> tuple[np.ndarray, np.ndarray]:
        t = index.read(frame_idx, lidar, ["t_ns", "x", "y", "z"])
        if t is None:
            return np.zeros((0, 3), np.float32), np.zeros(0, np.int64)
        xyz = np.stack([t.column(c).to_numpy() for c in ("x", "y", "z")], axis=1)
        return xyz, np.asarray(t.column("t_ns").to_numpy(), dtype=np.int64)

    ann = _annotation_columns(a.annotations, sensor)
    boxes = boxes_per_frame(ann, times) if ann is not None else {}
    return AgentScans(agent, sensor, a.track, extr[sensor], times, read_frame, boxes)


def _annotation_columns(ann: pa.Table, sensor: str) -> AnnotationColumns | None:
    """The agent's clean ``annotations`` of one LiDAR as columns; None when it has none."""
    if ann.num_rows == 0:
        return None
    ann = ann.filter(pc.equal(ann["sensor"].cast(pa.string()), sensor))

    def col(name: str) -> np.ndarray:
        return np.asarray(ann[name].to_numpy(zero_copy_only=False), dtype=np.float64)

    fr = np.asarray(ann["frame_idx"].to_numpy(), dtype=np.int64)
    return AnnotationColumns(
        frame_idx=fr, t_ns=np.asarray(ann["t_ns"].to_numpy(), dtype=np.int64),
        center=np.stack([col("cx"), col("cy"), col("cz")], 1),
        size_wlh=np.stack([col("w"), col("l"), col("h")], 1),
        quat_wxyz=np.stack([col("qw"), col("qx"), col("qy"), col("qz")], 1),
        velocity=np.stack([col(k) if k in ann.column_names else np.full(len(fr), np.nan)
                           for k in ("vx", "vy", "vz")], 1))


def refine_agent_lidars(lake: Lake, clip_id: str, agent: str,
                        settings: IntraStageSettings | None = None,
                        T_ego_primary: np.ndarray | None = None
                        ) -> tuple[list[CalibrationRefinedRow], list[str]]:
    """``calibration_refined`` rows for every secondary LiDAR of ``agent`` (none when it has
    one LiDAR) and notes: its LiDARs' scans read here (the agent's tables once, shared by
    its LiDARs), refined by ``intra_stage.refine_secondaries``. ``T_ego_primary``: the
    primary's effective extrinsic (the stage's refined one when usable; default the
    published one)."""
    s = settings or IntraStageSettings()
    extr = read_extrinsics(lake, clip_id, agent)
    if not s.enabled or len(extr) < 2:
        return [], []
    primary, secondaries = split_lidars(list(extr), s.primary)
    tables_of_agent = _read_agent(lake, clip_id, agent, extr)
    P = _lidar_scans(tables_of_agent, primary)
    return refine_secondaries(clip_id, P, (_lidar_scans(tables_of_agent, sec)
                                           for sec in secondaries), s, T_ego_primary)


def frame_rows(lake: Lake, clip_id: str) -> list[dict[str, object]]:
    """``calibration.frame_table`` of the clip's stored ``registrations`` rows (what
    ``v2xlake calibration --frames`` prints)."""
    return frame_table(read(lake, "registrations", clip_id).to_pylist())


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


def _rotations(measured: list[_Pair], sol: ClipSolution | None) -> np.ndarray:
    """(N, 3, 4) quaternions of each pair's GICP measurement (identity where it has none),
    eq. 1a and final transform (:func:`_row`), converted in one call: the same numbers as
    one at a time (``matrix_to_quat`` works element by element), without its per-call cost
    (three a row: two thirds of the time the rows took)."""
    R = np.empty((len(measured), 3, 3, 3))
    for k, p in enumerate(measured):
        Z = p.measurement.Z
        R[k, 0] = Z[:3, :3] if p.measurement.usable and Z is not None else np.eye(3)
        R[k, 1] = p.res.T_init[:3, :3]
        R[k, 2] = (p.res.T_final if sol is None else sol.T_cross[k])[:3, :3]
    return np.asarray(matrix_to_quat(R))


def _row(clip_id: str, ref: str, p: _Pair, k: int, sol: ClipSolution | None,
         cfg: RegisterConfig, method: str, quats: np.ndarray) -> RegistrationRow:
    """The ``registrations`` row of pair ``k``; ``quats``: its row of :func:`_rotations`."""
    r = p.res
    meas = p.measurement
    extra: dict[str, Any] = {}
    if meas.usable and meas.Z is not None:
        qg = quats[0]
        extra.update(gicp_tx=meas.Z[0, 3], gicp_ty=meas.Z[1, 3], gicp_tz=meas.Z[2, 3],
                     gicp_qw=qg[0], gicp_qx=qg[1], gicp_qy=qg[2], gicp_qz=qg[3])
    if sol is None:  # frame by frame, the gate decides
        T_final, accepted, reason = r.T_final, r.accepted, r.reason
        if r.H is not None:
            extra["information"] = [float(x) for x in r.H.ravel()]
    else:
        T_final = sol.T_cross[k]
        cov = sol.cross_cov[k]
        std_m = float(np.sqrt(max(np.max(np.diag(cov)[3:]), 0.0)))
        std_deg = float(np.degrees(np.sqrt(max(np.max(np.diag(cov)[:3]), 0.0))))
        outlier = bool(sol.outlier[k])
        extra.update(weight=float(sol.weight[k]), outlier=outlier, std_m=std_m, std_deg=std_deg,
                     loo_chi2=None if np.isnan(sol.loo_chi2[k]) else float(sol.loo_chi2[k]))
        if sol.information is not None and np.isfinite(sol.information[k]).all():
            extra["information"] = [float(x) for x in sol.information[k].ravel()]
        if outlier:
            accepted, reason = False, (
                f"outlier: its GICP result disagrees with the clip solution of the other frames "
                f"(leave-one-out chi2 {sol.loo_chi2[k]:.0f} > {sol.loo_limit:.0f}); clip "
                "estimate kept, not exported")
        elif std_m > cfg.solve.final_max_std_m or std_deg > cfg.solve.final_max_std_deg:
            accepted, reason = False, (
                f"uncertain: clip estimate 1-sigma {std_m * 100:.1f} cm / {std_deg:.3f} deg > "
                f"{cfg.solve.final_max_std_m * 100:.1f} cm / {cfg.solve.final_max_std_deg} deg")
        elif k < len(sol.unbracketed) and sol.unbracketed[k]:
            accepted, reason = False, sol.unbracketed[k]
        elif not meas.usable:
            accepted, reason = True, f"clip estimate (no GICP measurement: {r.reason})"
        else:
            accepted, reason = True, "ok"
    qi, qf = quats[1], quats[2]
    ti, tf = r.T_init[:3, 3], T_final[:3, 3]
    dm, ddeg = transform_delta(r.T_init, T_final)
    return RegistrationRow(
        clip_id=clip_id, agent_ref=ref, agent_other=p.other, frame_idx=p.ref_frame,
        t_ns=p.t_ns, init_tx=ti[0], init_ty=ti[1], init_tz=ti[2], init_qw=qi[0], init_qx=qi[1],
        init_qy=qi[2], init_qz=qi[3], tx=tf[0], ty=tf[1], tz=tf[2], qw=qf[0], qx=qf[1],
        qy=qf[2], qz=qf[3], fitness=r.fitness, inlier_rmse=r.inlier_rmse, correction_m=dm,
        correction_deg=ddeg, accepted=accepted, method=method, reason=reason,
        n_points_ref=p.n_ref, n_points_other=p.n_oth,
        removed_boxes=p.c_ref.boxes + p.c_oth.boxes,
        removed_bodies=p.c_ref.bodies + p.c_oth.bodies,
        removed_dynamic=p.c_ref.dynamic + p.c_oth.dynamic,
        observability=None if np.isnan(r.observability) else float(r.observability), **extra)


def _fit_consistent(cfg: RegisterConfig, sol: ClipSolution, agent: str) -> bool:
    """The clip's fit explains its measurements (variance factor) and few of the agent's
    frames are outliers: the condition for trusting its extrinsic correction at all."""
    return sol.variance_factor <= cfg.calibration.max_variance_factor \
        and sol.outlier_fraction.get(agent, 0.0) <= cfg.calibration.max_outlier_fraction


def _calibration_rows(clip_id: str, sol: ClipSolution, agents: list[AgentScans],
                      cfg: RegisterConfig, n_frames: int, method: str,
                      notes: list[str] | None = None) -> list[CalibrationRefinedRow]:
    """The clip's extrinsic corrections, applied in the components it determined and only
    when significant; ``usable`` also needs a consistent fit and small enough 1-sigma (every
    component determined with ``calibration.require_all``); why not goes to ``notes``."""
    rows = []
    prior = np.array([np.radians(cfg.solve.prior_ext_deg)] * 3 + [cfg.solve.prior_ext_m] * 3)
    names = ("rx", "ry", "rz", "tx", "ty", "tz")
    for a in agents:
        eps, cov = sol.eps[a.agent], sol.eps_cov[a.agent]
        std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
        det = std < cfg.calibration.determined_fraction * prior
        applied = np.where(det, eps, 0.0)
        why: list[str] = []
        if det.any():  # significance of the correction over the determined components
            cd = cov[np.ix_(det, det)]
            m2 = float(applied[det] @ np.linalg.pinv(cd, hermitian=True) @ applied[det])
            q_lim = chi2_isf(2 * normal_sf(cfg.calibration.significance), int(det.sum()))
            if m2 < q_lim:
                applied = np.zeros(6)
                why.append(f"correction not significant (chi2 {m2:.1f} < {q_lim:.1f}): published "
                           "kept")
        if not det.all():
            why.append("not determined (published kept): "
                       + " ".join(n for n, d in zip(names, det, strict=True) if not d))
        consistent = _fit_consistent(cfg, sol, a.agent)
        if not consistent:
            why.append(f"fit inconsistent (variance factor {sol.variance_factor:.2f}, outliers "
                       f"{sol.outlier_fraction.get(a.agent, 0.0):.0%})")
        T = a.T_ego_lidar @ se3_exp(applied)
        q, qp = matrix_to_quat(T[:3, :3]), matrix_to_quat(a.T_ego_lidar[:3, :3])
        std_m = float(std[3:][det[3:]].max()) if det[3:].any() else 0.0
        std_deg = float(np.degrees(std[:3][det[:3]].max())) if det[:3].any() else 0.0
        dm, ddeg = transform_delta(a.T_ego_lidar, T)
        rows.append(CalibrationRefinedRow(
            clip_id=clip_id, agent_id=a.agent, sensor=a.sensor, tx=T[0, 3], ty=T[1, 3],
            tz=T[2, 3], qw=q[0], qx=q[1], qy=q[2], qz=q[3], pub_tx=a.T_ego_lidar[0, 3],
            pub_ty=a.T_ego_lidar[1, 3], pub_tz=a.T_ego_lidar[2, 3], pub_qw=qp[0], pub_qx=qp[1],
            pub_qy=qp[2], pub_qz=qp[3], correction_m=dm, correction_deg=ddeg,
            cov=[float(x) for x in cov.ravel()], std_m=std_m, std_deg=std_deg,
            refined_components=" ".join(n for n, d in zip(names, det, strict=True) if d),
            usable=bool(det.any() and std_m <= cfg.calibration.max_std_m
                        and std_deg <= cfg.calibration.max_std_deg and consistent
                        and (det.all() or not cfg.calibration.require_all)),
            n_frames=n_frames, source="refined", method=method,
            reason="; ".join(why) or None))
        if notes is not None and why:
            notes.append(f"calibration {a.agent}: " + "; ".join(why))
    return rows


def _redeskew_extrinsics(cfg: RegisterConfig, agents: list[AgentScans], sol: ClipSolution,
                         rows: list[CalibrationRefinedRow]) -> dict[str, tuple[np.ndarray, str]]:
    """Agents whose scans should be deskewed again, with the extrinsic to use and why.

    Deskew depends on the extrinsic's rotation (it turns the ego motion into the LiDAR frame),
    hardly on its translation, so a rotation the clip determined is enough even where the
    translation is not (the undetermined components keep the published value, as in the
    refined row). Only when the predicted smear is worth a second pass: rotation correction
    times the agent's largest travel during one scan at least ``redeskew_min_shift_m``."""
    out: dict[str, tuple[np.ndarray, str]] = {}
    for a, c in zip(agents, rows, strict=True):
        if not {"rx", "ry", "rz"} <= set(c.refined_components.split()) \
                or c.std_deg > cfg.calibration.max_std_deg or c.correction_deg <= 0:
            continue
        if not _fit_consistent(cfg, sol, a.agent):
            continue
        shift = np.radians(c.correction_deg) * a.max_travel_per_scan()
        if shift >= cfg.redeskew.min_shift_m:
            out[a.agent] = (_matrix(c, ""), f"{c.correction_deg:.2f} deg: up to "
                            f"{shift * 100:.1f} cm across a scan")
    return out


def detect_ins_steps(track: PoseTrack, threshold_m: float) -> list[tuple[int, np.ndarray]]:
    """Discontinuities of a pose track: (time of the later sample, step vector) where a
    displacement between consecutive samples differs from the mean of its two neighbours
    (each scaled to this interval's duration) by more than ``threshold_m``. A smooth track
    (any acceleration at INS rates) stays far below centimetres; a position reset
    (RTK fix, a re-initialised filter) is a step of decimetres in one interval."""
    t = track.t_ns.astype(np.float64)
    p = track.xyz
    if len(t) < 4:
        return []
    dt = np.diff(t)
    v = np.diff(p, axis=0) / dt[:, None]  # per-interval mean velocity
    pred = 0.5 * (v[:-2] + v[2:]) * dt[1:-1, None]
    r = np.diff(p, axis=0)[1:-1] - pred
    n = np.linalg.norm(r, axis=1)
    out = []
    for i in np.flatnonzero(n > threshold_m):
        # a step leaves half of itself (opposite) in each neighbour's residual: keep maxima
        if n[i] >= n[max(i - 1, 0)] and n[i] >= n[min(i + 1, len(n) - 1)]:
            out.append((int(track.t_ns[i + 2]), r[i].copy()))
    return out


def _bodies(lake: Lake, clip_id: str, agents: list[AgentScans], cfg: RegisterConfig
            ) -> dict[str, Body]:
    """Declared footprints of the agents (clean ``agents``: length, width, height and the box
    centre in the ego frame); agents without one are not removed from the others' scans."""
    t = lake.read_table("clean", "agents", clip_id=clip_id)
    out: dict[str, Body] = {}
    if not cfg.static.enabled or t.num_rows == 0 or "length_m" not in t.column_names:
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


@dataclass
class _Pair:
    """One cross-agent frame pair as measured (before the clip solve)."""

    ref_frame: int
    other: str
    other_frame: int
    t_ns: int  # the reference scan's start
    res: PairResult
    n_ref: int
    n_oth: int
    c_ref: RemovalCounts
    c_oth: RemovalCounts
    measurement: CrossMeasurement


#: the clip's small input tables the stage's helpers each read again (which agents have a
#: pose, the tracks, the extrinsics, the bodies): read once per run (``Lake.reading_once``;
#: 36 -> 26 table reads, ~10 ms, on a three-agent clip)
_READ_ONCE = ("agents", "clips", "ego_poses", "calibrated_sensors")


def run_register(lake: Lake, clip_id: str, config: RegisterConfig | None = None) -> StageReport:
    """Register every other agent's deskewed scans to the reference agent's: per-frame GICP
    on the static scene as measurements, fused by the clip-level solve (see the module doc)."""
    with lake.reading_once("clean", _READ_ONCE):
        return _run_register(lake, clip_id, config)


def _run_register(lake: Lake, clip_id: str, config: RegisterConfig | None) -> StageReport:
    cfg = config or RegisterConfig()
    wall0 = time.perf_counter()
    report = StageReport(stage=STAGE, clip_id=clip_id)
    ref_id, other_ids = _reference_agent(lake, clip_id)
    lake.delete_partition("clean", "registrations", clip_id)
    lake.delete_partition("clean", "calibration_refined", clip_id)
    missing = {a: why for a in (ref_id, *other_ids) if (why := pose_missing(lake, clip_id, a))}
    if not other_ids and ref_id not in missing and cfg.intra.enabled \
            and len(read_extrinsics(lake, clip_id, ref_id)) > 1:
        report.notes.append(f"single agent ({ref_id}): its LiDARs registered to each other only")
        _write_calibration(lake, clip_id, cfg, [ref_id], [], report)
        return report
    if ref_id in missing or len(missing) == len(other_ids):
        return StageReport.not_applicable(
            STAGE, clip_id, "registration needs the reference agent and at least one other "
            "agent with a pose track" + (f" ({'; '.join(f'{a}: {w}' for a, w in missing.items())})"
                                         if missing else f"; the clip has {1 + len(other_ids)} "
                                         "agent(s)"))
    other_ids = [a for a in other_ids if a not in missing]
    if not other_ids:
        report.notes.append(f"single agent ({ref_id}): nothing to register")
        _write_calibration(lake, clip_id, cfg, [ref_id], [], report)
        return report
    ref = read_agent_scans(lake, clip_id, ref_id, cfg.sensor)
    others = [read_agent_scans(lake, clip_id, a, cfg.sensor) for a in other_ids]
    backend: RegistrationBackend = make_backend(cfg.gicp.backend, cfg.gicp)
    method = f"{cfg.gicp.backend}:GICP" + ("+clip" if cfg.solve.enabled else "")
    pairs = {o.agent: dict(_pairs(ref, o, cfg.pair_tolerance_ns)) for o in others}
    ref_frames = sorted({f for p in pairs.values() for f in p})
    if not ref_frames:
        raise _fail(clip_id, "no frame pairs: no scans of the other agents start within "
                             f"{cfg.pair_tolerance_ns} ns of the reference agent's scans")
    t0_ns = ref.frames[ref_frames[0]][1]
    bodies = _bodies(lake, clip_id, [ref, *others], cfg)
    measured, odo, timing = _measure(cfg, backend, ref, others, pairs, ref_frames, bodies,
                                     t0_ns)
    ground = {a: (float(np.nanmedian(h)), b.center_ego[2] - b.height / 2)
              for a, b in bodies.items()
              if (h := [x for x in timing["ground"].get(a, []) if np.isfinite(x)])}
    sol: ClipSolution | None = None  # the relative transforms, frame by frame
    ext: ClipSolution | None = None  # the extrinsic split (with odometry and priors)
    agents = [ref, *others]
    steps: list[tuple[str, float]] = []
    if cfg.solve.enabled:
        for sc in agents:
            for t_ns, d in detect_ins_steps(sc.track, cfg.solve.ins_step_m):
                steps.append((sc.agent, (t_ns - t0_ns) * 1e-9))
                report.notes.append(
                    f"INS step of {sc.agent} at {(t_ns - t0_ns) * 1e-9:.2f} s: "
                    f"{np.linalg.norm(d) * 100:.1f} cm ({d[0]:+.3f}, {d[1]:+.3f}, {d[2]:+.3f} m); "
                    "modelled as a free offset of its INS error from there on")
        t_solve = time.perf_counter()
        sol, ext = _solve(cfg, agents, measured, odo, ground, steps)
        timing["solve_s"] = time.perf_counter() - t_solve
        fix = _redeskew_extrinsics(cfg, agents, ext, _calibration_rows(
            clip_id, ext, agents, cfg, len(measured), method)) if cfg.redeskew.enabled else {}
        if fix:
            # the scans of an agent whose extrinsic was wrong were deskewed with it: deskew
            # them again with the refined one and measure and solve once more
            report.notes.append("re-deskewed with the refined extrinsic: " + ", ".join(
                f"{a} ({why})" for a, (_, why) in sorted(fix.items())))
            t_solve = time.perf_counter()
            measured, odo, timing = _measure(cfg, backend, ref, others, pairs, ref_frames,
                                             bodies, t0_ns,
                                             {a: T for a, (T, _) in fix.items()})
            sol, ext = _solve(cfg, agents, measured, odo, ground, steps)
            timing["solve_s"] = time.perf_counter() - t_solve
    quats = _rotations(measured, sol)
    rows = [_row(clip_id, ref_id, p, k, sol, cfg, method, quats[k])
             for k, p in enumerate(measured)]
    path, n = lake.write_table("clean", "registrations", rows_to_table(RegistrationRow, rows),
                               clip_id=clip_id, name="registrations")
    report.outputs.append(OutputFile(path=path, rows=n))
    cal: list[CalibrationRefinedRow] = []
    if ext is not None:
        cal = _calibration_rows(clip_id, ext, [ref, *others], cfg, len(measured), method,
                                report.notes)
    _write_calibration(lake, clip_id, cfg, [ref_id, *other_ids], cal, report)
    bev_frame = cfg.bev_frame if cfg.bev_frame is not None else ref_frames[len(ref_frames) // 2]
    if cfg.write_bev:
        for p, r in zip(measured, rows, strict=True):
            if p.ref_frame == bev_frame and p.other == others[0].agent:
                key = lake.path("clean", "images", clip_id, "registration_bev.png")
                o = next(a for a in others if a.agent == p.other)
                lake.write_bytes(key, render_registration_bev(
                    ref.points(p.ref_frame), o.points(p.other_frame), p.res.T_init,
                    _matrix(r, ""), title=f"{clip_id} frame {p.ref_frame}: {p.other} -> "
                    f"{ref_id} ({r.reason[:60]})"))
                report.images.append(key)
                break
    if cfg.write_bev:
        key = lake.path("clean", "images", clip_id, "registration_timeline.png")
        lake.write_bytes(key, render_registration_timeline(
            [r.model_dump() for r in rows], [c.model_dump() for c in cal] if ext else [],
            title=f"{clip_id}: registration against {ref_id} ({method})"))
        report.images.append(key)
    acc = [r for r in rows if r.accepted]
    res = [p.res for p in measured]
    removed = RemovalCounts()
    for p in measured:
        for k in ("boxes", "bodies", "dynamic"):
            setattr(removed, k, getattr(removed, k) + getattr(p.c_ref, k) + getattr(p.c_oth, k))
    n_frames = max(len(measured), 1)
    report.metrics.update(
        n_pairs=float(len(rows)), n_accepted=float(len(acc)),
        n_rejected=float(len(rows) - len(acc)),
        n_outliers=float(sum(bool(r.outlier) for r in rows)),
        mean_fitness=float(np.mean([r.fitness for r in res])) if res else 0.0,
        mean_correction_m=float(np.mean([r.correction_m for r in acc])) if acc else 0.0,
        mean_correction_deg=float(np.mean([r.correction_deg for r in acc])) if acc else 0.0,
        median_pair_s=float(np.median(timing["pair_s"])) if timing["pair_s"] else 0.0,
        gicp_s_per_frame=float(timing["gicp_s"]) / n_frames,
        read_s_per_frame=float(timing["read_s"]) / n_frames,
        voxel_s_per_frame=float(timing["voxel_s"]) / n_frames,
        filter_s_per_frame=float(timing["filter_s"]) / n_frames,
        odometry_s_per_frame=float(timing["odometry_s"]) / n_frames,
        prepare_s_per_frame=float(timing["prepare_s"]) / n_frames,
        solve_s_per_frame=float(timing.get("solve_s", 0.0)) / n_frames,
        removed_boxes=float(removed.boxes), removed_bodies=float(removed.bodies),
        removed_dynamic=float(removed.dynamic),
        n_odometry=float(len(odo)),
        variance_factor=float(sol.variance_factor) if sol is not None else 0.0,
        seconds=time.perf_counter() - wall0,
    )
    if ext is not None:
        for a in ext.agents:
            e = ext.eps[a]
            report.metrics[f"extrinsic_correction_m_{a}"] = float(np.linalg.norm(e[3:]))
            report.metrics[f"extrinsic_correction_deg_{a}"] = float(np.degrees(
                np.linalg.norm(e[:3])))
    for r in rows:
        if not r.accepted:
            report.notes.append(f"frame {r.frame_idx} {r.agent_other}: {r.reason}")
            log.warning("register %s frame %d %s->%s not accepted: %s", clip_id, r.frame_idx,
                        r.agent_other, ref_id, r.reason)
    return report


def _stationary(cfg: RegisterConfig, agents: list[AgentScans]) -> set[str]:
    """The agents that do not move during the clip (``cfg.stationary``)."""
    return {a.agent for a in agents if is_stationary(
        a.track.xyz, a.track.quat_wxyz, cfg.stationary.max_motion_m,
        cfg.stationary.max_rotation_deg)}


def _solve(cfg: RegisterConfig, agents: list[AgentScans], measured: list[_Pair],
           odo: list[OdoMeasurement], ground: dict[str, tuple[float, float]],
           steps: list[tuple[str, float]]) -> tuple[ClipSolution, ClipSolution]:
    """The two solves of a clip: (relative, extrinsic).

    The relative transform between two LiDARs is what the cross-agent GICP measures, frame
    by frame; the split of a correction into "extrinsic" and "INS error" is not (driving
    straight, a wrong extrinsic translation and a constant INS offset are the same
    measurement). So the per-frame estimates come from a solve of the cross-agent frames
    alone (the same model, robust weights, leave-one-out test, honest covariance and
    bracketing), which the split's extra information -- hand-eye odometry, the
    non-holonomic and ground constraints -- cannot pull away from what the frames measured:
    a bias in any of those (a corridor's odometry sliding along the street, a declared body
    height that is off) would otherwise move every frame's estimate with it. The full solve
    with that information estimates the extrinsic corrections (``calibration_refined``)."""
    names = [a.agent for a in agents]
    extr = {a.agent: a.T_ego_lidar for a in agents}
    cross = [p.measurement for p in measured]
    still = _stationary(cfg, agents)
    ext = solve_clip(names, agents[0].agent, extr, cross, odo, cfg.solve, ground,
                     steps, still)
    if not cfg.solve.relative or (not odo and not ground):
        return ext, ext
    rel = solve_clip(names, agents[0].agent, extr, cross, [], cfg.solve, None,
                     steps, still)
    return rel, ext


@dataclass
class _Scan:
    """One agent's frame as the frame loop uses it: its static-scene voxels, and the whole
    cloud prepared when the agent's odometry uses this frame."""

    agent: str
    frame: int
    points: np.ndarray
    counts: RemovalCounts
    ground_m: float
    odometry: bool
    whole: Prepared | None
    # prepared whole, shared by its co-visible clouds (grid and surfaces computed once):
    # ``whole``, or prepared for that when several agents register against the scan
    base: Prepared | None = None
    # ``base`` with a surface store of its own for the far pairs' number of neighbours
    # (``gicp.far_pair_num_neighbors``), filled only where a far pair uses the scan
    far_base: Prepared | None = None


@dataclass
class _CrossWork:
    """One cross pair of a frame, prepared: what its GICP needs."""

    other: AgentScans
    other_frame: int
    T_init: np.ndarray
    scan: _Scan
    target: Prepared | None
    source: Prepared | None
    why: str
    # the two LiDARs farther apart than ``gicp.far_pair_beyond_m``, or a stationary agent
    # in the pair (``stationary.far_pair_surfaces``): aligned by the far pairs' backend
    # (``gicp.far_pair_num_neighbors``)
    far: bool = False
    # a stationary agent in the pair (``register.stationary``): its surfaces and its
    # correspondences' direction (``gicp.far_pair_denser_side``) follow from it
    still: bool = False


def register_workers(cfg: RegisterConfig) -> int:
    """Threads for the per-frame work: ``cfg.workers``, or (0) the cores this process may
    use (its affinity mask: a Dask worker pinned to its share), at most ``MAX_WORKERS``."""
    if cfg.workers > 0:
        return cfg.workers
    return max(1, min(available_cores(), MAX_WORKERS))


def _measure(cfg: RegisterConfig, backend: RegistrationBackend, ref: AgentScans,
             others: list[AgentScans], pairs: dict[str, dict[int, int]], ref_frames: list[int],
             bodies: dict[str, Body], t0_ns: int,
             redeskew_with: dict[str, np.ndarray] | None = None
             ) -> tuple[list[_Pair], list[OdoMeasurement], dict[str, Any]]:
    """Per-frame GICP of every pair on the static scene, and the agents' own scan-to-scan
    GICP (odometry, every ``odometry.every`` frames over ``odometry.gap`` frames).

    With several workers (:func:`register_workers`) each frame's reading, static-scene
    filtering and cloud preparation run on a thread pool a few frames ahead, as do the
    odometry GICP calls (independent of each other); the cross-agent GICP runs on this
    thread in frame order, since each frame starts from the previous frame's accepted
    correction. Every computation is the one the serial loop does on the same inputs, so
    the results do not depend on the number of workers. The numeric kernels release the
    GIL (numba ``nogil``); small_gicp does not, so that backend gains little."""
    static = cfg.static
    workers = register_workers(cfg)
    scans = {a.agent: a for a in (ref, *others)}
    filt = {a.agent: StaticScans(a, static, [(b, bodies[b.agent]) for b in (ref, *others)
                                             if b is not a and b.agent in bodies],
                                 (redeskew_with or {}).get(a.agent),
                                 cfg.gicp.range_m(a is ref), in_flight=workers)
            for a in (ref, *others)}
    limits = cfg.quality.gated(not cfg.solve.enabled)
    # a far cross pair's surfaces from their own number of neighbours, in a second surface
    # store per scan (near pairs and odometry compute exactly what they do without it)
    far_params = cfg.gicp.far_pair()
    far_backend = (make_backend(cfg.gicp.backend, far_params) if far_params is not None
                   else None)
    own_surfaces = getattr(far_backend, "own_surfaces", None)

    def with_far(s: _Scan) -> _Scan:
        """``s`` with its far pairs' surface store beside ``s.base`` (before the scan is
        shared between frames or threads). The reference agent's scans, the target of near
        and far pairs alike, share the two stores' neighbour searches; another agent's
        scan is the source of one pair, so its stores hardly meet and keeping its
        searches would cost more than it saves."""
        if own_surfaces is not None and s.base is not None and s.far_base is None:
            s.far_base = own_surfaces(s.base, share=s.agent == ref.agent)
        return s

    # recent prepared clouds per agent, for odometry: frame -> Prepared
    recent: dict[str, dict[int, Prepared]] = {a: {} for a in scans}
    odo_frames = {a: {g: i for i, g in enumerate(sorted(sc.frames))} for a, sc in scans.items()}
    odo_work: list[tuple[str, int, int, np.ndarray, np.ndarray, Future[PairResult] | PairResult]
                   ] = []
    warm: dict[str, np.ndarray | None] = {o.agent: None for o in others}
    # whether the agent's previous cross pair found too few sample correspondences
    short: dict[str, bool] = {o.agent: False for o in others}
    out: list[_Pair] = []
    timing: dict[str, Any] = {"pair_s": [], "gicp_s": 0.0, "filter_s": 0.0, "odometry_s": 0.0,
                              "prepare_s": 0.0,
                              "ground": {a: [] for a in scans}}
    lock = threading.Lock()

    def spent(key: str, seconds: float) -> None:
        with lock:
            timing[key] += seconds

    def secs(agent: str, f: int) -> float:
        return (scans[agent].frames[f][1] - t0_ns) * 1e-9

    def M(agent: str, f: int) -> np.ndarray:
        a = scans[agent]
        return a.world_ego(a.frames[f][1])[0]

    def prepare(points: np.ndarray, other_origin: np.ndarray | None = None,
                base: Prepared | None = None, as_target: bool = False,
                b: RegistrationBackend = backend) -> tuple[Prepared | None, str]:
        """The scan prepared for GICP (by ``b``); with ``other_origin`` only what the LiDAR
        there sees from the same side (:mod:`covisible`; the whole scan where too little
        would remain), sharing what ``base`` (the same points prepared whole) computed."""
        t = time.perf_counter()
        try:
            if other_origin is None:
                return b.prepare_points(points), ""
            return b.prepare_covisible(points, other_origin, cfg.quality.min_inliers,
                                       base, as_target=as_target), ""
        except Exception as e:  # per frame, never the clip's end
            return None, f"{b.name} could not prepare the scan: {e}"
        finally:
            spent("gicp_s" if other_origin is None else "prepare_s", time.perf_counter() - t)

    def uses_odometry(agent: str, f: int) -> bool:
        frames = odo_frames[agent]
        if cfg.odometry.every <= 0 or f not in frames:
            return False
        i = frames[f]
        return i % cfg.odometry.every == 0 or (i - cfg.odometry.gap) % cfg.odometry.every == 0

    def own_scan(agent: str, f: int, voxel: float) -> _Scan:
        """The frame's static-scene voxels; prepared whole only when the agent's odometry
        uses this frame, since a cross pair prepares its co-visible part."""
        sc = filt[agent].filtered(f, voxel)
        odo_f = uses_odometry(agent, f)
        whole = prepare(sc.points)[0] if odo_f else None
        return with_far(_Scan(agent, f, sc.points, sc.counts, sc.ground_m, odo_f, whole,
                              whole))

    # a stationary agent's scans (cfg.stationary): one of every ``reuse_frames`` frames is
    # read and prepared, with its grid and lazily filled surfaces, and stands for the frames
    # after it up to the next; frame -> its anchor frame is fixed, so the results do not
    # depend on the number of workers or the order the frames are prepared in
    still = _stationary(cfg, [ref, *others])
    reuse = {a: cfg.stationary.reuse_frames for a in still if cfg.stationary.reuse_frames > 1}
    ordered = {a: sorted(scans[a].frames) for a in reuse}
    # a stationary agent's scan takes the surfaces of its previous one where they cannot
    # differ (sparse.Predecessor: the same results, fewer searches)
    follow = getattr(backend, "follow", None) if cfg.stationary.inherit_surfaces else None
    held: dict[str, OrderedDict[tuple[int, float], _Scan]] = {a: OrderedDict() for a in reuse}
    held_lock = {a: threading.Lock() for a in reuse}

    def scan(agent: str, f: int, voxel: float) -> _Scan:
        """The frame's scan as GICP uses it (:func:`own_scan`; a stationary agent's frame
        between two of its anchors: the anchor's, prepared once, and not an odometry frame:
        its ground height is not measured again)."""
        if agent not in reuse or f not in odo_frames[agent]:
            return own_scan(agent, f, voxel)
        i = odo_frames[agent][f]
        anchor = ordered[agent][i - i % reuse[agent]]
        if anchor != f and uses_odometry(agent, f):
            return own_scan(agent, f, voxel)
        with held_lock[agent]:
            s = held[agent].get((anchor, voxel))
            if s is None:
                s = own_scan(agent, anchor, voxel)
                if s.base is None:  # shared by the frames it stands for
                    s.base = prepare(s.points)[0]
                    with_far(s)
                j = i - i % reuse[agent] - reuse[agent]
                before = held[agent].get((ordered[agent][j], voxel)) if j >= 0 else None
                if follow is not None and before is not None:
                    follow([(s.base, before.base), (s.far_base, before.far_base)])
                held[agent][(anchor, voxel)] = s
                while len(held[agent]) > 2 + 2 * workers:
                    _, gone = held[agent].popitem(last=False)
                    if follow is not None:  # the chain of scans ends with the held ones
                        follow([(gone.base, None), (gone.far_base, None)])
        if anchor == f:
            return s
        return replace(s, frame=f, ground_m=float("nan"), odometry=False, whole=None)

    def cross_cloud(s: _Scan, other_origin: np.ndarray, as_target: bool, far: bool = False
                    ) -> tuple[Prepared | None, str]:
        """The cloud a cross pair registers: with ``covisible`` only what the other LiDAR
        sees from the same side (:mod:`covisible`; the whole scan where too little would
        remain), else the whole scan (prepared once, shared with odometry). ``far``: by
        the far pairs' backend, on the scan's second surface store."""
        if far and far_backend is not None:
            if not cfg.covisible:
                return (s.far_base, "") if s.far_base is not None else prepare(
                    s.points, b=far_backend)
            return prepare(s.points, other_origin, s.far_base, as_target, far_backend)
        if not cfg.covisible:
            return (s.whole, "") if s.whole is not None else prepare(s.points)
        return prepare(s.points, other_origin, s.base, as_target)

    def frame_work(f: int) -> tuple[_Scan, list[_CrossWork]]:
        """Everything of reference frame ``f`` that does not depend on earlier frames."""
        ref_scan = scan(ref.agent, f, cfg.gicp.voxel_m)
        if ref_scan.base is None and cfg.covisible \
                and sum(f in pairs[o.agent] for o in others) > 1:
            ref_scan.base = prepare(ref_scan.points)[0]
            with_far(ref_scan)
        work = []
        for o in others:
            if f not in pairs[o.agent]:
                continue
            fo = pairs[o.agent][f]
            # eq. 1a as initial_transform_at computes it, from the poses already interpolated
            T_init = initial_transform(ref.world_ego(ref.frames[f][1])[0],
                                       o.world_ego(o.frames[fo][1])[0], ref.T_ego_lidar,
                                       o.T_ego_lidar)
            oth = scan(o.agent, fo, cfg.gicp.source_voxel_m)
            standing = o.agent in still or ref.agent in still
            far = far_backend is not None and (
                float(np.linalg.norm(T_init[:3, 3])) > cfg.gicp.far_pair_beyond_m
                or (cfg.stationary.far_pair_surfaces and standing))
            target, why_t = cross_cloud(ref_scan, T_init[:3, 3], True, far)
            source, why_s = cross_cloud(oth, invert(T_init)[:3, 3], False, far)
            work.append(_CrossWork(o, fo, T_init, oth, target, source, why_t or why_s, far,
                                   standing))
        return ref_scan, work

    def odometry_gicp(g: Prepared, f: Prepared, T_ins: np.ndarray) -> PairResult:
        t = time.perf_counter()
        try:
            return refine(backend, g, f, T_ins, cfg.quality.gated(False))
        finally:
            spent("odometry_s", time.perf_counter() - t)

    def keep(s: _Scan, pool: ThreadPoolExecutor | None) -> None:
        """In frame order: the scan's ground height, and its odometry pair (GICP on the
        pool) when this frame closes one."""
        timing["ground"][s.agent].append(s.ground_m)
        if not s.odometry or s.whole is None:
            return
        agent, f = s.agent, s.frame
        recent[agent][f] = s.whole
        for old in [g for g in recent[agent] if g < f - cfg.odometry.gap]:
            del recent[agent][old]
        a = scans[agent]
        frames = sorted(a.frames)
        i = odo_frames[agent][f]
        if i < cfg.odometry.gap:
            return
        g = frames[i - cfg.odometry.gap]
        if g not in recent[agent] or (i - cfg.odometry.gap) % cfg.odometry.every:
            return
        M0, M1 = M(agent, g), M(agent, f)
        T_ins = invert(M0 @ a.T_ego_lidar) @ (M1 @ a.T_ego_lidar)
        # driving straight, a pair says less (no rotation to separate extrinsic from INS)
        straight = np.degrees(rotation_angle(T_ins)) < cfg.solve.straight_deg
        if straight and (i - cfg.odometry.gap) % max(cfg.odometry.straight_every,
                                                     cfg.odometry.every):
            return
        args = (recent[agent][g], recent[agent][f], T_ins)
        odo_work.append((agent, g, f, M0, M1, pool.submit(odometry_gicp, *args)
                         if pool is not None else odometry_gicp(*args)))

    def cross_gicp(w: _CrossWork, start: np.ndarray | None, dense: bool) -> PairResult:
        """One cross pair's GICP from ``start`` (the agent's previous accepted correction);
        ``dense``: every co-visible source centroid at once (the previous frame's sample was
        short, ``gicp.dense_after_short_sample``)."""
        t = time.perf_counter()
        try:
            if w.target is None or w.source is None:
                return failed_pair(w.T_init, w.why)
            source = replace(w.source, dense_first=True) if dense else w.source
            side = cfg.gicp.far_pair_denser_side
            if (side == "far" and w.far) or (side != "off" and w.still):
                source = replace(source, denser_side=True)
            if w.other.agent in still:
                source = replace(source, translation_eps_m=cfg.stationary.translation_eps_m,
                                 max_iterations=cfg.stationary.max_iterations,
                                 dense_cell_m=cfg.stationary.dense_cell_m)
            return refine(far_backend if w.far and far_backend is not None else backend,
                          w.target, source, w.T_init, limits, start)
        finally:
            spent("gicp_s", time.perf_counter() - t)

    def register_frame(f: int, ref_scan: _Scan, work: list[_CrossWork],
                       pool: ThreadPoolExecutor | None, cross_pool: ThreadPoolExecutor | None,
                       t0: float) -> None:
        """In frame order: the frame's cross pairs, each warm-started from the previous
        frame's accepted correction of the same agent. The pairs of different agents do not
        depend on each other: with ``cross_pool`` all but the first run there while the first
        runs here (a roadside unit's pairs beside the other vehicle's)."""
        keep(ref_scan, pool)
        for w in work:
            keep(w.scan, pool)
        starts = [warm[w.other.agent] if cfg.gicp.warm_start else None for w in work]
        dense = [short[w.other.agent] for w in work]
        jobs: list[Future[PairResult] | None] = [
            cross_pool.submit(cross_gicp, w, st, d) if cross_pool is not None and i > 0
            else None for i, (w, st, d) in enumerate(zip(work, starts, dense, strict=True))]
        for w, st, d, job in zip(work, starts, dense, jobs, strict=True):
            o, fo = w.other, w.other_frame
            res = cross_gicp(w, st, d) if job is None else job.result()
            if w.target is not None and w.source is not None:
                short[o.agent] = res.sample_short and (
                    cfg.gicp.dense_after_short_sample
                    or (o.agent in reuse and cfg.stationary.dense_after_short_sample))
            if res.accepted and (res.observability >= cfg.quality.min_observability or (
                    o.agent in still and cfg.stationary.warm_any_observability)):
                warm[o.agent] = res.correction
            usable = res.accepted and res.H is not None and bool(np.isfinite(res.H).all())
            meas = CrossMeasurement(f, o.agent, secs(ref.agent, f), M(ref.agent, f),
                                    M(o.agent, fo), res.T_refined if usable else None,
                                    res.H if usable else None, secs(o.agent, fo))
            out.append(_Pair(f, o.agent, fo, ref.frames[f][0], res, len(ref_scan.points),
                             len(w.scan.points), ref_scan.counts, w.scan.counts, meas))
            timing["pair_s"].append(time.perf_counter() - t0)
            t0 = time.perf_counter()  # the target's preparation is charged to the first pair

    if workers <= 1:
        for f in ref_frames:
            t0 = time.perf_counter()
            register_frame(f, *frame_work(f), None, None, t0)
    else:
        with ThreadPoolExecutor(max_workers=workers,
                                thread_name_prefix=f"register-{ref.agent}") as pool, \
                ThreadPoolExecutor(max_workers=max(len(others) - 1, 1),
                                   thread_name_prefix=f"register-cross-{ref.agent}") as cross:
            ahead: deque[Future[tuple[_Scan, list[_CrossWork]]]] = deque()
            frames = iter(ref_frames)
            for f in ref_frames:
                while len(ahead) < 2 * workers and (nxt := next(frames, None)) is not None:
                    ahead.append(pool.submit(frame_work, nxt))
                t0 = time.perf_counter()
                register_frame(f, *ahead.popleft().result(), pool,
                               cross if len(others) > 1 else None, t0)
    odo: list[OdoMeasurement] = []
    for agent, g, f, M0, M1, job in odo_work:
        r = job.result() if isinstance(job, Future) else job
        if r.accepted and r.H is not None and np.isfinite(r.H).all():
            odo.append(OdoMeasurement(agent, secs(agent, g), secs(agent, f), M0, M1,
                                      r.T_refined, r.H))
    for k in ("read", "voxel", "filter"):
        timing[f"{k}_s"] = sum(f.seconds[k] for f in filt.values())
    return out, odo, timing


def _write_calibration(lake: Lake, clip_id: str, cfg: RegisterConfig, agents: list[str],
                 cal: list[CalibrationRefinedRow], report: StageReport) -> None:
    """Write ``calibration_refined``: the clip solve's rows (``cal``) plus, for every agent
    with several LiDARs, its secondary LiDARs refined against its primary (issue #27), on top
    of the primary's refined extrinsic where that one is usable."""
    rows = list(cal)
    if cfg.intra.enabled:
        st = IntraStageSettings(frames=cfg.intra.frames)
        for a in agents:
            prim = next((_matrix(c, "") for c in cal if c.agent_id == a and c.usable), None)
            extra, notes = refine_agent_lidars(lake, clip_id, a, st, prim)
            solved = {c.sensor for c in cal if c.agent_id == a}
            rows += [r for r in extra if r.sensor not in solved]
            report.notes.extend(notes)
    if rows:
        path, n = lake.write_table("clean", "calibration_refined",
                                   rows_to_table(CalibrationRefinedRow, rows), clip_id=clip_id,
                                   name="calibration_refined")
        report.outputs.append(OutputFile(path=path, rows=n))


def _matrix(r: RegistrationRow | CalibrationRefinedRow, p: str) -> np.ndarray:
    q = np.array([getattr(r, f"{p}qw"), getattr(r, f"{p}qx"), getattr(r, f"{p}qy"),
                  getattr(r, f"{p}qz")], dtype=np.float64)
    t = np.array([getattr(r, f"{p}tx"), getattr(r, f"{p}ty"), getattr(r, f"{p}tz")],
                 dtype=np.float64)
    return transform(t, q / np.linalg.norm(q))


def plot_registration_timeline(lake: Lake, clip_id: str, out_png: str | Path) -> Path:
    """The whole clip's registration (``timeline.render_registration_timeline``) from the
    stored ``registrations`` and ``calibration_refined`` rows."""
    regs = lake.read_table("clean", "registrations", clip_id=clip_id).to_pylist()
    if not regs:
        raise _fail(clip_id, "no registrations rows: run the register stage first")
    cal = lake.read_table("clean", "calibration_refined", clip_id=clip_id).to_pylist()
    out = Path(out_png)
    render_registration_timeline(regs, cal, out, title=f"{clip_id}: registration against "
                                 f"{regs[0]['agent_ref']} ({regs[0]['method']})")
    return out


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

    ref = read_agent_scans(lake, clip_id, r["agent_ref"], cfg.sensor)
    oth = read_agent_scans(lake, clip_id, r["agent_other"], cfg.sensor)
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
