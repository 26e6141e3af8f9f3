"""Published vs refined LiDAR extrinsics of a clip (issue #13), for a CLI command.

The register stage's clip solve writes ``calibration_refined`` (its own table; ingest's
``calibrated_sensors`` is never rewritten). ``compare_calibration`` lines both up per sensor
with the correction, its 1-sigma, the components the clip determined and which one the
consumers after register use (``storage.reader.effective_calibration``); ``format_calibration``
is the text a ``v2xlake calibration --lake ... --clip ...`` command prints.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyarrow.compute as pc

from v2xlake.schemas.geometry import transform
from v2xlake.storage.lake import Lake
from v2xlake.storage.reader import (
    CalibrationChoice,
    calibrations,
    effective_calibration,
    read,
)
from v2xlake.tasks.geometry import invert, rotation_angle, so3_log


@dataclass(frozen=True)
class CalibrationComparison:
    agent_id: str
    sensor: str
    published: np.ndarray  # T_ego_sensor 4x4
    refined: np.ndarray | None  # None: the clip has no refinement for this sensor
    correction_m: float
    correction_deg: float
    std_m: float
    std_deg: float
    refined_components: str
    usable: bool
    effective: str  # "refined" | "published": what annotate, align and the exports use
    reason: str = ""  # why (part of) the published extrinsic is kept

    @property
    def delta_lidar(self) -> np.ndarray:
        """(6,) refined relative to published in the LiDAR frame: [rot deg, trans m]."""
        if self.refined is None:
            return np.zeros(6)
        d = invert(self.published) @ self.refined
        return np.concatenate([np.degrees(so3_log(d[:3, :3])), d[:3, 3]])


def compare_calibration(lake: Lake, clip_id: str,
                        choice: CalibrationChoice | None = None
                        ) -> list[CalibrationComparison]:
    """Every LiDAR of every agent of the clip: published, refined (if any), effective."""
    choice = choice or CalibrationChoice()
    out = []
    cal = read(lake, "calibrated_sensors", clip_id)
    ref = read(lake, "calibration_refined", clip_id)
    agents = sorted(set(cal["agent_id"].to_pylist())) if cal.num_rows else []
    for a in agents:
        pub_all = calibrations(cal.filter(pc.equal(cal["agent_id"], a)), clip_id, a)
        pub = {s: c for s, c in pub_all.items() if c.modality == "lidar"}
        ref_a = ref.filter(pc.equal(ref["agent_id"], a)) if ref.num_rows else ref
        _, source = effective_calibration(pub, ref_a, choice)
        rows = {r["sensor"]: r for r in ref_a.to_pylist()} if ref_a.num_rows else {}
        for s, c in sorted(pub.items()):
            r = rows.get(s)
            refined = None
            if r is not None:
                q = np.array([r["qw"], r["qx"], r["qy"], r["qz"]], dtype=np.float64)
                refined = transform(np.array([r["tx"], r["ty"], r["tz"]], dtype=np.float64),
                                    q / np.linalg.norm(q))
            d = invert(c.T_ego_sensor) @ refined if refined is not None else np.eye(4)
            out.append(CalibrationComparison(
                a, s, c.T_ego_sensor, refined, float(np.linalg.norm(d[:3, 3])),
                float(np.degrees(rotation_angle(d))), float(r["std_m"]) if r else float("nan"),
                float(r["std_deg"]) if r else float("nan"),
                str(r["refined_components"]) if r else "", bool(r["usable"]) if r else False,
                source[s], str((r or {}).get("reason") or "")))
    return out


def format_calibration(rows: list[CalibrationComparison]) -> str:
    """A table: agent, sensor, correction (LiDAR frame: rotation deg, translation cm), its
    1-sigma, determined components, and which calibration the consumers use."""
    head = (f"{'agent':10s} {'sensor':12s} {'rx':>7s} {'ry':>7s} {'rz':>7s} {'tx cm':>7s} "
            f"{'ty cm':>7s} {'tz cm':>7s} {'1-sigma':>15s} {'refined':16s} used")
    lines = [head, "-" * len(head)]
    for r in rows:
        d = r.delta_lidar
        sig = (f"{r.std_m * 100:.1f}cm/{r.std_deg:.3f}d" if r.refined is not None
               else "-")
        lines.append(f"{r.agent_id:10s} {r.sensor:12s} {d[0]:7.3f} {d[1]:7.3f} {d[2]:7.3f} "
                     f"{d[3] * 100:7.1f} {d[4] * 100:7.1f} {d[5] * 100:7.1f} {sig:>15s} "
                     f"{(r.refined_components or '-'):16s} {r.effective}"
                     + (f"  ({r.reason})" if r.reason else ""))
    return "\n".join(lines)


def frame_rows(lake: Lake, clip_id: str) -> list[dict[str, object]]:
    """Per registered frame pair: eq. 1a (INS + published extrinsics), the frame's own GICP
    and the clip estimate, each as the correction of eq. 1a (cm, deg in the reference LiDAR
    frame), the estimate's 1-sigma, and the decision with its reason."""
    from v2xlake.tasks.register.timeline import correction, row_transform

    out: list[dict[str, object]] = []
    rows = read(lake, "registrations", clip_id).to_pylist()
    for r in sorted(rows, key=lambda r: (r["agent_other"], r["frame_idx"])):
        init = row_transform(r, "init_")
        fin, gicp = row_transform(r, ""), row_transform(r, "gicp_")
        if init is None or fin is None:
            continue
        f = correction(init, fin)
        g = correction(init, gicp) if gicp is not None else None
        out.append({
            "agent_other": r["agent_other"], "frame_idx": r["frame_idx"],
            "t_s": r["t_ns"] * 1e-9,
            "gicp_cm": None if g is None else float(np.linalg.norm(g[:3])),
            "gicp_deg": None if g is None else float(np.linalg.norm(g[3:])),
            "final_cm": float(np.linalg.norm(f[:3])), "final_deg": float(np.linalg.norm(f[3:])),
            "final_minus_gicp_cm": None if g is None else float(np.linalg.norm(f[:3] - g[:3])),
            "std_cm": None if r.get("std_m") is None else float(r["std_m"]) * 100,
            "std_deg": r.get("std_deg"), "accepted": bool(r["accepted"]),
            "reason": str(r["reason"])})
    return out


def format_frames(rows: list[dict[str, object]]) -> str:
    """A table of :func:`frame_rows`: what registration moved each frame by, from where."""
    head = (f"{'other':8s} {'frame':>5s} {'t s':>6s} {'GICP cm':>8s} {'clip cm':>8s} "
            f"{'clip-GICP':>9s} {'1-sigma':>8s} {'acc':>4s} reason")
    lines = [head, "-" * len(head)]

    def num(x: object, f: str) -> str:
        return "-" if x is None else format(x, f)

    for r in rows:
        lines.append(f"{r['agent_other']!s:8s} {r['frame_idx']:5d} {r['t_s']:6.2f} "
                     f"{num(r['gicp_cm'], '8.1f')} {num(r['final_cm'], '8.1f')} "
                     f"{num(r['final_minus_gicp_cm'], '9.1f')} {num(r['std_cm'], '8.1f')} "
                     f"{'yes' if r['accepted'] else 'no':>4s} {r['reason']}")
    return "\n".join(lines)
