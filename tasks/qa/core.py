"""QA stage: sync and completeness checks against the PPS model (DESIGN.md stage 2).

Hardware sync means every stamp is predictable: LiDAR scans start on the 100 ms grid, camera
frames at ``sec + round(k * 1e9 / 30)``, INS samples every 8 ms from the PPS edge. A stamp off
its grid, a missing frame, a scan whose per-point times do not span one revolution, or LiDAR
time not bracketed by INS samples each break a later stage (deskew, registration, temporal
alignment) in a way that is hard to see there, so they are caught here, on the raw zone, with
the value, the threshold and the place (agent, sensor, topic, time span) in every row.

Severity: "error" raises ``ClipError`` carrying the checks (the flow quarantines the clip);
"warning" is recorded only. PPS-grid checks are errors for an agent that has an INS (its GNSS
receiver supplies the PPS the sensors claim to follow) and warnings for an agent without one
(a free-running clock, e.g. the real Ouster test capture). An agent with no INS topic
configured gets the warning "no INS topic configured: deskew/registration impossible"; an
agent whose INS is configured but silent, or has gaps inside LiDAR scans, fails with an error.

The numeric core (``check_*`` functions) works on NumPy arrays; ``run_qa`` does the I/O.
"""

from __future__ import annotations

from typing import cast

import numpy as np
import pyarrow as pa
from pydantic import BaseModel, ConfigDict, Field

from v2xlake.schemas.arrow import rows_to_table
from v2xlake.schemas.clip import AgentConfig, ClipConfig, Modality, SensorConfig
from v2xlake.schemas.errors import ClipError
from v2xlake.schemas.stage import OutputFile, StageReport
from v2xlake.schemas.tables import QaCheckRow
from v2xlake.storage.lake import Lake

STAGE = "qa"
NS = 1_000_000_000
MS = 1_000_000
DEFAULT_RATE_HZ = {Modality.LIDAR: 10.0, Modality.CAMERA: 30.0, Modality.INS: 125.0}


