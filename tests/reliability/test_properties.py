"""#16, property tests for the geometry a crash-free pipeline still has to get right.

``tests/test_geometry.py`` holds the SE(3) laws (compose / invert / apply, quaternion round
trips, SLERP end points and monotonic angle between two samples); these add what connects
them to the data: SLERP over whole tracks (sign flips of the stored quaternions change
nothing, the angle to the start grows monotonically inside every interval, every sample is
reproduced), and deskew of a static scene seen from a random smooth trajectory, which must
put every point back where the scene is, to float32 precision.
"""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from v2xlake.tasks.geometry import apply, compose, invert, quat_to_matrix, rotation_angle, transform
from v2xlake.tasks.interpolate import PoseTrack, interpolate_poses
from v2xlake.tasks.motion import deskew_points

SCAN_NS = 100_000_000  # one 10 Hz sweep
INS_NS = 8_000_000  # 125 Hz


def _euler_quat(roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """wxyz of R = Rz(yaw) Ry(pitch) Rx(roll), per sample."""
    cr, sr = np.cos(roll / 2), np.sin(roll / 2)
    cp, sp = np.cos(pitch / 2), np.sin(pitch / 2)
    cy, sy = np.cos(yaw / 2), np.sin(yaw / 2)
    return np.stack([cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
                     cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy], axis=-1)


@st.composite
def smooth_tracks(draw: st.DrawFn) -> PoseTrack:
    """A vehicle-like trajectory: speed up to 30 m/s, yaw rate up to ~1 rad/s, small pitch and
    roll oscillations, each a sum of sinusoids with random amplitude, frequency and phase,
    sampled at 125 Hz over the sweep (plus a margin)."""
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    t = np.arange(-2 * INS_NS, SCAN_NS + 3 * INS_NS, INS_NS, dtype=np.int64)
    s = t / 1e9
    speed = draw(st.floats(0.0, 30.0))
    heading0 = draw(st.floats(-np.pi, np.pi))
    yaw_rate = draw(st.floats(-1.0, 1.0))
    wob = rng.uniform(0.0, 0.05, (3, 3)), rng.uniform(0.5, 8.0, (3, 3)), \
        rng.uniform(0, 2 * np.pi, (3, 3))
    osc = [sum(a * np.sin(2 * np.pi * f * s + p) for a, f, p in zip(*(w[k] for w in wob),
                                                                    strict=True))
           for k in range(3)]
    yaw = heading0 + yaw_rate * s + osc[2]
    xyz = np.stack([np.cumsum(speed * np.cos(yaw) * INS_NS / 1e9),
                    np.cumsum(speed * np.sin(yaw) * INS_NS / 1e9), 0.3 * osc[0]], axis=1)
    q = _euler_quat(osc[0], osc[1], yaw)
    flip = rng.random(len(q)) < 0.3  # q and -q are the same rotation: stored either way
    q[flip] *= -1
    return PoseTrack(t, xyz + rng.uniform(-1e3, 1e3, 3), q)


def _pose(track: PoseTrack, t: np.ndarray) -> np.ndarray:
    xyz, q = interpolate_poses(track.t_ns, track.xyz, track.quat_wxyz, t)
    return np.stack([transform(p, qq) for p, qq in zip(xyz, q, strict=True)])


@given(smooth_tracks(), st.integers(0, 2**32 - 1), st.integers(0, SCAN_NS))
@settings(max_examples=30, deadline=None)
def test_deskew_of_a_static_scene_on_a_smooth_trajectory(track: PoseTrack, seed: int,
                                                         t_ref: int) -> None:
    """Points of a static scene observed at their own times from the moving LiDAR, deskewed
    to any reference time, are the scene seen from the LiDAR at that time (the trajectory
    between INS samples is the interpolated one, so the only error left is float32)."""
    rng = np.random.default_rng(seed)
    n = 500
    T_ego_lidar = transform(rng.uniform(-2, 2, 3), _euler_quat(*rng.uniform(-0.2, 0.2, 3)))
    t = np.sort(rng.integers(0, SCAN_NS, n)).astype(np.int64)
    T_world_lidar = compose(_pose(track, t), T_ego_lidar)  # (n, 4, 4)
    # a static scene: points 2-60 m around the sensor at the start of the sweep
    start = compose(_pose(track, np.array([0]))[0], T_ego_lidar)
    scene = apply(start, rng.normal(size=(n, 3)) * rng.uniform(2, 60, (n, 1)))
    seen = np.einsum("nij,nj->ni", invert(T_world_lidar)[:, :3, :3], scene) \
        + invert(T_world_lidar)[:, :3, 3]  # each point in the LiDAR frame of its own time
    res = deskew_points(seen, t, track, T_ego_lidar, t_ref_ns=t_ref)
    assert res.valid.all() and res.n_uncovered == 0
    want = apply(invert(compose(_pose(track, np.array([t_ref]))[0], T_ego_lidar)), scene)
    np.testing.assert_allclose(res.xyz, want, atol=2e-5 * 60 + 1e-5)
    # and a point observed exactly at the reference time does not move
    at_ref = t == t_ref
    np.testing.assert_allclose(res.xyz[at_ref], seen[at_ref], atol=1e-5 * 60 + 1e-5)


@given(smooth_tracks())
@settings(max_examples=30, deadline=None)
def test_slerp_over_a_track_reproduces_samples_and_is_monotonic_in_between(
        track: PoseTrack) -> None:
    t = track.t_ns
    at_samples = _pose(track, t)
    for T, p, q in zip(at_samples, track.xyz, track.quat_wxyz, strict=True):
        np.testing.assert_allclose(T, transform(p, q), atol=1e-9)
    for k in range(len(t) - 1):
        tq = np.linspace(t[k], t[k + 1], 9).astype(np.int64)
        Ts = _pose(track, tq)
        start = quat_to_matrix(track.quat_wxyz[k])
        ang = rotation_angle(np.einsum("ji,njk->nik", start, Ts[:, :3, :3]))
        assert np.all(np.diff(ang) >= -1e-9), ang
        # translation is linear in time between samples
        lin = np.linspace(0, 1, 9)[:, None]
        np.testing.assert_allclose(Ts[:, :3, 3],
                                   (1 - lin) * track.xyz[k] + lin * track.xyz[k + 1], atol=1e-9)


@given(smooth_tracks(), st.integers(0, 2**32 - 1))
@settings(max_examples=20, deadline=None)
def test_quaternion_sign_of_the_samples_changes_nothing(track: PoseTrack, seed: int) -> None:
    rng = np.random.default_rng(seed)
    flipped = track.quat_wxyz * np.where(rng.random(len(track.t_ns)) < 0.5, -1.0, 1.0)[:, None]
    other = PoseTrack(track.t_ns, track.xyz, flipped)
    tq = np.sort(rng.integers(track.t_ns[0], track.t_ns[-1], 50))
    np.testing.assert_allclose(_pose(track, tq), _pose(other, tq), atol=1e-12)
