"""Bird's-eye view of two agents' deskewed scans before / after GICP (main paper Fig. 5)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from v2xlake.tasks.geometry import apply
from v2xlake.tasks.register.raster import Canvas, Panel, rgb

REF, OTHER = rgb("#d62728"), rgb("#1f77b4")
# opacity of one point in its pixel: ground rings faint, structures strong (n points in a
# pixel: 1 - (1 - alpha)^n)
GROUND_ALPHA, STRUCTURE_ALPHA = 0.05, 0.6


def _finite(xyz: np.ndarray) -> np.ndarray:
    p = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    return p[np.isfinite(p).all(axis=1)]


def _layers(pts: np.ndarray, extent_m: float) -> tuple[np.ndarray, ...]:
    """The points within ``extent_m`` (x and y) as (ground, structure) layers (none when
    there are none): ground rings say little about alignment, so they are drawn faint and
    structures strong; ground is the lowest 5 % + 0.3 m."""
    p = pts[(np.abs(pts[:, 0]) < extent_m) & (np.abs(pts[:, 1]) < extent_m)]
    if not len(p):
        return ()
    ground = p[:, 2] < np.percentile(p[:, 2], 5) + 0.3
    return p[ground], p[~ground]


def render_registration_bev(ref_xyz: np.ndarray, other_xyz: np.ndarray, T_init: np.ndarray,
                            T_refined: np.ndarray, path: str | Path | None = None, *,
                            extent_m: float = 50.0, title: str = "") -> bytes:
    """PNG with two panels: the other agent's scan placed by ``T_init`` (eq. 1a) and by
    ``T_refined`` (eq. 1b) over the reference scan, both in the reference LiDAR frame.

    Returns the PNG bytes; also writes them to ``path`` if given. Ground points (lowest
    5 % + 0.3 m) are drawn faint so facades and poles, where misregistration shows, stand out.
    Every point is drawn (counted into its pixel, ``raster.splat``): 1320 x 660 px, 0.2 m a
    pixel at the default 50 m extent.
    """
    ref = _finite(ref_xyz)
    oth = _finite(other_xyz)
    c = Canvas(1320, 660)
    # two square panels side by side under the title, room for the tick and axis labels
    top = 92 if title else 66
    side = 660 - top - 60
    gap = 62
    x0 = 92 + (1320 - 92 - 14 - 2 * side - gap) // 2
    ref_layers = _layers(ref, extent_m)  # the same in both panels
    for k, (T, name) in enumerate(((T_init, "initial (eq. 1a)"),
                                   (T_refined, "GICP refined (eq. 1b)"))):
        px0 = x0 + k * (side + gap)
        ax = Panel(c, px0, top, px0 + side, top + side, (-extent_m, extent_m),
                   (-extent_m, extent_m))
        ax.axes(ylabels=k == 0, tick_px=15)
        for layers, color in ((ref_layers, REF), (_layers(apply(T, oth), extent_m), OTHER)):
            for p, alpha in zip(layers, (GROUND_ALPHA, STRUCTURE_ALPHA), strict=False):
                ax.points(p[:, 0], p[:, 1], color, alpha)
        ax.markers([0.0], [0.0], "^", 12, REF)
        ax.markers([T[0, 3]], [T[1, 3]], "^", 12, OTHER)
        ax.frame()
        c.text((ax.x0 + ax.x1) / 2, top - 8, name, 18, anchor="md")
        c.text((ax.x0 + ax.x1) / 2, ax.y1 + 30, "x (m, reference LiDAR)", 15, anchor="mt")
        if k == 0:
            ax.ylabel("y (m)", 15)
        else:
            ax.legend([("dot", "reference", REF), ("dot", "other", OTHER)], 15)
    if title:
        c.text(660, 14, title, 18, anchor="mt")
    return c.png(path)
