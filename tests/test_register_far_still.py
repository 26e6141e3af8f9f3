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

from v2xlake.tasks.register.scans import without_still
from v2xlake.tasks.register.static import MovingBoxes, annotation_boxes, box_of_point


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
