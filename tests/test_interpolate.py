"""Pose interpolation (supplementary eq. 2a-2c) against SciPy's Slerp, edges and bad input."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from v2xlake.tasks.geometry import invert as invert_rigid
from v2xlake.tasks.interpolate import PoseCoverageError, PoseTrack, interpolate_poses


def _track(n: int = 40, seed: int = 0, flip_signs: bool = True) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.integers(7_000_000, 9_000_000, n)).astype(np.int64)  # ~125 Hz, jittered
    xyz = np.cumsum(rng.normal(0, 0.16, (n, 3)), axis=0) + np.array([1000.0, -2000.0, 50.0])
    rot = Rotation.from_rotvec(np.cumsum(rng.normal(0, 0.05, (n, 3)), axis=0))
    q = rot.as_quat(scalar_first=True)
    if flip_signs:  # q and -q are one rotation; INS streams do flip
        q[rng.random(n) < 0.4] *= -1
    return t, xyz, q


def test_matches_scipy_slerp_and_linear_translation() -> None:
    t, xyz, q = _track()
    rng = np.random.default_rng(1)
    tq = rng.integers(t[0], t[-1] + 1, 5000)
    tq[:3] = [t[0], t[-1], t[7]]  # exact sample times included
    p, qq = interpolate_poses(t, xyz, q, tq)
    ref_r = Slerp(t.astype(float), Rotation.from_quat(q, scalar_first=True))(tq.astype(float))
    ang = (Rotation.from_quat(qq, scalar_first=True) * ref_r.inv()).magnitude()
    assert ang.max() < 1e-9
    ref_p = np.stack([np.interp(tq, t, xyz[:, j]) for j in range(3)], axis=1)
    np.testing.assert_allclose(p, ref_p, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(qq, axis=1), 1.0, atol=1e-12)
    # at a sample time the sample itself comes back (up to sign)
    assert min(np.abs(qq[2] - q[7]).max(), np.abs(qq[2] + q[7]).max()) < 1e-12


def test_shortest_arc_between_sign_flipped_samples() -> None:
    t = np.array([0, 8_000_000], dtype=np.int64)
    q0 = Rotation.from_euler("z", 10, degrees=True).as_quat(scalar_first=True)
    q1 = -Rotation.from_euler("z", 20, degrees=True).as_quat(scalar_first=True)
    _, qm = interpolate_poses(t, np.zeros((2, 3)), np.stack([q0, q1]), 4_000_000)
    yaw = Rotation.from_quat(qm[0], scalar_first=True).as_euler("zyx", degrees=True)[0]
    assert yaw == pytest.approx(15.0, abs=1e-9)  # not the 345-degree long way round


def test_tiny_rotation_is_stable() -> None:
    t = np.array([0, 8_000_000], dtype=np.int64)
    q = np.array([[1.0, 0, 0, 0], [np.cos(1e-12), 0, 0, np.sin(1e-12)]])
    _, qm = interpolate_poses(t, np.zeros((2, 3)), q, 4_000_000)
    assert np.all(np.isfinite(qm)) and abs(np.linalg.norm(qm) - 1) < 1e-15


def test_uncovered_queries_raise_or_flag_never_extrapolate() -> None:
    t, xyz, q = _track(10)
    with pytest.raises(PoseCoverageError) as ei:
        interpolate_poses(t, xyz, q, np.array([t[0] - 1, t[3], t[-1] + 5]))
    assert ei.value.n == 2 and ei.value.t_min == t[0] - 1 and ei.value.t_max == t[-1] + 5
    assert str(t[-1]) in str(ei.value)
    p, qq = interpolate_poses(t, xyz, q, np.array([t[0] - 1, t[3], t[-1] + 5]), uncovered="nan")
    assert np.isnan(p[[0, 2]]).all() and np.isnan(qq[[0, 2]]).all()
    assert np.isfinite(p[1]).all()


@pytest.mark.parametrize(
    ("t", "match"),
    [([0, 5, 5, 9], "strictly increasing"), ([3], "at least 2")],
)
def test_bad_tracks_rejected(t: list[int], match: str) -> None:
    n = len(t)
    with pytest.raises(ValueError, match=match):
        PoseTrack(np.array(t), np.zeros((n, 3)), np.tile([1.0, 0, 0, 0], (n, 1)))


def test_track_matrices_and_rigid_inverse() -> None:
    t, xyz, q = _track(12, flip_signs=False)
    track = PoseTrack.create(t, xyz, q)
    m = track.matrices(t[[2, 5]])
    np.testing.assert_allclose(m[0, :3, 3], xyz[2])
    r5 = Rotation.from_quat(q[5], scalar_first=True).as_matrix()
    np.testing.assert_allclose(m[1, :3, :3], r5, atol=1e-12)
    np.testing.assert_allclose(invert_rigid(m) @ m, np.broadcast_to(np.eye(4), m.shape), atol=1e-9)
    assert track.covers(np.array([t[0] - 1, t[0], t[-1], t[-1] + 1])).tolist() == [
        False, True, True, False]
