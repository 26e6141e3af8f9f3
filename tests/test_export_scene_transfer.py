"""Scene transfer (eq. 6): a rainy pass over the same street, started 3.5 m further back,
matches each overcast reference frame with the frame taken at the same place."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from tests.export_fixtures import SPEED, T0_NS, build_clean_clip
from v2xlake.storage.lake import Lake
from v2xlake.tasks.export.scene_transfer import (
    SceneTransferConfig,
    edge_map,
    export_scene_transfer,
    similarity,
)


def test_similarity_is_cosine() -> None:
    a = np.array([[1.0, 0.0], [2.0, 0.0]])
    assert similarity(a, 3 * a) == pytest.approx(1.0)
    assert similarity(a, np.array([[0.0, 1.0], [0.0, 0.0]])) == pytest.approx(0.0)
    img = (np.random.default_rng(0).random((90, 160)) * 255).astype(np.uint8)
    e = edge_map(img, SceneTransferConfig())
    assert e.shape == (80 * 45,) and np.linalg.norm(e) == pytest.approx(1.0)


def test_pairs_match_the_same_place(tmp_path: Path) -> None:
    lake = Lake(tmp_path / "lake")
    build_clean_clip(lake, "sunny-ref", weather="overcast", seconds=2.0, n_ground=500)
    shift_m = -3.5  # the rainy pass is 0.7 s behind at 5 m/s
    build_clean_clip(lake, "rainy", weather="rain", x_offset=shift_m, seconds=2.0,
                     n_ground=500, seed=3)
    rep = export_scene_transfer(lake, ["sunny-ref", "rainy"], tmp_path / "st")
    pairs = pq.read_table(tmp_path / "st" / "pairs.parquet").to_pylist()
    assert len(pairs) == 2 and rep.metrics["pairs"] == 2  # 1 Hz over 2 s: t = 1 s, 2 s
    for p in pairs:
        assert p["condition"] == "rain/day" and p["match_clip"] == "rainy"
        # same place: x_ref(t_r) = x_rain(t_m)  =>  t_m = t_r - shift / speed
        t_r = (p["ref_t_ns"] - T0_NS) / 1e9
        t_m = (p["match_t_ns"] - T0_NS) / 1e9
        expect = t_r - shift_m / SPEED
        if expect <= 1.97:  # inside the rainy clip
            assert abs(t_m - expect) <= 2.5 / 30, (t_r, t_m, expect)
        assert p["score"] > p["second_score"] - 1e-9
    assert (tmp_path / "st" / "contact_sheet.png").stat().st_size > 1000
    assert (tmp_path / "st" / "pairs.csv").read_text().count("\n") == 3
    assert len(list((tmp_path / "st" / "pairs").rglob("*.png"))) == 4
