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
from v2xlake.tasks.register.raster import Canvas, Panel, limits, rgb


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
    decision as a coloured strip, and a legend counting the reasons. 1100 px wide per other
    agent, 1200 px high (``raster``: a 3 s clip with two other agents in 0.1 s of one core,
    matplotlib took 1.0-1.2 s)."""
    others = sorted({str(r["agent_other"]) for r in rows})
    cal = "; ".join(
        f"{c['agent_id']} {c['sensor']}: {'refined' if c['usable'] else 'published'} "
        f"({c['correction_m'] * 100:.1f} cm / {c['correction_deg']:.3f} deg"
        + (f", {c['reason']}" if c.get("reason") else "") + ")"
        for c in calibration if c["correction_m"] > 0 or c["correction_deg"] > 0
        or c.get("reason"))
    lines = ([title] if title else []) + (textwrap.wrap(f"extrinsics: {cal}", 140) if cal
                                          else [])
    ncol = max(len(others), 1)
    W, H = 1100 * ncol, 1200
    canvas = Canvas(W, H)
    for i, line in enumerate(lines):
        canvas.text(W / 2, 18 + 17 * i, line, 14, anchor="mt")
    # the panels' boxes: fixed margins (tick and axis labels left, the title's lines on
    # top, the strip's legend below), five rows of heights 3:3:3:3:1 with 0.3 of a mean
    # row between rows, 0.85 in between agents
    left, right, bottom, top = 75, 15, 100, 60 + 18 * max(len(lines), 1)
    sep_w = 85
    ax_w = (W - left - right - sep_w * (ncol - 1)) / ncol
    cell = (H - top - bottom) / (5 + 4 * 0.3)
    heights = [cell * 5 / 13 * k for k in (3, 3, 3, 3, 1)]
    ys = [float(top)]
    for h in heights[:-1]:
        ys.append(ys[-1] + h + 0.3 * cell)
    sigma_fill = _blend(GREEN, 0.25)
    for c, other in enumerate(others):
        rs = sorted((r for r in rows if r["agent_other"] == other), key=lambda r: r["t_ns"])
        t = np.array([r["t_ns"] for r in rs], dtype=np.float64) * 1e-9
        init = [row_transform(r, "init_") for r in rs]
        final = [row_transform(r, "") for r in rs]
        has_fin = np.array([i is not None and f is not None
                            for f, i in zip(final, init, strict=True)], dtype=bool)
        fin = np.array([correction(i, f) for f, i in zip(final, init, strict=True)
                        if i is not None and f is not None])
        gicp = np.array([correction(i, g)
                         if (g := row_transform(r, "gicp_")) is not None and i is not None
                         else np.full(6, np.nan) for r, i in zip(rs, init, strict=True)])
        std_cm = np.array([(r.get("std_m") or np.nan) * 100 for r in rs], dtype=np.float64)
        std_deg = np.array([r.get("std_deg") or np.nan for r in rs], dtype=np.float64)
        kinds = [decision(r) for r in rs]
        x0 = round(left + c * (ax_w + sep_w))
        x1 = round(x0 + ax_w)
        xlim = limits([t])
        for k, (col, unit, std) in enumerate(((0, "x (cm)", std_cm), (1, "y (cm)", std_cm),
                                              (2, "z (cm)", std_cm),
                                              (5, "yaw (deg)", std_deg))):
            tf = t[has_fin] if len(fin) else t[:0]
            est = fin[:, col] if len(fin) else np.zeros(0)
            sd = std[has_fin] if len(fin) else np.zeros(0)
            ylim = limits([np.zeros(1), gicp[:, col], est - sd, est + sd])
            ax = Panel(canvas, x0, round(ys[k]), x1, round(ys[k] + heights[k]),
                       xlim, ylim)
            ax.axes(xlabels=False, grid=True)
            if len(fin):
                ax.band(tf, est - sd, est + sd, GREEN, 0.25)
            ax.hline(0.0, (0, 0, 0), 1.0)
            if len(fin):
                ax.line(tf, est, GREEN, 2.0)
            ok = np.isfinite(gicp[:, col])
            ax.markers(t[ok], gicp[ok, col], "o", 5.5, BLUE)
            ax.frame()
            ax.ylabel(unit, 14)
            if k == 0:
                canvas.text((x0 + x1) / 2, ax.y0 - 7,
                            f"{other} -> reference: correction of eq. 1a per frame", 17,
                            anchor="md")
                ax.legend([("hline", "eq. 1a (INS + published)", (0, 0, 0)),
                           ("dot", "frame's own GICP", BLUE),
                           ("line", "clip estimate", GREEN),
                           ("patch", "clip estimate 1-sigma", sigma_fill)], 11)
        strip = Panel(canvas, x0, round(ys[4]), x1, round(ys[4] + heights[4]),
                      xlim, (-1.0, 1.0))
        strip.axes(yticks=np.zeros(0))
        counts = Counter(kinds)
        for kind, colour in COLOURS.items():
            m = np.array([x == kind for x in kinds], dtype=bool)
            if m.any():
                strip.markers(t[m], np.zeros(int(m.sum())), "|", 28, rgb(colour))
        strip.frame()
        canvas.text((x0 + x1) / 2, strip.y1 + 24, "clip time (s)", 14, anchor="mt")
        strip.legend([("|", f"{kind} ({counts[kind]})", rgb(colour))
                      for kind, colour in COLOURS.items() if counts[kind]], 11,
                     ncol=len(COLOURS), at=((x0 + x1) / 2, strip.y1 + 44))
        reasons = Counter(str(r.get("reason") or "").split(":")[0] for r in rs
                          if not r["accepted"])
        if reasons:
            canvas.text((x0 + x1) / 2, strip.y0 - 5, "not accepted: " + ", ".join(
                f"{k} x{v}" for k, v in reasons.most_common(4)), 11, anchor="md")
    return canvas.png(path)


BLUE, GREEN = rgb("#1f77b4"), rgb("#2ca02c")


def _blend(colour: tuple[int, int, int], alpha: float) -> tuple[int, int, int]:
    """``colour`` at opacity ``alpha`` over white."""
    r, g, b = (round(255 + (v - 255) * alpha) for v in colour)
    return r, g, b