class QaConfig(BaseModel):
    """Thresholds (hashed into the manifest)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    lidar_grid_ms: float = Field(100.0, description="LiDAR scans start every this many ms")
    camera_fps: int = Field(30, description="camera frames at sec + round(k * 1e9 / fps)")
    ins_grid_ms: float = Field(8.0, description="INS samples every this many ms")
    lidar_tolerance_ms: float = Field(1.0, gt=0)
    camera_tolerance_ms: float = Field(1.0, gt=0)
    ins_tolerance_ms: float = Field(0.5, gt=0)
    max_dropped_fraction: float = Field(0.05, ge=0, description="above: error, else warning")
    scan_span_min: float = Field(0.5, description="min scan time span / scan period")
    scan_span_max: float = Field(1.05, description="max scan time span / scan period")
    min_rtk_fixed_fraction: float = Field(0.9, ge=0, le=1)
    rtk_fixed_status: int = 2
    ins_max_gap_ms: float = Field(20.0, gt=0, description="largest INS gap inside a scan")
    ins_edge_scans: int = Field(1, ge=0, description=(
        "scans at each end of the clip that may reach past the first/last INS sample "
        "(recording boundaries): a warning; more, or any gap inside, is an error"))


def _row(cid: str, check: str, passed: bool, severity: str, detail: str, *,
         agent: str | None = None, sensor: str | None = None, value: float | None = None,
         threshold: float | None = None) -> QaCheckRow:
    return QaCheckRow(clip_id=cid, agent_id=agent, sensor=sensor, check=check, passed=passed,
                      severity=severity, value=value, threshold=threshold, detail=detail)


# --------------------------------------------------------------------------- numeric core
def grid_offsets_ns(t_ns: np.ndarray, period_ns: int) -> np.ndarray:
    """Signed distance of each stamp to the nearest multiple of ``period_ns`` (PPS-aligned)."""
    r = np.mod(t_ns, period_ns)
    return np.where(r > period_ns // 2, r - period_ns, r)


def camera_offsets_ns(t_ns: np.ndarray, fps: int) -> np.ndarray:
    """Signed distance of each stamp to ``sec + round(k * 1e9 / fps)`` for the nearest k."""
    sec = np.floor_divide(t_ns, NS)
    frac = t_ns - sec * NS
    k = np.rint(frac * fps / NS).astype(np.int64)
    grid = np.rint(k * (NS / fps)).astype(np.int64)  # k == fps lands on the next second
    return frac - grid


def dropped_frames(t_ns: np.ndarray, period_ns: float) -> tuple[int, list[tuple[int, int]]]:
    """Number of missing frames and the (before, after) stamps of every gap."""
    if t_ns.size < 2:
        return 0, []
    dt = np.diff(t_ns)
    missing = np.maximum(np.rint(dt / period_ns).astype(np.int64) - 1, 0)
    idx = np.flatnonzero(missing)
    return int(missing.sum()), [(int(t_ns[i]), int(t_ns[i + 1])) for i in idx]


def ins_uncovered(ins_t: np.ndarray, t_start: np.ndarray, t_end: np.ndarray,
                  max_gap_ns: int) -> np.ndarray:
    """Boolean per scan: True when INS samples do not bracket [t_start, t_end] densely
    (a sample at or before the start, one at or after the end, no gap above ``max_gap_ns``
    in between), i.e. deskew could not interpolate a pose for every point."""
    bad = np.ones(t_start.size, dtype=bool)
    if ins_t.size < 2:
        return bad
    lo = np.searchsorted(ins_t, t_start, side="right") - 1
    hi = np.searchsorted(ins_t, t_end, side="left")
    ok = (lo >= 0) & (hi < ins_t.size)
    gaps = np.diff(ins_t)
    # largest gap between samples lo..hi (gaps index lo..hi-1); prefix trick via reduceat
    for i in np.flatnonzero(ok):
        a, b = int(lo[i]), int(hi[i])
        bad[i] = b > a and bool(gaps[a:b].max() > max_gap_ns)
    return bad


def spans(mask: np.ndarray, t_start: np.ndarray, t_end: np.ndarray) -> list[tuple[int, int]]:
    """Merge consecutive flagged scans into (start, end) time spans."""
    out: list[tuple[int, int]] = []
    for i in np.flatnonzero(mask):
        s, e = int(t_start[i]), int(t_end[i])
        if out and s <= out[-1][1] + 200 * MS:
            out[-1] = (out[-1][0], max(out[-1][1], e))
        else:
            out.append((s, e))
    return out


# --------------------------------------------------------------------------- checks
class _Qa:
    def __init__(self, lake: Lake, cfg: ClipConfig, config: QaConfig) -> None:
        self.lake, self.cfg, self.c = lake, cfg, config
        self.cid = cfg.clip_id
        self.rows: list[QaCheckRow] = []
        t = {name: lake.read_table("raw", name, clip_id=self.cid)
             for name in ("sensors", "lidar_frames", "camera_frames", "ins", "agents")}
        self.t = t
        starts = [int(np.min(c)) for c in (
            _col(t["lidar_frames"], "t_start_ns"), _col(t["camera_frames"], "stamp_ns"),
            _col(t["ins"], "t_ns")) if c.size]
        self.t0 = min(starts) if starts else 0

    def rel(self, t: int) -> str:
        return f"+{(t - self.t0) / NS:.3f} s"

    def span_txt(self, a: int, b: int) -> str:
        return f"[{self.rel(a)}, {self.rel(b)}] (abs {a}..{b} ns)"

    def add(self, *a: object, **k: object) -> None:
        self.rows.append(_row(self.cid, *a, **k))  # type: ignore[arg-type]

    def frames(self, table: str, agent: str, sensor: str, col: str) -> pa.Table:
        t = self.t[table]
        if t.num_rows == 0:
            return t
        m = np.asarray(t.column("agent_id").to_numpy(zero_copy_only=False) == agent) & \
            np.asarray(t.column("sensor").to_numpy(zero_copy_only=False) == sensor)
        return t.filter(pa.array(m)).sort_by(col)

    def run(self) -> list[QaCheckRow]:
        counts = {(r["agent_id"], r["sensor"]): r["n_messages"]
                  for r in self.t["sensors"].to_pylist()}
        for agent in self.cfg.agents:
            has_ins = bool(agent.sensors_of(Modality.INS)) or (
                agent.pose is not None and agent.pose.kind != "none")
            for s in agent.sensors:
                n = counts.get((agent.agent_id, s.name), 0)
                self.add("messages_present", n > 0, "error",
                         f"{n} messages on {s.topic}" if n else f"no message on {s.topic}",
                         agent=agent.agent_id, sensor=s.name, value=float(n), threshold=1.0)
                if not n:
                    continue
                if s.modality is Modality.LIDAR:
                    self.lidar(agent, s, has_ins)
                elif s.modality is Modality.CAMERA:
                    self.camera(agent, s, has_ins)
            self.ins(agent)
        return self.rows

    def rate(self, s: SensorConfig) -> float:
        return float(s.rate_hz or DEFAULT_RATE_HZ[s.modality])

    def grid_check(self, name: str, agent: AgentConfig, s: SensorConfig, t: np.ndarray,
                   off: np.ndarray, tol_ms: float, has_pps: bool, what: str) -> None:
        worst = float(np.abs(off).max()) / MS
        n_bad = int(np.count_nonzero(np.abs(off) > tol_ms * MS))
        sev = "error" if has_pps else "warning"
        why = "" if has_pps else " (agent has no INS/PPS source: free-running clock, warning only)"
        i = int(np.argmax(np.abs(off)))
        self.add(name, n_bad == 0, sev,
                 f"{n_bad}/{t.size} stamps of {s.topic} off the {what} by more than {tol_ms} ms; "
                 f"worst {worst:.3f} ms at {self.rel(int(t[i]))}{why}",
                 agent=agent.agent_id, sensor=s.name, value=worst, threshold=tol_ms)

    def drop_check(self, agent: AgentConfig, s: SensorConfig, t: np.ndarray) -> None:
        period = NS / self.rate(s)
        n_drop, gaps = dropped_frames(t, period)
        expected = t.size + n_drop
        frac = n_drop / expected if expected else 0.0
        sev = "error" if frac > self.c.max_dropped_fraction else "warning"
        where = ", ".join(self.span_txt(a, b) for a, b in gaps[:5]) + (" ..." if len(gaps) > 5
                                                                      else "")
        self.add("dropped_frames", n_drop == 0, sev,
                 f"{n_drop} of {expected} expected frames at {self.rate(s):g} Hz missing on "
                 f"{s.topic}" + (f": gaps {where}" if gaps else ""),
                 agent=agent.agent_id, sensor=s.name, value=frac,
                 threshold=self.c.max_dropped_fraction)
        nonmono = int(np.count_nonzero(np.diff(t) <= 0)) if t.size > 1 else 0
        if nonmono:
            self.add("stamps_increasing", False, "error",
                     f"{nonmono} non-increasing header stamps on {s.topic}",
                     agent=agent.agent_id, sensor=s.name, value=float(nonmono), threshold=0.0)

    def lidar(self, agent: AgentConfig, s: SensorConfig, has_ins: bool) -> None:
        f = self.frames("lidar_frames", agent.agent_id, s.name, "frame_idx")
        stamp = _col(f, "stamp_ns")
        self.grid_check("pps_lidar", agent, s, stamp,
                        grid_offsets_ns(stamp, int(self.c.lidar_grid_ms * MS)),
                        self.c.lidar_tolerance_ms, has_ins, f"{self.c.lidar_grid_ms:g} ms grid")
        self.drop_check(agent, s, np.sort(stamp))
        n_pts = _col(f, "n_points")
        empty = np.flatnonzero(n_pts == 0)
        self.add("lidar_empty_frames", empty.size == 0, "warning",
                 f"{empty.size} frames of {s.topic} without a finite point"
                 + (f" (frames {empty[:10].tolist()})" if empty.size else ""),
                 agent=agent.agent_id, sensor=s.name, value=float(empty.size), threshold=0.0)
        ok = n_pts > 0
        span = (_col(f, "t_end_ns") - _col(f, "t_start_ns"))[ok] / MS
        period = 1000.0 / self.rate(s)
        lo, hi = self.c.scan_span_min * period, self.c.scan_span_max * period
        bad = np.flatnonzero((span < lo) | (span > hi))
        med = float(np.median(span)) if span.size else 0.0
        self.add("scan_time_span", bad.size == 0, "error",
                 f"per-point time span of {s.topic} scans: median {med:.2f} ms, expected "
                 f"{lo:.1f}..{hi:.1f} ms; {bad.size} scans outside"
                 + (f" (frames {np.flatnonzero(ok)[bad][:10].tolist()})" if bad.size else ""),
                 agent=agent.agent_id, sensor=s.name, value=med, threshold=hi)

    def camera(self, agent: AgentConfig, s: SensorConfig, has_ins: bool) -> None:
        f = self.frames("camera_frames", agent.agent_id, s.name, "frame_idx")
        stamp = _col(f, "stamp_ns")
        self.grid_check("pps_camera", agent, s, stamp, camera_offsets_ns(stamp, self.c.camera_fps),
                        self.c.camera_tolerance_ms, has_ins,
                        f"PPS + k x {1000 / self.c.camera_fps:.3f} ms grid")
        self.drop_check(agent, s, np.sort(stamp))

    def ins(self, agent: AgentConfig) -> None:
        """The pose track's timing and coverage. A PPS-locked INS sensor (the simulator's
        and CATS-V2V's layout) is checked against its grid; a ``pose:`` source (Odometry,
        NavSatFix + Imu, a vendor INS, a fixed pose) keeps its own rate and is checked for
        covering every scan."""
        aid = agent.agent_id
        ins_sensors = agent.sensors_of(Modality.INS)
        pose = agent.pose
        if (pose is not None and pose.kind == "none") or (pose is None and not ins_sensors):
            why = "pose: none" if pose is not None else "no INS topic configured"
            self.add("ins_coverage", False, "warning",
                     f"agent {aid}: {why}: deskew/registration impossible", agent=aid)
            return
        s = ins_sensors[0] if pose is None else None
        label = s.name if s is not None else "POSE"
        topic = s.topic if s is not None else (pose.topic if pose and pose.topic
                                               else f"pose ({pose.kind if pose else ''})")
        t = self.t["ins"]
        ins_t = np.sort(_col(t.filter(pa.array(
            np.asarray(t.column("agent_id").to_numpy(zero_copy_only=False) == aid)))
            if t.num_rows else t, "t_ns"))
        if ins_t.size == 0:
            if s is None:
                self.add("ins_coverage", False, "error",
                         f"pose source {topic} of agent {aid} gave no pose", agent=aid,
                         sensor=label)
            return  # an INS sensor: messages_present already failed with an error
        if s is not None:
            self.grid_check("pps_ins", agent, s, ins_t,
                            grid_offsets_ns(ins_t, int(self.c.ins_grid_ms * MS)),
                            self.c.ins_tolerance_ms, True, f"{self.c.ins_grid_ms:g} ms grid")
            self.drop_check(agent, s, ins_t)
        if s is not None or (pose is not None and pose.kind == "ins"):
            rtk = _col(t.filter(pa.array(np.asarray(
                t.column("agent_id").to_numpy(zero_copy_only=False) == aid))), "rtk_status")
            fixed = float(np.mean(rtk == self.c.rtk_fixed_status))
            self.add("rtk_fixed", fixed >= self.c.min_rtk_fixed_fraction, "warning",
                     f"{fixed:.1%} of INS samples on {topic} have RTK fixed "
                     f"(status {self.c.rtk_fixed_status})", agent=aid, sensor=label,
                     value=fixed, threshold=self.c.min_rtk_fixed_fraction)
        # a pose source keeps its own rate (a 20 Hz fix, a fixed pose at 10 Hz): a gap is
        # 2.5 of its median sample interval, never less than the configured INS gap
        max_gap = int(self.c.ins_max_gap_ms * MS)
        if s is None and ins_t.size > 1:
            max_gap = max(max_gap, int(2.5 * float(np.median(np.diff(ins_t)))))
        for lid in agent.sensors_of(Modality.LIDAR):
            f = self.frames("lidar_frames", aid, lid.name, "frame_idx")
            if f.num_rows == 0:
                continue
            ts, te = _col(f, "t_start_ns"), _col(f, "t_end_ns")
            bad = ins_uncovered(ins_t, ts, te, max_gap)
            # scans reaching past the INS recording at the clip's two ends (bags are cut
            # independently per topic) vs. scans inside the INS time range
            head = bad & (ts < ins_t[0])
            tail = bad & (te > ins_t[-1])
            inner = bad & ~head & ~tail
            edge_ok = (int(head.sum()) <= self.c.ins_edge_scans
                       and int(tail.sum()) <= self.c.ins_edge_scans)
            sev = "error" if inner.any() or not edge_ok else "warning"
            where = "; ".join(self.span_txt(a, b) for a, b in spans(bad, ts, te))
            what = (f"{int(inner.sum())} inside the INS time range (gap > "
                    f"{max_gap / MS:g} ms), {int(head.sum())} before its first and "
                    f"{int(tail.sum())} after its last sample")
            self.add("ins_coverage", not bad.any(), sev,
                     f"INS {topic} of agent {aid} does not cover {int(bad.sum())} of "
                     f"{bad.size} {lid.name} scans ({what}): uncovered {where}" if bad.any() else
                     f"INS {topic} brackets all {bad.size} {lid.name} scans",
                     agent=aid, sensor=label, value=float(bad.sum()), threshold=0.0)


def _col(t: pa.Table, name: str) -> np.ndarray:
    if t.num_rows == 0 or name not in t.column_names:
        return np.zeros(0, dtype=np.int64)
    return np.asarray(t.column(name).to_numpy())


def load_landing_config(lake: Lake, clip_id: str) -> ClipConfig:
    import yaml

    path = lake.path("landing", clip_id, "clip.yaml")
    if not lake.exists(path):
        raise ClipError(clip_id, "no landing copy of clip.yaml: run ingest first", path=path,
                        stage=STAGE)
    return ClipConfig.model_validate(yaml.safe_load(lake.read_bytes(path)))


def run_qa(lake: Lake, clip_id: str, config: QaConfig | None = None) -> StageReport:
    """Check one ingested clip, write ``raw/qa_checks``; on an error-severity failure raise
    ``ClipError`` with the checks (the flow writes the quarantine report)."""
    config = config or QaConfig()
    cfg = load_landing_config(lake, clip_id)
    qa = _Qa(lake, cfg, config)
    if qa.t["sensors"].num_rows == 0:
        raise ClipError(clip_id, "no raw tables for this clip (not ingested, or quarantined): "
                        "run ingest first", path=lake.table_dir("raw", "sensors", clip_id),
                        stage=STAGE)
    rows = qa.run()
    table = rows_to_table(QaCheckRow, cast(list[BaseModel], rows))
    path, n = lake.write_table("raw", "qa_checks", table, clip_id=clip_id)
    failed = [r for r in rows if not r.passed and r.severity == "error"]
    warnings = [r for r in rows if not r.passed and r.severity == "warning"]
    if failed:  # the flow quarantines (once, in one place) with these checks in the report
        first = failed[0]
        topic = None
        if first.agent_id and first.sensor:
            agent = cfg.agent(first.agent_id)
            named = [x for x in agent.sensors if x.name == first.sensor]
            topic = named[0].topic if named else (agent.pose.topic if agent.pose else None)
        raise ClipError(clip_id, "; ".join(f"{r.check}: {r.detail}" for r in failed),
                        agent_id=first.agent_id, topic=topic, stage=STAGE, checks=rows)
    return StageReport(
        stage=STAGE, clip_id=clip_id,
        outputs=[OutputFile(path=path[len(lake.base) + 1:], rows=n)],
        metrics={"checks": float(len(rows)), "warnings": float(len(warnings)), "errors": 0.0},
        notes=[f"warning {r.check}" + (f" {r.agent_id}" if r.agent_id else "")
               + (f"/{r.sensor}" if r.sensor else "") + f": {r.detail}" for r in warnings])
