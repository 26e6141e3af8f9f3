"""Deskew stage: clean ``lidar_points`` -> clean ``lidar_points_deskewed`` (+ per-frame stats).

Reads per agent the clean ``ego_poses`` (``T_world_ego``), the LiDAR extrinsic from
``calibrated_sensors`` and each scan's start time from ``lidar_frames``; moves every point
into the LiDAR frame at its scan start (supplementary A.4, :func:`tasks.motion.deskew_points`)
and writes them with the same schema as ``lidar_points`` (one row group per frame). The
per-frame figures (points outside INS coverage, reference time, max / RMS shift) go into
deskew's own ``deskew_frames``; the catalog's ``lidar_frames`` view joins them, so the
catalog shows how much each scan was corrected while ``lidar_frames`` keeps one writer.

Policy for scans that cannot be compensated (points outside the INS span or over an INS
gap): frames at the clip's edges (the INS starts after the first scan or stops before the
last) are skipped and reported by default, an uncovered frame in the middle of the clip is
a data fault and raises :class:`ClipError` naming clip, agent, frame and the time spans.
An agent without a pose track is not deskewed (a note says so) and a clip where no agent
has one gets a ``not_applicable`` report: per-point compensation without poses is
impossible, and publishing skewed scans as "deskewed" would be worse than saying so; the raw
scans stay in ``lidar_points`` and the rest of the clip (images, QA) is kept.
"""

from __future__ import annotations

import itertools
import logging
import time
from dataclasses import dataclass, field

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from v2xlake.schemas.arrow import rows_to_table
from v2xlake.schemas.errors import ClipError
from v2xlake.schemas.stage import Chunked, OutputFile, Stage, StageReport, tables
from v2xlake.schemas.tables import DeskewFrameRow
from v2xlake.storage.frames import iter_row_groups, partition_files, row_group_count
from v2xlake.storage.lake import Lake
from v2xlake.storage.reader import (
    pose_less_report,
    pose_missing,
    poses_missing,
    read_extrinsics,
)
from v2xlake.tasks.deskew import DECLARATION
from v2xlake.tasks.deskew.config import DeskewConfig
from v2xlake.tasks.deskew.coverage import max_pose_gap, pose_gaps, uncompensable
from v2xlake.tasks.interpolate import PoseTrack
from v2xlake.tasks.motion import DeskewResult, deskew_points
from v2xlake.tasks.reader import load_pose_track

log = logging.getLogger(__name__)

STAGE = "deskew"
OUT_TABLE = "lidar_points_deskewed"
FRAMES_TABLE = "deskew_frames"


@dataclass
class _FrameStat:
    n_uncovered: int
    ref_ns: int | None
    max_shift: float | None
    rms_shift: float | None


@dataclass
class _Totals:
    points: int = 0
    valid: int = 0
    uncovered: int = 0
    nan: int = 0
    frames: int = 0
    skipped: int = 0
    skipped_points: int = 0
    empty: int = 0
    kernel_s: float = 0.0
    max_shift: float = 0.0
    rms_shifts: list[float] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)


def _fail(clip_id: str, reason: str, agent_id: str | None = None) -> ClipError:
    return ClipError(clip_id, reason, agent_id=agent_id, stage=STAGE)


def _col(t: pa.Table, name: str) -> np.ndarray:
    return np.asarray(t.column(name).to_numpy(zero_copy_only=False))


def _frame_parts(tbl: pa.Table) -> list[tuple[int, pa.Table]]:
    """(frame_idx, rows of that frame) in a row group; usually the row group IS one frame
    (zero-copy slices when rows are frame-sorted)."""
    f = _col(tbl, "frame_idx")
    if len(f) == 0:
        return []
    if np.all(f[1:] >= f[:-1]):
        cuts = np.flatnonzero(np.diff(f)) + 1
        bounds = [0, *cuts.tolist(), len(f)]
        return [(int(f[a]), tbl.slice(a, b - a)) for a, b in itertools.pairwise(bounds)]
    return [(int(k), tbl.take(pa.array(np.flatnonzero(f == k)))) for k in np.unique(f)]


