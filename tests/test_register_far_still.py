"""Annotated boxes that stand still stay in the scan (``static.keep_still_boxes_mps``), on
small arrays.

WHY (issue #21, docs/registration.md "Far pairs: what fixes them along the street"): two
vehicles 50 m apart on a street of walls see each block end face from one side only while it
stands between them, so along the street the pair is held by the poles and the parked cars;
removing the parked cars with every other annotated box left GICP, started at the true pose,
~5 cm off along the street. The end-to-end figure is in tests/test_register_far.py.
"""

from __future__ import annotations

import numpy as np

from v2xlake.tasks.register.static import (
    MovingBoxes,
    annotation_boxes,
    box_of_point,
    without_still,
)


def _boxes(velocity: np.ndarray) -> MovingBoxes:
    n = len(velocity)
    centers = np.stack([np.arange(n) * 10.0, np.zeros(n), np.full(n, 0.75)], 1)
    q = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    return annotation_boxes(centers, np.tile([1.8, 4.5, 1.5], (n, 1)), q, velocity,
                            np.zeros(n), margin_m=0.0)


def test_still_boxes_are_left_out_of_the_removal() -> None:
    """A parked car (0 m/s) and one creeping at 0.05 m/s stay; a car at 0.5 m/s, a walker and
    a box without a velocity (NaN) are removed."""
    v = np.array([[0.0, 0.0, 0.0], [0.05, 0.0, 0.0], [0.5, 0.0, 0.0], [0.0, 1.3, 0.0],
                  [np.nan, np.nan, np.nan]])
    b = _boxes(v)
    kept = without_still(b, 0.1)
    assert len(kept) == 3
    np.testing.assert_allclose(kept.center[:, 0], [20.0, 30.0, 40.0])
    # the points inside each box: only the moving boxes' points are hit
    pts = b.center.copy()
    hit = box_of_point(pts, np.zeros(len(pts)), kept)
    assert (hit >= 0).tolist() == [False, False, True, True, True]


def test_none_removes_every_box_as_before() -> None:
    b = _boxes(np.zeros((3, 3)))
    assert without_still(b, None) is b
    assert len(without_still(b, 0.0)) == 3  # nothing is slower than 0 m/s
    assert len(without_still(MovingBoxes.empty(), 0.1)) == 0
    # boxes without annotated speeds (the agents' bodies) are never taken for still
    bodies = MovingBoxes(b.center, b.half, b.R, b.velocity, b.t_s, b.margin)
    assert without_still(bodies, 0.1) is bodies


def test_velocity_columns_absent_or_null_read_as_unknown() -> None:
    """The stage's reader gives NaN, not 0, where a velocity is missing, so such boxes are
    removed rather than taken for parked (a column of zeros would keep every box)."""
    import pyarrow as pa

    from v2xlake.tasks.register.stage import _annotation_columns

    base = {"sensor": ["LIDAR_TOP"] * 2, "frame_idx": [0, 0], "t_ns": [0, 0],
            "cx": [0.0, 10.0], "cy": [0.0, 0.0], "cz": [0.75, 0.75], "w": [1.8, 1.8],
            "l": [4.5, 4.5], "h": [1.5, 1.5], "qw": [1.0, 1.0], "qx": [0.0, 0.0],
            "qy": [0.0, 0.0], "qz": [0.0, 0.0]}
    absent = _annotation_columns(pa.table(base), "LIDAR_TOP")
    assert absent is not None and np.isnan(absent.velocity).all()
    partly = _annotation_columns(pa.table({**base, "vx": [0.0, None], "vy": [0.0, 0.0],
                                           "vz": [0.0, 0.0]}), "LIDAR_TOP")
    assert partly is not None
    assert partly.velocity[0].tolist() == [0.0, 0.0, 0.0] and np.isnan(partly.velocity[1, 0])


def test_the_static_filter_keeps_the_parked_cars_points() -> None:
    """``StaticScans`` removes the moving car's points and keeps the parked car's; with the
    setting None it removes both (the behaviour before it)."""
    from v2xlake.tasks.interpolate import PoseTrack
    from v2xlake.tasks.register.config import StaticSection
    from v2xlake.tasks.register.scans import AgentScans, StaticScans

    rng = np.random.default_rng(0)
    # points filling a parked car (x 0) and a car driving at 8 m/s (x 10), plus a wall
    cars = [c + rng.uniform(-0.8, 0.8, (400, 3)) * [2.0, 0.8, 0.6] + [0, 0, 0.75]
            for c in (np.array([0.0, 0.0, 0.0]), np.array([10.0, 0.0, 0.0]))]
    wall = np.stack([rng.uniform(-20, 20, 800), np.full(800, 6.0), rng.uniform(0, 3, 800)], 1)
    pts = np.concatenate([*cars, wall]).astype(np.float32)
    boxes = {0: _boxes(np.array([[0.0, 0.0, 0.0], [8.0, 0.0, 0.0]]))}
    t = np.array([0, 1_000_000_000], np.int64)
    track = PoseTrack(t, np.zeros((2, 3)), np.tile([1.0, 0.0, 0.0, 0.0], (2, 1)))

    def removed(speed: float | None) -> tuple[int, int]:
        scans = AgentScans("a", "LIDAR_TOP", track, np.eye(4), {0: (0, 0)},
                           lambda f: (pts, np.zeros(len(pts), np.int64)), boxes)
        s = StaticSection(keep_still_boxes_mps=speed, dynamic="off")
        out = StaticScans(scans, s, []).filtered(0, 0.1)
        return out.counts.n_in, out.counts.boxes

    n_in, kept_parked = removed(0.1)
    _, both = removed(None)
    assert 0 < kept_parked < both < n_in
    assert both - kept_parked > 0.8 * kept_parked  # the parked car's share came back
