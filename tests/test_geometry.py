"""Property tests of the one geometry vocabulary (v2xlake/tasks/geometry.py)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation

from v2xlake.tasks.geometry import (
    apply,
    compose,
    count_points_in_boxes,
    greedy_boxes,
    invert,
    iou_xyxy,
    matrix_to_quat,
    points_in_boxes,
    quat_to_matrix,
    quat_wxyz_of,
    rigid,
    rotation_angle,
    transform,
    transform_boxes,
)
from v2xlake.tasks.interpolate import interpolate_poses

finite = st.floats(-50, 50, allow_nan=False, width=64)
quats = arrays(np.float64, 4, elements=st.floats(-1, 1, allow_nan=False)).filter(
    lambda q: np.linalg.norm(q) > 0.1).map(lambda q: q / np.linalg.norm(q))
vecs = arrays(np.float64, 3, elements=finite)


@given(vecs, quats, vecs, quats, arrays(np.float64, (7, 3), elements=finite))
@settings(max_examples=60, deadline=None)
def test_compose_invert_apply(t1: np.ndarray, q1: np.ndarray, t2: np.ndarray, q2: np.ndarray,
                              pts: np.ndarray) -> None:
    A, B = transform(t1, q1), transform(t2, q2)
    np.testing.assert_allclose(compose(A, invert(A)), np.eye(4), atol=1e-9)
    np.testing.assert_allclose(invert(compose(A, B)), compose(invert(B), invert(A)), atol=1e-9)
    homog = np.c_[pts, np.ones(len(pts))] @ compose(A, B).T
    np.testing.assert_allclose(apply(compose(A, B), pts), homog[:, :3], atol=1e-8)
    np.testing.assert_allclose(apply(A, apply(B, pts)), apply(compose(A, B), pts), atol=1e-8)
    # quaternion round trip (sign canonical: w >= 0)
    back = matrix_to_quat(quat_to_matrix(q1))
    assert back[0] >= 0 and min(np.abs(back - q1).max(), np.abs(back + q1).max()) < 1e-9


@given(quats, quats, vecs, vecs)
@settings(max_examples=60, deadline=None)
def test_slerp_end_points_and_monotonic_angle(qa: np.ndarray, qb: np.ndarray, pa: np.ndarray,
                                              pb: np.ndarray) -> None:
    t = np.array([0, 1_000_000_000], dtype=np.int64)
    tq = np.linspace(0, 1_000_000_000, 11).astype(np.int64)
    xyz, q = interpolate_poses(t, np.stack([pa, pb]), np.stack([qa, qb]), tq)
    np.testing.assert_allclose(xyz[0], pa, atol=1e-9)
    np.testing.assert_allclose(xyz[-1], pb, atol=1e-9)
    Ra, Rb = quat_to_matrix(qa), quat_to_matrix(qb)
    np.testing.assert_allclose(quat_to_matrix(q[0]), Ra, atol=1e-9)
    np.testing.assert_allclose(quat_to_matrix(q[-1]), Rb, atol=1e-9)
    # the angle from the start grows monotonically along the shorter arc
    ang = [np.arccos(np.clip((np.trace(Ra.T @ quat_to_matrix(x)) - 1) / 2, -1, 1)) for x in q]
    assert np.all(np.diff(ang) >= -1e-6)  # arccos near 1 is only good to ~1e-8


@given(arrays(np.float64, (200, 3), elements=st.floats(-6, 6, allow_nan=False)),
       arrays(np.float64, (4, 3), elements=st.floats(-3, 3, allow_nan=False)),
       arrays(np.float64, (4, 3), elements=st.floats(0.2, 4, allow_nan=False)),
       st.lists(quats, min_size=4, max_size=4), st.floats(0, 0.3))
@settings(max_examples=40, deadline=None)
def test_points_in_boxes_matches_brute_force(xyz: np.ndarray, center: np.ndarray,
                                             size: np.ndarray, q: list[np.ndarray],
                                             margin: float) -> None:
    quat = np.stack(q)
    got = points_in_boxes(xyz, center, size, quat, margin)
    R = quat_to_matrix(quat)
    for k in range(len(center)):
        local = (xyz - center[k]) @ R[k]  # box frame: x length, y width, z height
        half = np.array([size[k, 1], size[k, 0], size[k, 2]]) / 2 + margin
        brute = np.flatnonzero(np.all(np.abs(local) <= half + 1e-12, axis=1))
        np.testing.assert_array_equal(got[k], brute)
    assert count_points_in_boxes(xyz, center, size, quat, margin).tolist() == \
        [len(g) for g in got]


@given(arrays(np.float64, (5, 2), elements=st.floats(0, 100, allow_nan=False)),
       arrays(np.float64, (5, 2), elements=st.floats(1, 50, allow_nan=False)))
@settings(max_examples=60, deadline=None)
def test_iou_matrix_and_paired_agree(xy: np.ndarray, wh: np.ndarray) -> None:
    a = np.c_[xy, xy + wh]
    b = np.c_[xy + wh / 3, xy + wh]
    m = iou_xyxy(a, b)
    np.testing.assert_allclose(np.diag(m), iou_xyxy(a, b, paired=True))
    np.testing.assert_allclose(np.diag(iou_xyxy(a, a)), 1.0)
    assert np.all((m >= 0) & (m <= 1 + 1e-12))


@given(quats, vecs)
@settings(max_examples=60, deadline=None)
def test_conversions_agree_with_scipy(q: np.ndarray, t: np.ndarray) -> None:
    """schemas/ converts without SciPy (it may not import it); the numbers must be SciPy's."""
    rot = Rotation.from_quat(q, scalar_first=True)
    np.testing.assert_allclose(quat_to_matrix(q), rot.as_matrix(), atol=1e-12)
    want = Rotation.from_matrix(rot.as_matrix()).as_quat(scalar_first=True)
    T = transform(t, q)
    np.testing.assert_allclose(T, rigid(rot.as_matrix(), t), atol=1e-12)
    for got in (matrix_to_quat(rot.as_matrix()), quat_wxyz_of(T)):  # sign: w >= 0
        assert got[0] >= 0 and min(np.abs(got - want).max(), np.abs(got + want).max()) < 1e-12
    # the angle, also where arccos((tr - 1) / 2) has no digits left
    assert abs(rotation_angle(T) - rot.magnitude()) < 1e-9
    tiny = Rotation.from_rotvec(q[1:] * 1e-10)
    assert abs(rotation_angle(tiny.as_matrix()) - tiny.magnitude()) < 1e-15


