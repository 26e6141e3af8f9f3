"""Published vs refined LiDAR extrinsics of a clip (issue #13), as ``v2xlake calibration``
prints them. Pure: it formats records that were read elsewhere.

The register stage's clip solve writes ``calibration_refined`` (its own table; ingest's
``calibrated_sensors`` is never rewritten). ``compare_calibration`` (in the shared clip reader,
:mod:`v2xlake.tasks.reader`, so the Python API uses it too) lines both up per sensor with the
correction, its 1-sigma, the components the clip determined and which one the consumers after
register use; ``format_calibration`` is its text. ``frame_table`` turns the stored
``registrations`` rows (``stage.frame_rows`` reads them) into what registration moved each
frame pair by; ``format_frames`` is its text.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from v2xlake.tasks.reader import CalibrationComparison

__all__ = ["format_calibration", "format_frames", "frame_table"]

def format_calibration(rows: list[CalibrationComparison]) -> str:
    """A table: agent, sensor, correction (LiDAR frame: rotation deg, translation cm), its
    1-sigma, determined components, and which calibration the consumers use."""
    head = (f"{'agent':10s} {'sensor':12s} {'rx':>7s} {'ry':>7s} {'rz':>7s} {'tx cm':>7s} "
            f"{'ty cm':>7s} {'tz cm':>7s} {'1-sigma':>15s} {'refined':16s} {'by':24s} used")
    lines = [head, "-" * len(head)]
    for r in rows:
        d = r.delta_lidar
        sig = (f"{r.std_m * 100:.1f}cm/{r.std_deg:.3f}d"
               if r.refined is not None and np.isfinite([r.std_m, r.std_deg]).all() else "-")
        lines.append(f"{r.agent_id:10s} {r.sensor:12s} {d[0]:7.3f} {d[1]:7.3f} {d[2]:7.3f} "
                     f"{d[3] * 100:7.1f} {d[4] * 100:7.1f} {d[5] * 100:7.1f} {sig:>15s} "
                     f"{(r.refined_components or '-'):16s} {(r.method or '-')[:24]:24s} "
                     f"{r.effective}"
                     + (f"  ({r.reason})" if r.reason else ""))
    return "\n".join(lines)


def frame_table(rows: list[dict[str, Any]]) -> list[dict[str, object]]:
    """Per registered frame pair (``rows``: the clip's ``registrations`` rows): eq. 1a (INS
    + published extrinsics), the frame's own GICP and the clip estimate, each as the
    correction of eq. 1a (cm, deg in the reference LiDAR frame), the estimate's 1-sigma, and
    the decision with its reason."""
    from v2xlake.tasks.register.timeline import correction, row_transform

    out: list[dict[str, object]] = []
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
    """A table of :func:`frame_table`: what registration moved each frame by, from where."""
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
