"""Static-scene filtering before GICP and backend robustness (issue #13), on small arrays.

The end-to-end behaviour on the hard street is in tests/test_register_street.py.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tests.test_register import cast_scan, drive, lidar_pose, make_street
from v2xlake.tasks.register.backends import make_backend
from v2xlake.tasks.register.config import GicpSection, QualitySection
from v2xlake.tasks.register.core import refine
from v2xlake.tasks.register.static import (
    MovingBoxes,
    above_ground,
    annotation_boxes,
    body_box,
    box_of_point,
    dynamic_mask,
    grow_to_objects,
)
from v2xlake.tasks.register.voxel import voxel_downsample, voxel_downsample_t


def test_voxel_mean_time_and_non_finite_points_dropped() -> None:
    pts = np.array([[0.1, 0.1, 0.1], [0.2, 0.2, 0.2], [5.1, 0, 0], [np.nan, 0, 0],
                    [np.inf, 0, 0], [0, -np.inf, 0], [200.0, 0, 0]], np.float32)
    t = np.array([1.0, 3.0, 7.0, 9.0, 9.0, 9.0, 9.0])
    c, m = voxel_downsample_t(pts, t, 1.0, max_range_m=np.inf)
    # NaN and both infinities are dropped even without a range limit; 200 m is finite and kept
    assert len(c) == 3 and np.isfinite(c).all()
    np.testing.assert_allclose(c[0], [0.15, 0.15, 0.15], atol=1e-6)
    np.testing.assert_allclose(m, [2.0, 7.0, 9.0])
    assert len(voxel_downsample(pts, 1.0, max_range_m=50.0)) == 2
    with pytest.raises(ValueError, match="values"):
        voxel_downsample_t(pts, t[:3], 1.0)


def test_moving_box_follows_its_velocity_to_each_point_time() -> None:
    """A car 4.5 x 1.8 x 1.5 m at x = 10 driving +x at 10 m/s, annotated at t = 0.05 s:
    a point on its front at t = 0.0 is 0.5 m behind where the box is at 0.05 s."""
    yaw = np.radians(30.0)
    q = Rotation.from_euler("z", yaw).as_quat(scalar_first=True)
    v = 10.0 * np.array([np.cos(yaw), np.sin(yaw), 0.0])
    boxes = annotation_boxes(np.array([[10.0, 0.0, 0.75]]), np.array([[1.8, 4.5, 1.5]]),
                             q[None], v[None], np.array([0.05]), margin_m=0.0)
    fwd = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    c = np.array([10.0, 0.0, 0.75])
    front_at_0 = c + fwd * (2.25 - 0.5 - 0.05)  # just inside the front face at t = 0
    front_at_005 = c + fwd * (2.25 - 0.05)
    pts = np.stack([front_at_0, front_at_0, front_at_005, front_at_005])
    t = np.array([0.0, 0.05, 0.05, 0.0])
    hit = box_of_point(pts, t, boxes)
    # at its own time each point is inside; the same place at the other time is not
    assert hit.tolist() == [0, 0, 0, -1]
    # (the second point: at 0.05 s the front is 0.5 m further, so that place is inside too)
    grown = MovingBoxes(boxes.center, boxes.half, boxes.R, boxes.velocity, boxes.t_s,
                        np.array([0.6]))
    assert box_of_point(pts[3:], t[3:], grown).tolist() == [0]
    # the width axis: 0.9 m half-width, +-1.0 m outside without margin
    side = c + np.array([-np.sin(yaw), np.cos(yaw), 0.0]) * 1.0
    assert box_of_point(side[None], np.array([0.05]), boxes).tolist() == [-1]


def test_body_box_from_pose_and_footprint() -> None:
    T = lidar_pose(12.0, 3.5, 90.0, height=0.0)  # the other agent's ego frame in this scan
    b = body_box(T, np.array([0.0, 10.0, 0.0]), 0.0, 4.92, 1.86, 1.48,
                 np.array([0.0, 0.0, 0.34]), margin_m=0.0)
    assert len(b) == 1
    np.testing.assert_allclose(b.center[0], [12.0, 3.5, 0.34])
    inside = np.array([[12.0, 3.5 + 2.3, 0.5], [12.0 + 0.8, 3.5, 1.0]])
    outside = np.array([[12.0 + 1.2, 3.5, 0.5], [12.0, 3.5, 1.2]])
    got = box_of_point(np.vstack([inside, outside]), np.zeros(4), b)
    assert got.tolist() == [0, 0, -1, -1]


def test_dynamic_rule_and_objects_grow_whole() -> None:
    far, near = np.array([4.0, 4.0, 0.01]), np.array([4.0, 0.01, 0.01])
    assert dynamic_mask(far, near, 0.5).tolist() == [True, False, False]
    assert dynamic_mask(None, far, 0.5).tolist() == [True, True, False]
    with pytest.raises(ValueError):
        dynamic_mask(None, None, 0.5)
    # ground plane 40 x 40 m, a car (a block of points at 10..14.5, 2..4, 0.4..1.5 m) and
    # a wall; one in four of the car's points was found moving: the whole car goes, the
    # wall (one of its points flagged) keeps its per-point decision, the ground never moves
    rng = np.random.default_rng(0)
    ground = np.column_stack([rng.uniform(-20, 20, 4000), rng.uniform(-20, 20, 4000),
                              rng.normal(-1.9, 0.01, 4000)])
    car = np.column_stack([rng.uniform(10, 14.5, 400), rng.uniform(2, 4, 400),
                           rng.uniform(-1.5, -0.4, 400)])
    wall = np.column_stack([rng.uniform(-20, 20, 800), np.full(800, -9.0),
                            rng.uniform(-1.9, 5, 800)])
    pts = np.vstack([ground, car, wall])
    up = above_ground(pts)
    assert not up[:4000].any() and up[4000:4400].all()
    moving = np.zeros(len(pts), bool)
    moving[4000:4100] = True
    moving[4500] = True
    out = grow_to_objects(pts, moving, up, 0.5, 0.25)
    assert out[4000:4400].all() and out[4500] and out[4400:].sum() == 1 and not out[:4000].any()
    assert not grow_to_objects(pts, moving, up, 0.5, 0.3)[4100:4400].any()


def test_nan_and_inf_points_never_reach_a_backend() -> None:
    """Open3D crashed on NaN points ('x' must be finite); now both backends register a scan
    with NaN and inf returns, and a cloud with any left is refused before the backend."""
    c = drive("turning", 1, beams=32, cols=720)[0]
    rng = np.random.default_rng(1)
    dirty = c.other.copy()
    bad = rng.choice(len(dirty), 500, replace=False)
    dirty[bad[:250], 0] = np.nan
    dirty[bad[250:], 2] = np.inf
    for name in ("small_gicp", "open3d", "sparse"):
        be = make_backend(name, GicpSection(voxel_m=0.6, source_voxel_m=1.0))  # type: ignore[arg-type]
        res = refine(be, be.prepare(c.ref), be.prepare(dirty, as_target=False), c.T_init,
                     QualitySection())
        assert res.accepted, res.reason
        with pytest.raises(ValueError, match="non-finite"):
            be.prepare_points(np.array([[0.0, 0.0, np.nan]]))


class _Exploding:
    """A backend whose GICP raises: the frame gets the reason, the caller keeps going."""

    name = "exploding"
    params = GicpSection(voxel_m=0.6, source_voxel_m=1.0)

    def __init__(self) -> None:
        self._inner = make_backend("small_gicp")

    def prepare(self, xyz: np.ndarray, *, as_target: bool = True):  # type: ignore[no-untyped-def]
        return self._inner.prepare(xyz, as_target=as_target)

    def prepare_points(self, pts: np.ndarray):  # type: ignore[no-untyped-def]
        return self._inner.prepare_points(pts)

    def align(self, target, source, init):  # type: ignore[no-untyped-def]
        raise RuntimeError("solver blew up")

    def nearest_sq_dist(self, target, query, max_dist_m=np.inf):  # type: ignore[no-untyped-def]
        return self._inner.nearest_sq_dist(target, query, max_dist_m)

    def prepare_covisible(self, pts, other_origin, min_keep, base=None, *, as_target=False):  # type: ignore[no-untyped-def]
        return self._inner.prepare_covisible(pts, other_origin, min_keep, base,
                                             as_target=as_target)


def test_backend_failure_is_a_per_frame_reason() -> None:
    street = make_street(0)
    t1, t2 = lidar_pose(0.0, -1.75, 0.0), lidar_pose(12.0, 1.75, 180.0)
    be = _Exploding()
    T_init = np.linalg.inv(t1) @ t2
    res = refine(be, be.prepare(cast_scan(street, t1, n_beams=16, n_cols=360)),  # type: ignore[arg-type]
                 be.prepare(cast_scan(street, t2, n_beams=16, n_cols=360), as_target=False),
                 T_init, QualitySection())
    assert not res.accepted and "GICP failed: RuntimeError: solver blew up" in res.reason
    np.testing.assert_array_equal(res.T_final, T_init)


def test_redeskew_with_a_refined_extrinsic_equals_deskewing_with_it() -> None:
    """A scan deskewed with a wrong extrinsic, deskewed again with the right one (deskew's
    kernel backwards, then forwards), equals the scan deskewed with the right one."""
    from v2xlake.tasks.interpolate import PoseTrack
    from v2xlake.tasks.motion import deskew_points
    from v2xlake.tasks.register.scans import redeskew

    t = np.arange(0, 400_000_001, 8_000_000, dtype=np.int64)
    yaw = 0.3 * t * 1e-9
    xyz = np.column_stack([10.0 * t * 1e-9, 0.5 * np.sin(t * 1e-9), np.zeros(len(t))])
    q = np.column_stack([np.cos(yaw / 2), np.zeros(len(t)), np.zeros(len(t)), np.sin(yaw / 2)])
    track = PoseTrack.create(t, xyz, q)
    rng = np.random.default_rng(0)
    pts = rng.uniform(-30, 30, (5000, 3)).astype(np.float32)
    tp = np.sort(rng.integers(100_000_000, 200_000_000, 5000))
    right = lidar_pose(0.2, 0.0, 1.0, height=1.55)
    wrong = right @ lidar_pose(0.1, -0.1, 0.4, roll_deg=0.2, height=0.05)
    good = deskew_points(pts, tp, track, right, t_ref_ns=100_000_000).xyz
    bad = deskew_points(pts, tp, track, wrong, t_ref_ns=100_000_000).xyz
    fixed = redeskew(bad, tp, 100_000_000, track, wrong, right)
    assert np.abs(bad - good).max() > 0.005  # the wrong extrinsic leaves millimetres of skew
    np.testing.assert_allclose(fixed, good, atol=2e-5)