def test_matrix_to_quat_every_branch() -> None:
    """Shepperd's four branches (largest of w, x, y, z) and batch shapes."""
    mats = np.stack([np.eye(3), np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]),
                     np.diag([-1.0, -1, 1])])
    np.testing.assert_allclose(matrix_to_quat(mats), np.eye(4), atol=1e-15)
    assert matrix_to_quat(np.zeros((0, 3, 3))).shape == (0, 4)
    assert matrix_to_quat(np.broadcast_to(np.eye(3), (2, 5, 3, 3))).shape == (2, 5, 4)


@given(arrays(np.float64, (5, 3), elements=finite), st.lists(quats, min_size=5, max_size=5),
       arrays(np.float64, (5, 3), elements=finite), vecs, quats,
       arrays(np.float64, (5, 3), elements=st.floats(0.5, 5)))
@settings(max_examples=40, deadline=None)
def test_transform_boxes_moves_their_corners(center: np.ndarray, q: list[np.ndarray],
                                             vel: np.ndarray, t: np.ndarray, qt: np.ndarray,
                                             size: np.ndarray) -> None:
    """A box moved by T has T's image of its corners (one 4x4 or one per box)."""
    from v2xlake.tasks.geometry import box_corners

    quat = np.stack(q)
    T = transform(t, qt)
    for TT in (T, np.broadcast_to(T, (5, 4, 4))):
        c, qq, v = transform_boxes(TT, center, quat, vel)
        moved = apply(T, box_corners(center, size, quat).reshape(-1, 3)).reshape(5, 8, 3)
        np.testing.assert_allclose(box_corners(c, size, qq), moved, atol=1e-8)
        np.testing.assert_allclose(v, vel @ T[:3, :3].T, atol=1e-9)


def test_se3_adjoint_moves_a_perturbation_across_a_transform() -> None:
    """``T exp(d) T^-1 = exp(Ad_T d)`` with the true SE(3) exponential, one and stacked."""
    from scipy.linalg import expm

    from v2xlake.tasks.geometry import se3_adjoint, so3_exp

    def hat(d: np.ndarray) -> np.ndarray:  # [rot, trans] twist -> 4x4
        w, v = d[:3], d[3:]
        m = np.zeros((4, 4))
        m[:3, :3] = [[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]
        m[:3, 3] = v
        return m

    T = np.eye(4)
    T[:3, :3] = so3_exp(np.array([0.3, -0.5, 1.1]))
    T[:3, 3] = [4.0, -2.0, 1.5]
    d = np.array([0.02, -0.01, 0.03, 0.4, -0.2, 0.1])
    lhs = T @ expm(hat(d)) @ np.linalg.inv(T)
    np.testing.assert_allclose(lhs, expm(hat(se3_adjoint(T) @ d)), atol=1e-12)
    np.testing.assert_allclose(se3_adjoint(np.stack([T, np.eye(4)]))[0], se3_adjoint(T))
    np.testing.assert_allclose(se3_adjoint(np.eye(4)), np.eye(6))


def test_merge_until_stable_merges_in_order_until_nothing_merges() -> None:
    """Intervals that touch are merged; a merge can make a new pair mergeable (the scan starts
    again), and the first pair in order is merged first."""
    from v2xlake.tasks.geometry import merge_until_stable

    def union(a: tuple[int, int], b: tuple[int, int]) -> tuple[int, int] | None:
        return (min(a[0], b[0]), max(a[1], b[1])) if a[0] <= b[1] and b[0] <= a[1] else None

    # (0, 2) and (5, 7) only touch once (2, 5) has joined the first
    assert merge_until_stable([(0, 2), (5, 7), (2, 5), (9, 10)], union) == [(0, 7), (9, 10)]
    assert merge_until_stable([], union) == []
    # a rule that merges nothing returns the items as they were
    assert merge_until_stable([(0, 1), (0, 1)], lambda a, b: None) == [(0, 1), (0, 1)]


def test_greedy_boxes_keeps_the_best_apart_within_the_cap() -> None:
    scored = [(0.5, (0.0, 0.0, 10.0, 4.0)), (0.9, (1.0, 0.0, 11.0, 4.0)),
              (0.7, (50.0, 0.0, 60.0, 4.0)), (0.6, (100.0, 0.0, 110.0, 4.0))]
    assert greedy_boxes(scored, 5) == [((1.0, 0.0, 11.0, 4.0), 0.9),
                                       ((50.0, 0.0, 60.0, 4.0), 0.7),
                                       ((100.0, 0.0, 110.0, 4.0), 0.6)]
    assert [s for _b, s in greedy_boxes(scored, 2)] == [0.9, 0.7]
    assert [s for _b, s in greedy_boxes(scored, 5, accept=lambda b: b[0] > 20)] == [0.7, 0.6]
    assert [s for _b, s in greedy_boxes(scored, 5, candidates=2)] == [0.9, 0.7]
    assert greedy_boxes([], 3) == []
