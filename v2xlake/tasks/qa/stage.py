"""QA stage: timing and completeness checks against each sensor's declared model
(docs/architecture.md, Stages).

Nothing here assumes one rig. Every sensor's ``clip.yaml`` entry says its rate and how it is
timed (``sync``): PPS-locked sensors stamp on a grid ``sec + phase + round(k * 1e9 / rate)``
(LiDAR scans every 100 ms at 10 Hz, cameras at 20 or 30 Hz, an INS at 100 or 125 Hz) and are
checked against it; free-running ones are checked for gaps and jitter of their intervals
instead. A rate that is not declared is measured from the stamps (and the check says so); a
declared rate the stamps contradict is an error. A stamp off its grid, a missing frame, a
stamp going back in time (checked in bag order, before anything is sorted), a scan whose
per-point times do not span its share of a revolution (``scan_fov_deg``), or a LiDAR scan
not bracketed by the agent's pose track each break a later stage (deskew, registration,
temporal alignment) in a way that is hard to see there, so they are caught here, on the raw
zone, with the value, the threshold and the place (agent, sensor, topic, time span) in every
row. Every threshold is a ``QaConfig`` field, settable per clip in its ``params: qa:``.

Severity: "error" raises ``ClipError`` carrying the checks (the flow quarantines the clip);
"warning" is recorded only. A sensor that declares no ``sync`` is PPS-locked when its agent
has a pose or GNSS source (the receiver supplies the PPS) and grid findings are errors;
without one (a free-running clock, e.g. the real Ouster test capture) they are warnings. An
agent without a pose gets the warning "no pose: deskew/registration impossible"; an agent
whose pose source is configured but silent, or leaves gaps inside LiDAR scans, an error.

This module reads the raw zone, runs the checks and writes ``qa_checks`` (and defines
``QA``); the numeric core on stamp arrays is ``timing.py``, the thresholds ``config.py``.
"""


from __future__ import annotations

from typing import cast

import numpy as np
import pyarrow as pa
from pydantic import BaseModel

from v2xlake.schemas.arrow import rows_to_table
from v2xlake.schemas.clip import (
    AgentConfig,
    ClipConfig,
    FixedPose,
    InsPose,
    Modality,
    NoPose,
    OdometryPose,
    SensorConfig,
    SplitPose,
    SyncMode,
    load_yaml,
)
from v2xlake.schemas.errors import ClipError
from v2xlake.schemas.stage import OutputFile, Stage, StageReport, tables
from v2xlake.schemas.tables import QaCheckRow
from v2xlake.storage.lake import Lake
from v2xlake.tasks.qa import DECLARATION
from v2xlake.tasks.qa.config import QaConfig
from v2xlake.tasks.qa.timing import (
    MS,
    NS,
    dropped_frames,
    ins_uncovered,
    interval_jitter_ns,
    measured_rate_hz,
    pps_offsets_ns,
    spans,
)

STAGE = "qa"
#: the raw tables the checks read (and so ``QA.reads``)
CHECKED = ("sensors", "lidar_frames", "camera_frames", "radar_frames", "ins", "ego_poses", "imu",
           "gnss", "agents")
STATUS_UNKNOWN = -2  # tasks.ingest.pose: the pose source reports no solution status


def _row(cid: str, check: str, passed: bool, severity: str, detail: str, *,
         agent: str | None = None, sensor: str | None = None, value: float | None = None,
         threshold: float | None = None) -> QaCheckRow:
    return QaCheckRow(clip_id=cid, agent_id=agent, sensor=sensor, check=check, passed=passed,
                      severity=severity, value=value, threshold=threshold, detail=detail)




# --------------------------------------------------------------------------- checks
def pose_time_base(agent: AgentConfig) -> SensorConfig | None:
    """The sensor whose stamps the agent's pose track has (None: derived or fixed times)."""
    p = agent.effective_pose
    if isinstance(p, InsPose | OdometryPose):
        return agent.sensor(p.sensor)
    if isinstance(p, SplitPose):
        return agent.sensor(p.attitude if p.sample_at == "attitude" else p.position)
    return None


