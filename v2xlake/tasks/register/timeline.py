"""The registration of a whole clip as one picture: per frame, the frame's own GICP result, the
clip solve's estimate with its 1-sigma and eq. 1a (INS + published extrinsics), and the
decision taken on each frame with its reason; the clip's extrinsic corrections in the title.

Everything is drawn as a correction relative to eq. 1a, in the reference LiDAR frame: the
INS start is the zero line, so a reader sees at once how far registration moved each frame,
whether the solve follows what GICP measured, and why a frame was not accepted. Pure: rows
of ``registrations`` / ``calibration_refined`` in, PNG bytes out.
"""

from __future__ import annotations

import textwrap
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from v2xlake.schemas.geometry import transform
from v2xlake.tasks.geometry import invert, so3_log
from v2xlake.tasks.register.bev import figure_png


def row_transform(r: dict[str, Any], p: str) -> np.ndarray | None:
    """The 4x4 stored under prefix ``p`` (``init_``, ``gicp_``, "") of a ``registrations``
    row as a dict; None where the row has none (no GICP measurement)."""
    if r.get(f"{p}tx") is None:
        return None
    q = np.array([r[f"{p}qw"], r[f"{p}qx"], r[f"{p}qy"], r[f"{p}qz"]], dtype=np.float64)
    return transform(np.array([r[f"{p}tx"], r[f"{p}ty"], r[f"{p}tz"]], dtype=np.float64),
                     q / np.linalg.norm(q))


def correction(T_init: np.ndarray, T: np.ndarray) -> np.ndarray:
    """(6,) ``T`` relative to eq. 1a as [translation cm (x y z), rotation deg (x y z)] in the
    reference LiDAR frame (left: ``T T_init^-1``)."""
    d = T @ invert(T_init)
    return np.concatenate([d[:3, 3] * 100.0, np.degrees(so3_log(d[:3, :3]))])


def decision(r: dict[str, Any]) -> str:
    """A short class of a frame's decision: accepted, outlier, uncertain, no GICP, rejected."""
    if r["accepted"]:
        return "accepted"
    reason = str(r.get("reason") or "")
    if reason.startswith("outlier"):
        return "outlier"
    if reason.startswith("uncertain"):
        return "uncertain"
    if r.get("gicp_tx") is None:
        return "no GICP"
    return "rejected"


COLOURS = {"accepted": "#2ca02c", "uncertain": "#ff7f0e", "outlier": "#d62728",
           "no GICP": "#7f7f7f", "rejected": "#9467bd"}


def render_registration_timeline(rows: list[dict[str, Any]], calibration: list[dict[str, Any]],
                                 path: str | Path | None = None, *, title: str = "") -> bytes:
    """PNG: for each other agent, four panels (x, y, z in cm, yaw in deg) over clip time of
    GICP (dots), the clip estimate (line, 1-sigma band) and eq. 1a (zero), each frame's
    decision as a coloured strip, and a legend counting the reasons."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    others = sorted({str(r["agent_other"]) for r in rows})
    fig, axes = plt.subplots(5, max(len(others), 1), figsize=(11 * max(len(others), 1), 12),
                             dpi=100, squeeze=False, sharex="col",
                             gridspec_kw={"height_ratios": [3, 3, 3, 3, 1]})
    for c, other in enumerate(others):
        rs = sorted((r for r in rows if r["agent_other"] == other), key=lambda r: r["t_ns"])
        t = np.array([r["t_ns"] for r in rs], dtype=np.float64) * 1e-9
        init = [row_transform(r, "init_") for r in rs]
        fin = np.array([correction(i, f) for r, i in zip(rs, init, strict=True)
                        if i is not None and (f := row_transform(r, "")) is not None])
        gicp = np.array([correction(i, g)
                         if (g := row_transform(r, "gicp_")) is not None and i is not None
                         else np.full(6, np.nan) for r, i in zip(rs, init, strict=True)])
        std_cm = np.array([(r.get("std_m") or np.nan) * 100 for r in rs], dtype=np.float64)
        std_deg = np.array([r.get("std_deg") or np.nan for r in rs], dtype=np.float64)
        kinds = [decision(r) for r in rs]
        for k, (ax, col, unit, std) in enumerate((
                (axes[0, c], 0, "x (cm)", std_cm), (axes[1, c], 1, "y (cm)", std_cm),
                (axes[2, c], 2, "z (cm)", std_cm), (axes[3, c], 5, "yaw (deg)", std_deg))):
            ax.axhline(0.0, color="black", lw=0.8, label="eq. 1a (INS + published)")
            ax.plot(t, gicp[:, col], ".", ms=4, color="#1f77b4", label="frame's own GICP")
            if len(fin):
                ax.plot(t, fin[:, col], "-", lw=1.3, color="#2ca02c", label="clip estimate")
                ax.fill_between(t, fin[:, col] - std, fin[:, col] + std, color="#2ca02c",
                                alpha=0.25, lw=0, label="clip estimate 1-sigma")
            ax.set_ylabel(unit)
            ax.grid(alpha=0.3)
            if k == 0:
                ax.set_title(f"{other} -> reference: correction of eq. 1a per frame")
                ax.legend(loc="upper right", fontsize=8)
        strip = axes[4, c]
        for kind in COLOURS:
            m = np.array([x == kind for x in kinds])
            if m.any():
                strip.scatter(t[m], np.zeros(int(m.sum())), marker="|", s=400,
                              color=COLOURS[kind], label=f"{kind} ({int(m.sum())})")
        strip.set_yticks([])
        strip.set_xlabel("clip time (s)")
        strip.legend(loc="upper center", ncol=len(COLOURS), fontsize=8,
                     bbox_to_anchor=(0.5, -0.6))
        reasons = Counter(str(r.get("reason") or "").split(":")[0] for r in rs
                          if not r["accepted"])
        if reasons:
            strip.set_title("not accepted: " + ", ".join(f"{k} x{v}" for k, v in
                                                         reasons.most_common(4)), fontsize=8)
    cal = "; ".join(
        f"{c['agent_id']} {c['sensor']}: {'refined' if c['usable'] else 'published'} "
        f"({c['correction_m'] * 100:.1f} cm / {c['correction_deg']:.3f} deg"
        + (f", {c['reason']}" if c.get("reason") else "") + ")"
        for c in calibration if c["correction_m"] > 0 or c["correction_deg"] > 0
        or c.get("reason"))
    text = (title + "\n" if title else "") + \
        "\n".join(textwrap.wrap(f"extrinsics: {cal}", 140) if cal else [])
    fig.suptitle(text, fontsize=10)
    # fixed margins in inches (the figure is 11 in per agent by 12 in): tick and axis labels
    # on the left, the title's lines on top, the strip's legend below (see figure_png)
    w, lines = 11.0 * max(len(others), 1), text.count("\n") + 1
    fig.subplots_adjust(left=0.75 / w, right=1 - 0.15 / w, bottom=1.0 / 12,
                        top=1 - (0.6 + 0.18 * lines) / 12, wspace=0.85 / 10.5, hspace=0.3)
    return figure_png(fig, path)