def _sensor_parts(part: pa.Table) -> list[tuple[str, pa.Table]]:
    """Split a frame by LiDAR (dictionary column: unique on the dictionary, no string copies)."""
    col = part.column("sensor")
    found: set[str] = set()
    for chunk in col.chunks:
        if pa.types.is_dictionary(chunk.type):
            used = pc.unique(chunk.indices).drop_null()
            found.update(str(s) for s in chunk.dictionary.take(used).to_pylist())
        else:
            found.update(str(s) for s in pc.unique(chunk).drop_null().to_pylist())
    names = sorted(found)
    if len(names) <= 1:
        return [(names[0] if names else "", part)]
    s = col.cast(pa.string())
    return [(n, part.filter(pc.equal(s, n))) for n in names]


def _warm_up() -> None:
    """Load (or compile) the numba kernels before timing, so points_per_s is the kernel's."""
    track = PoseTrack(np.array([0, 1], np.int64), np.zeros((2, 3)),
                      np.array([[1.0, 0, 0, 0], [1.0, 0, 0, 0]]))
    deskew_points(np.zeros((1, 3), np.float32), np.zeros(1, np.int64), track, np.eye(4), 0)


@dataclass(frozen=True)
class DeskewChunk:
    """A share of the clip's scans: row groups ``[rg0, rg1)`` of one agent's points file."""

    agent: str
    path: str
    rg0: int
    rg1: int


@dataclass
class DeskewPart:
    """What a chunk produced: its output files, per-frame figures and totals."""

    outputs: list[OutputFile]
    stats: dict[tuple[str, str, int], _FrameStat]
    tot: _Totals


def plan_deskew(lake: Lake, clip_id: str, cfg: DeskewConfig) -> list[DeskewChunk] | StageReport:
    """The chunks of the clip's scans (``frames_per_file`` frames each, one output file per
    chunk), or a not-applicable report when no agent has a pose track."""
    agents_tbl = lake.read_table("clean", "agents", clip_id=clip_id)
    if agents_tbl.num_rows == 0:
        raise _fail(clip_id, "no clean 'agents' rows: run anonymize first")
    point_files = partition_files(lake, "clean", "lidar_points", clip_id)
    if not point_files:
        raise _fail(clip_id, "no clean lidar_points: nothing to deskew")
    lake.delete_partition("clean", OUT_TABLE, clip_id)
    lake.delete_partition("clean", FRAMES_TABLE, clip_id)
    agents = sorted({a for _, a, _ in point_files if a is not None})
    without = poses_missing(lake, clip_id, agents)
    if len(without) == len(agents):
        return pose_less_report(STAGE, clip_id, "per-point motion compensation needs poses; "
                                "the raw scans stay available as lidar_points", without)
    chunks: list[DeskewChunk] = []
    for path, agent, _ in point_files:
        if agent is None or agent in without:
            continue
        n = row_group_count(lake, path)  # one per frame, usually
        chunks += [DeskewChunk(agent, path, r, min(r + cfg.frames_per_file, n))
                   for r in range(0, n, cfg.frames_per_file)]
    return chunks


def deskew_chunk(lake: Lake, clip_id: str, cfg: DeskewConfig, chunk: DeskewChunk) -> DeskewPart:
    """Deskew one chunk and write its output file (runs anywhere: a Dask worker too)."""
    _warm_up()
    agent = chunk.agent
    track = load_pose_track(lake, clip_id, agent)
    extr = read_extrinsics(lake, clip_id, agent)
    gaps = pose_gaps(track, max_pose_gap(track, cfg.pose_gaps))
    fa = lake.read_table("clean", "lidar_frames", clip_id=clip_id, agent_id=agent)
    t_start = {(str(s), int(f)): int(t0) for s, f, t0 in zip(
        _col(fa, "sensor"), _col(fa, "frame_idx"), _col(fa, "t_start_ns"), strict=True)} \
        if fa.num_rows else {}
    part = DeskewPart([], {}, _Totals())
    pending: list[pa.Table] = []
    for group in iter_row_groups(lake, chunk.path, chunk.rg0, chunk.rg1):
        for frame_idx, rows in _frame_parts(group):
            for sensor, sub in _sensor_parts(rows):
                out = _deskew_frame(clip_id, agent, sensor, frame_idx, sub, track, extr, gaps,
                                    t_start, cfg, part.stats, part.tot)
                if out is not None:
                    pending.append(out)
    if pending:
        data = pa.concat_tables(pending)
        first = int(_col(data, "frame_idx").min())
        # one points file per LiDAR of the agent: its name keeps the chunks of several
        # LiDARs (each starting at frame 0) apart
        source = chunk.path.rsplit("/", 1)[-1].removesuffix(".parquet")
        path, rows_n = lake.write_table("clean", OUT_TABLE, data, clip_id=clip_id,
                                        agent_id=agent, name=f"{source}-frames-{first:06d}",
                                        row_group_by="frame_idx")
        part.outputs.append(OutputFile(path=path, rows=rows_n))
    return part