class _Qa:
    def __init__(self, lake: Lake, cfg: ClipConfig, config: QaConfig) -> None:
        self.lake, self.cfg, self.c = lake, cfg, config
        self.cid = cfg.clip_id
        self.rows: list[QaCheckRow] = []
        self.t = {name: lake.read_table("raw", name, clip_id=self.cid) for name in CHECKED}
        starts = [int(np.min(c)) for c in (
            _col(self.t["lidar_frames"], "t_start_ns"), _col(self.t["camera_frames"], "stamp_ns"),
            _col(self.t["ins"], "t_ns"), _col(self.t["ego_poses"], "t_ns")) if c.size]
        self.t0 = min(starts) if starts else 0

    def rel(self, t: int) -> str:
        return f"+{(t - self.t0) / NS:.3f} s"

    def span_txt(self, a: int, b: int) -> str:
        return f"[{self.rel(a)}, {self.rel(b)}] (abs {a}..{b} ns)"

    def add(self, *a: object, **k: object) -> None:
        self.rows.append(_row(self.cid, *a, **k))  # type: ignore[arg-type]

    def _of(self, table: str, agent: str, sensor: str | None = None) -> pa.Table:
        """Rows of one agent (and sensor), in the order ingest wrote them (bag order)."""
        t = self.t[table]
        if t.num_rows == 0:
            return t
        m = np.asarray(t.column("agent_id").to_numpy(zero_copy_only=False) == agent)
        if sensor is not None and "sensor" in t.column_names:
            m &= np.asarray(t.column("sensor").to_numpy(zero_copy_only=False) == sensor)
        return t.filter(pa.array(m))

    def frames(self, table: str, agent: str, sensor: str, col: str) -> pa.Table:
        f = self._of(table, agent, sensor)
        return f.sort_by(col) if f.num_rows else f

    def pose_times(self, aid: str) -> np.ndarray:
        """The agent's pose track stamps (raw ``ins`` or, in a local map, ``ego_poses``)."""
        for table in ("ins", "ego_poses"):
            t = _col(self._of(table, aid), "t_ns")
            if t.size:
                return t
        return np.zeros(0, np.int64)

    def stamps(self, agent: AgentConfig, s: SensorConfig) -> np.ndarray | None:
        """The sensor's stamps in bag order, where a table holds them per sensor."""
        aid = agent.agent_id
        if s.modality is Modality.LIDAR:
            return _col(self.frames("lidar_frames", aid, s.name, "frame_idx"), "stamp_ns")
        if s.modality is Modality.CAMERA:
            return _col(self.frames("camera_frames", aid, s.name, "frame_idx"), "stamp_ns")
        if s.modality is Modality.RADAR:
            return _col(self.frames("radar_frames", aid, s.name, "frame_idx"), "stamp_ns")
        if s.modality is Modality.IMU:
            return _col(self._of("imu", aid, s.name), "t_ns")
        if s.modality is Modality.GNSS and len(agent.sensors_of(Modality.GNSS)) == 1:
            return _col(self._of("gnss", aid), "t_ns")
        base = pose_time_base(agent)
        if base is not None and base.name == s.name:
            return self.pose_times(aid)
        return None

    def run(self) -> list[QaCheckRow]:
        info = {(r["agent_id"], r["sensor"]): r for r in self.t["sensors"].to_pylist()}
        for agent in self.cfg.agents:
            pps = (not isinstance(agent.effective_pose, NoPose)
                   or bool(agent.sensors_of(Modality.GNSS)))
            for s in agent.sensors:
                row = info.get((agent.agent_id, s.name), {})
                n = int(row.get("n_messages") or 0)
                self.add("messages_present", n > 0, "error",
                         f"{n} messages on {s.topic}" if n else f"no message on {s.topic}",
                         agent=agent.agent_id, sensor=s.name, value=float(n), threshold=1.0)
                if not n:
                    continue
                self.order(agent, s, int(row.get("n_backwards") or 0),
                           int(row.get("n_duplicates") or 0), n)
                t = self.stamps(agent, s)
                if t is not None and t.size:
                    self.timing(agent, s, t, pps)
                if s.modality is Modality.LIDAR:
                    self.lidar(agent, s)
            self.pose(agent)
        return self.rows

    def order(self, agent: AgentConfig, s: SensorConfig, n_back: int, n_dup: int,
              n: int) -> None:
        """Time order as the bag delivered it (counted at ingest, before any sorting)."""
        aid = agent.agent_id
        self.add("stamps_increasing", n_back == 0, "error",
                 f"{n_back} of {n} header stamps on {s.topic} go back in time (bag order)"
                 if n_back else f"header stamps on {s.topic} increase",
                 agent=aid, sensor=s.name, value=float(n_back), threshold=0.0)
        if n_dup:
            # ingest drops every repeat (a frame's only with the same payload: one with
            # another payload is refused there), so the count is of messages not kept
            self.add("duplicate_messages", False, "warning",
                     f"{n_dup} message(s) on {s.topic} repeat an earlier stamp "
                     "(dropped at ingest)",
                     agent=aid, sensor=s.name, value=float(n_dup), threshold=0.0)

    def tolerance_ms(self, s: SensorConfig) -> float:
        if s.sync is not None and s.sync.tolerance_ms is not None:
            return s.sync.tolerance_ms
        return {Modality.LIDAR: self.c.tolerance_ms.lidar,
                Modality.CAMERA: self.c.tolerance_ms.camera,
                Modality.INS: self.c.tolerance_ms.ins, Modality.IMU: self.c.tolerance_ms.imu,
                Modality.GNSS: self.c.tolerance_ms.gnss,
                Modality.RADAR: self.c.tolerance_ms.radar}[s.modality]

    def rate(self, agent: AgentConfig, s: SensorConfig, t: np.ndarray) -> float | None:
        """The sensor's rate: declared (and checked against the stamps) or measured."""
        aid = agent.agent_id
        got = measured_rate_hz(t)
        if s.rate_hz is None:
            if got is None:
                return None
            rate = float(round(got)) if got >= 1.5 else got
            self.add("rate", True, "warning",
                     f"{s.topic} declares no rate_hz: measured {got:.3f} Hz, checked as "
                     f"{rate:g} Hz", agent=aid, sensor=s.name, value=got)
            return rate
        if got is not None:
            off = abs(got / s.rate_hz - 1.0)
            self.add("rate", off <= self.c.stream.rate_mismatch_fraction, "error",
                     f"{s.topic}: declared {s.rate_hz:g} Hz, stamps show {got:.3f} Hz",
                     agent=aid, sensor=s.name, value=got, threshold=s.rate_hz)
        return float(s.rate_hz)

    def timing(self, agent: AgentConfig, s: SensorConfig, t: np.ndarray, pps: bool) -> None:
        aid = agent.agent_id
        rate = self.rate(agent, s, t)
        if rate is None:
            return
        period = NS / rate
        ts = np.sort(t)  # order was checked above, in bag order
        mode = s.sync.mode if s.sync is not None else SyncMode.PPS
        tol_ms = self.tolerance_ms(s)
        if mode is SyncMode.PPS:
            phase = round((s.sync.phase_ms if s.sync else 0.0) * MS)
            off = pps_offsets_ns(ts, rate, phase)
            locked = s.sync is not None or pps
            worst = float(np.abs(off).max()) / MS
            n_bad = int(np.count_nonzero(np.abs(off) > tol_ms * MS))
            i = int(np.argmax(np.abs(off)))
            why = "" if locked else (" (agent has no pose/GNSS source and the sensor declares "
                                     "no sync: free-running clock, warning only)")
            grid = (f"PPS + {s.sync.phase_ms:g} ms + k x {1000 / rate:.3f} ms grid"
                    if s.sync and s.sync.phase_ms else f"PPS + k x {1000 / rate:.3f} ms grid")
            self.add(f"pps_{s.modality.value}", n_bad == 0, "error" if locked else "warning",
                     f"{n_bad}/{ts.size} stamps of {s.topic} off the {grid} by more than "
                     f"{tol_ms:g} ms; worst {worst:.3f} ms at {self.rel(int(ts[i]))}{why}",
                     agent=aid, sensor=s.name, value=worst, threshold=tol_ms)
        else:
            tol = (s.sync.tolerance_ms if s.sync and s.sync.tolerance_ms
                   else self.c.stream.free_jitter_fraction * period / MS)
            jit = interval_jitter_ns(ts, period)
            worst = float(np.abs(jit).max()) / MS if jit.size else 0.0
            n_bad = int(np.count_nonzero(np.abs(jit) > tol * MS))
            self.add("jitter", n_bad == 0, "error",
                     f"free-running {s.topic} at {rate:g} Hz: {n_bad} of {jit.size} intervals "
                     f"deviate from whole periods by more than {tol:.3f} ms; worst "
                     f"{worst:.3f} ms", agent=aid, sensor=s.name, value=worst, threshold=tol)
        self.drop_check(agent, s, ts, rate)

    def drop_check(self, agent: AgentConfig, s: SensorConfig, t: np.ndarray,
                   rate: float) -> None:
        n_drop, gaps = dropped_frames(t, NS / rate)
        expected = t.size + n_drop
        frac = n_drop / expected if expected else 0.0
        sev = "error" if frac > self.c.stream.max_dropped_fraction else "warning"
        where = ", ".join(self.span_txt(a, b) for a, b in gaps[:5]) + (" ..." if len(gaps) > 5
                                                                      else "")
        self.add("dropped_frames", n_drop == 0, sev,
                 f"{n_drop} of {expected} expected frames at {rate:g} Hz missing on "
                 f"{s.topic}" + (f": gaps {where}" if gaps else ""),
                 agent=agent.agent_id, sensor=s.name, value=frac,
                 threshold=self.c.stream.max_dropped_fraction)

    def lidar(self, agent: AgentConfig, s: SensorConfig) -> None:
        f = self.frames("lidar_frames", agent.agent_id, s.name, "frame_idx")
        n_pts = _col(f, "n_points")
        empty = np.flatnonzero(n_pts == 0)
        self.add("lidar_empty_frames", empty.size == 0, "warning",
                 f"{empty.size} frames of {s.topic} without a point with a return"
                 + (f" (frames {empty[:10].tolist()})" if empty.size else ""),
                 agent=agent.agent_id, sensor=s.name, value=float(empty.size), threshold=0.0)
        rate = s.rate_hz or measured_rate_hz(_col(f, "stamp_ns"))
        if not rate:
            return
        ok = n_pts > 0
        span = (_col(f, "t_end_ns") - _col(f, "t_start_ns"))[ok] / MS
        expect = 1000.0 / rate * s.scan_fov_deg / 360.0
        lo, hi = self.c.scan_span.min * expect, self.c.scan_span.max * expect
        bad = np.flatnonzero((span < lo) | (span > hi))
        med = float(np.median(span)) if span.size else 0.0
        fov = f", {s.scan_fov_deg:g} deg FOV" if s.scan_fov_deg < 360 else ""
        self.add("scan_time_span", bad.size == 0, "error",
                 f"per-point time span of {s.topic} scans: median {med:.2f} ms, expected "
                 f"{lo:.1f}..{hi:.1f} ms (at {rate:g} Hz{fov}); {bad.size} scans outside"
                 + (f" (frames {np.flatnonzero(ok)[bad][:10].tolist()})" if bad.size else ""),
                 agent=agent.agent_id, sensor=s.name, value=med, threshold=hi)

    def pose(self, agent: AgentConfig) -> None:
        aid = agent.agent_id
        p = agent.effective_pose
        if isinstance(p, NoPose):
            why = "pose: none" if agent.pose is not None else "no pose block and no INS topic"
            self.add("ins_coverage", False, "warning",
                     f"agent {aid}: no pose source ({why} configured): deskew/registration "
                     "impossible", agent=aid)
            return
        base = pose_time_base(agent)
        label = base.name if base is not None else None
        topic = base.topic if base is not None else f"pose ({p.kind})"
        ins_t = np.unique(self.pose_times(aid))
        if ins_t.size == 0:
            self.add("ins_coverage", False, "error",
                     f"pose source {topic} ({p.kind}) of agent {aid} gave no pose",
                     agent=aid, sensor=label)
            return
        t_ins = self._of("ins", aid)
        status = _col(t_ins if t_ins.num_rows else self._of("ego_poses", aid), "rtk_status")
        known = status[status != STATUS_UNKNOWN]
        if known.size:
            fixed = float(np.mean(known == self.c.rtk.fixed_status))
            self.add("rtk_fixed", fixed >= self.c.rtk.min_fixed_fraction, "warning",
                     f"{fixed:.1%} of pose samples from {topic} have RTK fixed "
                     f"(status {self.c.rtk.fixed_status})", agent=aid, sensor=label,
                     value=fixed, threshold=self.c.rtk.min_fixed_fraction)
        if isinstance(p, FixedPose):
            max_gap = np.iinfo(np.int64).max  # constant: two samples span the recording
        else:
            rate = base.rate_hz if base is not None and base.rate_hz else measured_rate_hz(ins_t)
            max_gap = int(max(self.c.pose_coverage.max_gap_ms * MS,
                              self.c.pose_coverage.gap_periods * NS / (rate or 1.0)))
        for lid in agent.sensors_of(Modality.LIDAR):
            f = self.frames("lidar_frames", aid, lid.name, "frame_idx")
            if f.num_rows == 0:
                continue
            ts, te = _col(f, "t_start_ns"), _col(f, "t_end_ns")
            bad = ins_uncovered(ins_t, ts, te, max_gap)
            # scans reaching past the pose recording at the clip's two ends (bags are cut
            # independently per topic) vs. scans inside the pose time range
            head = bad & (ts < ins_t[0])
            tail = bad & (te > ins_t[-1])
            inner = bad & ~head & ~tail
            edge_ok = (int(head.sum()) <= self.c.pose_coverage.edge_scans
                       and int(tail.sum()) <= self.c.pose_coverage.edge_scans)
            sev = "error" if inner.any() or not edge_ok else "warning"
            where = "; ".join(self.span_txt(a, b) for a, b in spans(bad, ts, te))
            gap_txt = "" if isinstance(p, FixedPose) else f" (gap > {max_gap / MS:g} ms)"
            what = (f"{int(inner.sum())} inside the pose time range{gap_txt}, "
                    f"{int(head.sum())} before its first and {int(tail.sum())} after its last "
                    "sample")
            self.add("ins_coverage", not bad.any(), sev,
                     f"pose {topic} of agent {aid} does not cover {int(bad.sum())} of "
                     f"{bad.size} {lid.name} scans ({what}): uncovered {where}" if bad.any() else
                     f"pose {topic} brackets all {bad.size} {lid.name} scans",
                     agent=aid, sensor=label, value=float(bad.sum()), threshold=0.0)


