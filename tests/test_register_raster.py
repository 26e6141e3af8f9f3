"""The register stage's own raster plotter (``register/raster.py``) and the two PNGs drawn with
it: tick choice, point compositing, data-to-pixel mapping, and that the pictures carry each
agent's points where the transforms put them."""

from __future__ import annotations

import numpy as np
import pytest

from v2xlake.tasks.pngcodec import decode_png
from v2xlake.tasks.register.bev import OTHER, REF, render_registration_bev
from v2xlake.tasks.register.raster import (
    Canvas,
    Panel,
    limits,
    nice_ticks,
    splat,
    tick_labels,
)
from v2xlake.tasks.register.timeline import render_registration_timeline


def test_ticks_and_labels() -> None:
    assert nice_ticks(-50, 50).tolist() == [-40, -20, 0, 20, 40]
    assert nice_ticks(-0.045, 3.145).tolist() == pytest.approx(
        [0, 0.5, 1, 1.5, 2, 2.5, 3])
    t = nice_ticks(-0.055, 0.055, max_ticks=6)
    assert t.tolist() == pytest.approx([-0.05, -0.025, 0, 0.025, 0.05])
    assert tick_labels(t) == ["\u22120.050", "\u22120.025", "0.000", "0.025", "0.050"]
    assert tick_labels(np.array([-5.0, 0.0, 5.0])) == ["\u22125", "0", "5"]
    assert limits([np.array([0.0, 10.0]), np.array([np.nan])]) == pytest.approx((-0.5, 10.5))
    assert limits([np.zeros(3)]) == (-1.0, 1.0)


def test_splat_composites_counts_and_drops_outside() -> None:
    img = np.full((4, 5, 3), 255, np.uint8)
    # three points in pixel (row 1, col 2), one in (3, 0), two outside
    col = np.array([2.2, 2.9, 2.5, 0.1, -0.5, 5.0])
    row = np.array([1.1, 1.7, 1.0, 3.9, 1.0, 1.0])
    splat(img, col, row, (0, 0, 255), 0.5)
    a3 = 1 - 0.5**3
    assert img[1, 2].tolist() == [round(255 * (1 - a3))] * 2 + [255]
    assert img[3, 0].tolist() == [128, 128, 255]
    assert (img.reshape(-1, 3) != 255).any(axis=1).sum() == 2


def test_panel_maps_data_to_its_box() -> None:
    c = Canvas(200, 100)
    ax = Panel(c, 20, 10, 120, 60, (0.0, 10.0), (-1.0, 1.0))
    x, y = ax.px([0.0, 10.0, 5.0], [-1.0, 1.0, 0.0])
    assert x.tolist() == [20, 120, 70] and y.tolist() == [60, 10, 35]
    ax.points(np.array([5.0, 50.0]), np.array([0.0, 0.0]), (255, 0, 0), 1.0)
    assert c.img[35, 70].tolist() == [255, 0, 0]
    assert (c.img != 255).any(axis=2).sum() == 1  # the point outside the box is clipped
    ax.line([0.0, 100.0], [0.5, 0.5], (0, 0, 0), 1.0)
    assert (c.img[:, 121:] == 255).all()  # clipped at the box's right edge
    png = c.png()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and decode_png(png).shape == (100, 200, 3)


def test_bev_draws_each_scan_where_its_transform_puts_it() -> None:
    # the reference sees a wall at y = +20 m, the other agent the same wall from 10 m to the
    # side (its frame: y = +10 m); T_init leaves it 4 m off, T_refined puts it on the wall
    xs = np.linspace(-30, 30, 3000)
    wall = np.stack([xs, np.full_like(xs, 20.0), np.full_like(xs, 1.5)], axis=1)
    ground = np.stack([xs, np.full_like(xs, -5.0), np.zeros_like(xs)], axis=1)
    ref = np.concatenate([wall, ground, [[np.nan, 0, 0]]])
    oth = ref.copy()
    oth[:, 1] -= 10.0
    T_ref = np.eye(4)
    T_ref[1, 3] = 10.0
    T_init = T_ref.copy()
    T_init[1, 3] = 14.0
    img = decode_png(render_registration_bev(ref, oth, T_init, T_ref, title="t"))
    assert img.shape == (660, 1320, 3)
    rgb = img[:, :, ::-1].astype(int)

    def rows_of(colour: tuple[int, int, int], cols: slice) -> set[int]:
        # rows where a strongly coloured pixel of ``colour``'s hue lies
        d = np.abs(rgb[:, cols] - np.array(colour)).sum(axis=2)
        return set(np.flatnonzero((d < 60).any(axis=1)).tolist())

    # columns of x = -25 .. -8 m in each panel: the wall, away from the agents' markers and
    # the legend
    left, right = slice(290, 370), slice(860, 940)
    ref_rows, oth_rows_l = rows_of(REF, left), rows_of(OTHER, left)
    # initial: the other's wall 4 m (20 px) above the reference's; refined: drawn over it
    # (the other agent's points are drawn last)
    assert ref_rows and max(oth_rows_l) < min(ref_rows) - 15
    assert rows_of(OTHER, right) == ref_rows and not rows_of(REF, right)


def test_timeline_renders_every_other_agent() -> None:
    rows = []
    for k, other in enumerate(("black", "rsu")):
        for f in range(6):
            r = {"agent_other": other, "t_ns": f * 100_000_000, "accepted": f != 2,
                 "reason": "" if f != 2 else "uncertain: y", "std_m": 0.01, "std_deg": 0.02}
            for p, dx in (("init_", 0.0), ("gicp_", 0.02 * (k + 1)), ("", 0.01)):
                r.update({f"{p}tx": 10.0 + dx, f"{p}ty": 0.0, f"{p}tz": 0.0, f"{p}qw": 1.0,
                          f"{p}qx": 0.0, f"{p}qy": 0.0, f"{p}qz": 0.0})
            rows.append(r)
    cal = [{"agent_id": "black", "sensor": "LIDAR_TOP", "usable": True, "correction_m": 0.05,
            "correction_deg": 0.4, "reason": ""}]
    img = decode_png(render_registration_timeline(rows, cal, title="clip"))
    assert img.shape == (1200, 2200, 3)
    # the uncertain frame's orange strip mark in both columns
    orange = (np.abs(img[:, :, ::-1].astype(int) - [255, 127, 14]).sum(axis=2) < 40)
    assert orange[:, :1100].any() and orange[:, 1100:].any()
