"""The register stage's bookkeeping that must not change a result: the clip's small tables
read once per run (``Lake.reading_once``) and the ground plane fitted over the kept rows
only (``static._ground_fit``)."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest

from v2xlake.storage.lake import Lake
from v2xlake.tasks.register.static import _ground_fit, above_ground, ground_distance


def _agents(n: int) -> pa.Table:
    return pa.table({"agent_id": [f"a{i}" for i in range(n)], "has_ins": [True] * n})


def test_reading_once_memoises_named_tables_in_the_block_only(tmp_path: Path) -> None:
    lake = Lake(tmp_path / "lake")
    lake.write_table("clean", "agents", _agents(2), clip_id="c", name="agents")
    lake.write_table("clean", "clips", pa.table({"reference_agent": ["a0"]}), clip_id="c",
                     name="clips")
    before = lake.read_table("clean", "agents", clip_id="c")
    assert lake.read_table("clean", "agents", clip_id="c") is not before  # no block: reads
    seen: list[pa.Table] = []
    with lake.reading_once("clean", ["agents"]):
        first = lake.read_table("clean", "agents", clip_id="c")
        assert first.equals(before)
        assert lake.read_table("clean", "agents", clip_id="c") is first
        # other columns, filters, another table, another lake, another thread: read again
        cols = lake.read_table("clean", "agents", clip_id="c", columns=["has_ins"])
        assert cols.column_names == ["has_ins"]
        assert lake.read_table("clean", "agents", clip_id="c", columns=["has_ins"]) is cols
        assert lake.read_table("clean", "agents", clip_id="c",
                               filters=[("has_ins", "=", True)]) is not first
        clips = lake.read_table("clean", "clips", clip_id="c")
        assert lake.read_table("clean", "clips", clip_id="c") is not clips
        assert Lake(tmp_path / "lake").read_table("clean", "agents", clip_id="c") is not first
        t = threading.Thread(target=lambda: seen.append(
            lake.read_table("clean", "agents", clip_id="c")))
        t.start()
        t.join()
        assert seen[0] is not first and seen[0].equals(first)
        # a change inside the block is not seen there (the tables it names are inputs) ...
        lake.write_table("clean", "agents", _agents(3), clip_id="c", name="agents")
        assert lake.read_table("clean", "agents", clip_id="c").num_rows == 2
    # ... and is after it
    assert lake.read_table("clean", "agents", clip_id="c").num_rows == 3


def _ground_reference(pts: np.ndarray, min_range_m: float = 3.0, max_range_m: float = 15.0,
                      trim_m: float = 0.05, min_points: int = 30) -> float:
    """The fit as a mask over the whole scan (what the kernel did before it kept a list of
    the rows it uses)."""
    r2 = pts[:, 0] ** 2 + pts[:, 1] ** 2
    use = ~above_ground(pts) & (r2 >= min_range_m**2) & (r2 <= max_range_m**2)
    a = b = c = 0.0
    for _ in range(3):
        p = pts[use]
        if len(p) < min_points:
            return float("nan")
        M = np.array([[p[:, 0] @ p[:, 0], p[:, 0] @ p[:, 1], p[:, 0].sum()],
                      [p[:, 0] @ p[:, 1], p[:, 1] @ p[:, 1], p[:, 1].sum()],
                      [p[:, 0].sum(), p[:, 1].sum(), float(len(p))]])
        a, b, c = np.linalg.solve(M, [p[:, 0] @ p[:, 2], p[:, 1] @ p[:, 2], p[:, 2].sum()])
        use &= ~(np.abs(pts[:, 2] - (a * pts[:, 0] + b * pts[:, 1] + c)) > trim_m)
    return float(abs(c) / np.sqrt(a * a + b * b + 1.0))


def test_ground_fit_over_kept_rows_matches_the_whole_scan_mask() -> None:
    rng = np.random.default_rng(7)
    for k in range(40):
        n = int(rng.integers(0, 6000))
        pts = rng.normal(size=(n, 3)) * [9.0, 9.0, 0.04]
        pts[:, 2] += -1.8 + 0.02 * pts[:, 0] - 0.01 * pts[:, 1]
        wall = rng.random(n) < 0.3  # points above the ground, and outliers near it
        pts[wall, 2] += rng.uniform(0.5, 3.0, int(wall.sum()))
        pts[rng.random(n) < 0.05, 2] += 0.2
        got, want = ground_distance(pts), _ground_reference(pts)
        if k % 10 == 0:  # too few ground points: NaN on both
            few = pts[:20]
            assert np.isnan(ground_distance(few)) and np.isnan(_ground_reference(few))
        assert np.isnan(got) == np.isnan(want)
        if not np.isnan(want):
            assert abs(got - want) <= 1e-9 * max(1.0, abs(want)), (k, got, want)
            assert abs(got - 1.8) < 0.1
    # the kernel as the filter calls it: NaN where fewer than min_points are on the ground
    pts = np.zeros((10, 3))
    assert np.isnan(_ground_fit(pts, np.zeros(10, bool), 0.0, 1e6, 0.05, 30))
    # ground points all on one line (a wall's foot along the street, no road in range): the
    # normal equations are singular; no plane, NaN (not a LinAlgError that fails the clip,
    # nor, the line turned off the axes, an arbitrary plane's height)
    t = np.linspace(-14.0, 14.0, 400)
    for a in np.radians([0.0, 10.0, 30.0, 90.0]):
        line = np.stack([t * np.cos(a) - 6 * np.sin(a), t * np.sin(a) + 6 * np.cos(a),
                         np.full(400, -1.8)], 1)
        assert np.isnan(_ground_fit(line, np.zeros(400, bool), 9.0, 225.0, 0.05, 30)), a


def test_one_table_name_as_a_string_is_refused(tmp_path: Path) -> None:
    lake = Lake(tmp_path / "lake")
    with pytest.raises(TypeError, match="iterable of table names"), \
            lake.reading_once("clean", "agents"):
        pass
    nan = np.array([[0.0, 0.0, 0.0], [np.nan, 1.0, 0.0]])
    with pytest.raises(ValueError, match="finite"):
        above_ground(nan)
