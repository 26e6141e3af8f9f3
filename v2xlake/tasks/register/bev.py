"""Bird's-eye view of two agents' deskewed scans before / after GICP (main paper Fig. 5)."""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import numpy as np

from v2xlake.tasks.geometry import apply


def _thin(xyz: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    p = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    p = p[np.isfinite(p).all(axis=1)]
    if len(p) > n:
        p = p[np.random.default_rng(seed).choice(len(p), n, replace=False)]
    return p


def render_registration_bev(ref_xyz: np.ndarray, other_xyz: np.ndarray, T_init: np.ndarray,
                            T_refined: np.ndarray, path: str | Path | None = None, *,
                            extent_m: float = 50.0, title: str = "",
                            max_points: int = 60_000) -> bytes:
    """PNG with two panels: the other agent's scan placed by ``T_init`` (eq. 1a) and by
    ``T_refined`` (eq. 1b) over the reference scan, both in the reference LiDAR frame.

    Returns the PNG bytes; also writes them to ``path`` if given. Ground points (lowest
    5 % + 0.3 m) are drawn faint so facades and poles, where misregistration shows, stand out.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ref = _thin(ref_xyz, max_points)
    oth = _thin(other_xyz, max_points, seed=1)
    fig, axes = plt.subplots(1, 2, figsize=(12, 6), dpi=110, sharex=True, sharey=True)
    # fixed margins (inches on this fixed-size figure) for the tick labels, axis labels and
    # titles, instead of tight_layout (see figure_png)
    fig.subplots_adjust(left=0.07, right=0.99, bottom=0.09, top=0.86 if title else 0.9,
                        wspace=0.05)
    for ax, T, name in ((axes[0], T_init, "initial (eq. 1a)"), (axes[1], T_refined,
                                                                  "GICP refined (eq. 1b)")):
        moved = apply(T, oth)
        for pts, color, label in ((ref, "#d62728", "reference"), (moved, "#1f77b4", "other")):
            keep = (np.abs(pts[:, 0]) < extent_m) & (np.abs(pts[:, 1]) < extent_m)
            p = pts[keep]
            if not len(p):
                continue
            # ground rings say little about alignment: draw them faint, structures strong
            ground = p[:, 2] < np.percentile(p[:, 2], 5) + 0.3
            ax.scatter(p[ground, 0], p[ground, 1], s=0.2, c=color, alpha=0.08, linewidths=0)
            ax.scatter(p[~ground, 0], p[~ground, 1], s=0.4, c=color, alpha=0.6, linewidths=0,
                       label=label)
        ax.plot(0, 0, marker="^", color="#d62728", ms=8)
        ax.plot(T[0, 3], T[1, 3], marker="^", color="#1f77b4", ms=8)
        ax.set_title(name)
        ax.set_aspect("equal")
        ax.set_xlim(-extent_m, extent_m)
        ax.set_ylim(-extent_m, extent_m)
        ax.set_xlabel("x (m, reference LiDAR)")
    axes[0].set_ylabel("y (m)")
    axes[1].legend(loc="upper right", markerscale=20)
    if title:
        fig.suptitle(title)
    return figure_png(fig, path)


def figure_png(fig: Any, path: str | Path | None = None) -> bytes:
    """The figure rendered as PNG bytes (also written to ``path`` if given), then closed: the
    register stage stores the bytes in the lake, the CLI writes a file. The figures set
    their margins themselves: ``tight_layout`` measured every tick label and title first, a
    third of the rendering (0.1 of 0.35 s for this BEV, 0.26 of 0.95 s for a two-agent
    timeline, one core), and the register stage renders both for every clip."""
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    data = buf.getvalue()
    if path is not None:
        Path(path).write_bytes(data)
    return data