def _col(t: pa.Table, name: str) -> np.ndarray:
    if t.num_rows == 0 or name not in t.column_names:
        return np.zeros(0, dtype=np.int64)
    return np.asarray(t.column(name).to_numpy())


def load_landing_config(lake: Lake, clip_id: str) -> ClipConfig:
    path = lake.path("landing", clip_id, "clip.yaml")
    if not lake.exists(path):
        raise ClipError(clip_id, "no landing copy of clip.yaml: run ingest first", path=path,
                        stage=STAGE)
    return ClipConfig.model_validate(load_yaml(lake.read_bytes(path)))


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
            named = [x for x in cfg.agent(first.agent_id).sensors if x.name == first.sensor]
            topic = named[0].topic if named else None
        raise ClipError(clip_id, "; ".join(f"{r.check}: {r.detail}" for r in failed),
                        agent_id=first.agent_id, topic=topic, stage=STAGE, checks=rows)
    return StageReport(
        stage=STAGE, clip_id=clip_id,
        outputs=[OutputFile(path=path[len(lake.base) + 1:], rows=n)],
        metrics={"checks": float(len(rows)), "warnings": float(len(warnings)), "errors": 0.0},
        notes=[f"warning {r.check}" + (f" {r.agent_id}" if r.agent_id else "")
               + (f"/{r.sensor}" if r.sensor else "") + f": {r.detail}" for r in warnings])


QA = Stage(
    name=DECLARATION.name, config_model=QaConfig,
    # and the landing clip.yaml, which ingest turns into clips and calibrated_sensors
    reads=tables("raw", *CHECKED, "clips", "calibrated_sensors"),
    owns=DECLARATION.owns, run=run_qa,
    doc="timing, gaps and coverage checks; an error-severity finding quarantines the clip")