def finish_deskew(lake: Lake, clip_id: str, cfg: DeskewConfig, parts: list[DeskewPart],
                  seconds: float | None = None) -> StageReport:
    """Merge the chunks: ``deskew_frames``, the report's outputs, notes and metrics."""
    report = StageReport(stage=STAGE, clip_id=clip_id)
    tot = _Totals()
    stats: dict[tuple[str, str, int], _FrameStat] = {}
    for p in parts:
        report.outputs.extend(p.outputs)
        stats.update(p.stats)
        for f in ("points", "valid", "uncovered", "nan", "frames", "skipped", "skipped_points"):
            setattr(tot, f, getattr(tot, f) + getattr(p.tot, f))
        tot.kernel_s += p.tot.kernel_s
        tot.max_shift = max(tot.max_shift, p.tot.max_shift)
        tot.rms_shifts += p.tot.rms_shifts
        tot.notes += p.tot.notes
    frames = lake.read_table("clean", "lidar_frames", clip_id=clip_id, columns=["n_points"])
    tot.empty = int(np.sum(_col(frames, "n_points") == 0)) if frames.num_rows else 0
    _write_frames(lake, clip_id, stats, report)
    posed = {k[0] for k in stats}
    agents = lake.read_table("clean", "agents", clip_id=clip_id, columns=["agent_id"])
    for a in sorted(set(agents.column("agent_id").to_pylist()) - posed):
        if (why := pose_missing(lake, clip_id, a)):
            report.notes.append(f"{a} not deskewed: {why}")
    report.notes.extend(tot.notes)
    wall = seconds if seconds is not None else tot.kernel_s
    rms_all = float(np.sqrt(np.mean(np.square(tot.rms_shifts)))) if tot.rms_shifts else 0.0
    report.metrics.update(
        n_points=float(tot.points), n_deskewed=float(tot.valid), n_uncovered=float(tot.uncovered),
        n_nan=float(tot.nan), n_frames=float(tot.frames), n_frames_skipped=float(tot.skipped),
        n_frames_empty=float(tot.empty), n_points_in_skipped_frames=float(tot.skipped_points),
        n_chunks=float(len(parts)),
        points_per_s=tot.points / tot.kernel_s if tot.kernel_s > 0 else 0.0,
        stage_points_per_s=tot.points / wall if wall > 0 else 0.0,
        max_shift_m=tot.max_shift, rms_shift_m=rms_all, seconds=wall,
    )
    log.info("deskew %s: %d frames, %d points (%.0f M/s kernel), max shift %.2f m", clip_id,
             tot.frames, tot.points, report.metrics["points_per_s"] / 1e6, tot.max_shift)
    return report


def run_deskew(lake: Lake, clip_id: str, config: DeskewConfig | None = None) -> StageReport:
    """Deskew every LiDAR frame of every agent of the clip, chunk after chunk (the flow
    spreads the chunks over its task runner instead); see the module docstring."""
    cfg = config or DeskewConfig()
    wall0 = time.perf_counter()
    plan = plan_deskew(lake, clip_id, cfg)
    if isinstance(plan, StageReport):
        return plan
    parts = [deskew_chunk(lake, clip_id, cfg, c) for c in plan]
    return finish_deskew(lake, clip_id, cfg, parts, time.perf_counter() - wall0)


