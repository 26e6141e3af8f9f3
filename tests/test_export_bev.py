"""BEV rasters: layers land where the world geometry is, through the written grid json."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from tests.export_fixtures import build_clean_clip
from v2xlake.storage.lake import Lake
from v2xlake.tasks.export.bev import BevConfig, BevGrid, export_bev


def test_grid_accumulates_max_mean_count() -> None:
    g = BevGrid(0.0, 2.0, 1.0, 2, 2)  # x in [0, 2), y in [0, 2)
    g.add(np.array([[0.5, 1.5, 1.0], [0.6, 1.4, 3.0], [1.5, 0.5, -1.0]]),
          np.array([0.2, 0.4, 0.9]))
    lay = g.layers()
    assert lay["height"][0, 0] == 3.0 and lay["height"][1, 1] == -1.0
    assert np.isclose(lay["intensity"][0, 0], 0.3)
    assert lay["occupancy"].tolist() == [[True, False], [False, True]]
    assert np.isnan(lay["height"][0, 1])


def test_export_bev(tmp_path: Path) -> None:
    lake = Lake(tmp_path / "lake")
    build_clean_clip(lake, "clip-a", with_cameras=False, seconds=1.0)
    rep = export_bev(lake, "clip-a", tmp_path / "bev", BevConfig(resolution_m=0.25))
    d = tmp_path / "bev" / "clip-a"
    meta = json.loads((d / "grid.json").read_text())
    height = np.load(d / "height.npy")
    occ = np.load(d / "occupancy.npy")
    inten = np.load(d / "intensity.npy")
    assert height.shape == occ.shape == inten.shape == (meta["height"], meta["width"])
    assert rep.metrics["n_points"] > 50_000

    def cell(x: float, y: float) -> tuple[int, int]:
        res = meta["resolution_m"]
        return int((meta["y_max"] - y) // res), int((x - meta["x_min"]) // res)

    # the parked car (centre 22, -5; 1.6 m tall; points sampled up to 0.45 h above centre)
    r, c = cell(22.0, -5.0)
    assert 1.2 < height[r, c] <= 0.8 + 0.45 * 1.6 + 1e-3
    assert 0.5 <= inten[r, c] <= 0.9
    # a facade (y = -12, up to 6 m) and the open street ground
    heights = [height[cell(x, -12.01)] for x in np.arange(5.0, 15.0, 0.25)]
    assert np.nanmax(heights) > 4.0
    r, c = cell(10.0, -10.0)
    assert occ[r, c] and abs(height[r, c]) < 0.05
    for name in ("height", "occupancy", "intensity"):
        img = cv2.imread(str(d / f"{name}.png"), cv2.IMREAD_UNCHANGED)
        assert img is not None
        assert img.shape[:2] == height.shape