def _deskew_frame(clip_id: str, agent: str, sensor: str, frame_idx: int, part: pa.Table,
                  track: PoseTrack, extr: dict[str, np.ndarray], gaps: np.ndarray,
                  t_start: dict[tuple[str, int], int], cfg: DeskewConfig,
                  stats: dict[tuple[str, str, int], _FrameStat], tot: _Totals) -> pa.Table | None:
    if sensor not in extr:
        raise _fail(clip_id, f"no calibrated_sensors row (modality lidar) for {sensor}: "
                             "the LiDAR extrinsic T_ego_lidar is needed for deskew", agent)
    n = part.num_rows
    tot.frames += 1
    tot.points += n
    t = _col(part, "t_ns").astype(np.int64)
    xyz = np.stack([_col(part, c) for c in ("x", "y", "z")], axis=1)
    ref = t_start.get((sensor, frame_idx)) if cfg.reference == "scan_start" else None
    k0 = time.perf_counter()
    res: DeskewResult = deskew_points(xyz, t, track, extr[sensor], ref)
    tot.kernel_s += time.perf_counter() - k0
    tot.nan += res.n_nan
    if n == 0:
        stats[(agent, sensor, frame_idx)] = _FrameStat(0, res.t_ref_ns, None, None)
        return None
    problem = uncompensable(res, track, gaps, cfg.uncovered, cfg.pose_gaps)
    if problem is not None:
        # at the clip's edge = the scan reaches outside the INS span (INS started late or
        # stopped early); otherwise the INS has a hole in the middle of the clip
        lo = min(res.t_min_ns or track.t_min, res.t_ref_ns or track.t_min)
        hi = max(res.t_max_ns or track.t_max, res.t_ref_ns or track.t_max)
        edge = lo < track.t_min or hi > track.t_max
        if cfg.uncovered.policy == "error" or (cfg.uncovered.policy == "skip_edge"
                                                 and not edge):
            raise _fail(clip_id, f"{sensor} frame {frame_idx}: {problem}", agent)
        tot.skipped += 1
        tot.skipped_points += n - res.n_nan
        tot.uncovered += res.n_uncovered
        # deskew_ref_ns stays null: the frame has no deskewed points
        stats[(agent, sensor, frame_idx)] = _FrameStat(res.n_uncovered, None, None, None)
        tot.notes.append(f"{agent} {sensor} frame {frame_idx} skipped: {problem}")
        log.warning("deskew %s/%s %s frame %d skipped: %s", clip_id, agent, sensor, frame_idx,
                    problem)
        return None
    tot.uncovered += res.n_uncovered
    tot.valid += res.n_valid
    tot.max_shift = max(tot.max_shift, res.max_shift_m)
    tot.rms_shifts.append(res.rms_shift_m)
    stats[(agent, sensor, frame_idx)] = _FrameStat(res.n_uncovered, res.t_ref_ns, res.max_shift_m,
                                                   res.rms_shift_m)
    keep = pa.array(res.valid)
    out = part.filter(keep) if res.n_valid < n else part
    kept = res.xyz[res.valid] if res.n_valid < n else res.xyz
    for j, c in enumerate(("x", "y", "z")):
        out = out.set_column(out.schema.get_field_index(c), c,
                             pa.array(np.ascontiguousarray(kept[:, j]), pa.float32()))
    return out


def _write_frames(lake: Lake, clip_id: str, stats: dict[tuple[str, str, int], _FrameStat],
                  report: StageReport) -> None:
    """Per-frame deskew figures into deskew's own ``deskew_frames`` (one file per agent)."""
    by_agent: dict[str, list[DeskewFrameRow]] = {}
    for (agent, sensor, frame_idx), g in sorted(stats.items()):
        by_agent.setdefault(agent, []).append(DeskewFrameRow(
            clip_id=clip_id, agent_id=agent, sensor=sensor, frame_idx=frame_idx,
            n_uncovered=g.n_uncovered, deskew_ref_ns=g.ref_ns,
            deskew_max_shift_m=g.max_shift, deskew_rms_shift_m=g.rms_shift))
    for agent, rows in by_agent.items():
        out, n = lake.write_table("clean", FRAMES_TABLE, rows_to_table(DeskewFrameRow, rows),
                                  clip_id=clip_id, agent_id=agent, name="part")
        report.outputs.append(OutputFile(path=out, rows=n))


DESKEW = Stage(
    name=DECLARATION.name, config_model=DeskewConfig,
    reads=tables("clean", "agents", "ego_poses", "calibrated_sensors", "lidar_frames",
                 "lidar_points"),
    owns=DECLARATION.owns, run=run_deskew,
    chunked=Chunked(plan=plan_deskew, run_chunk=deskew_chunk, finish=finish_deskew),
    doc="per-point motion compensation into the scan-start LiDAR frame (supp. A.4 eq. 2-3)")
