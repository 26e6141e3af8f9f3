"""Per-point motion compensation (supplementary eq. 3) against an analytic ground truth.

The generator here (also used by tests/bench/bench_deskew.py) drives a LiDAR along a smooth
analytic trajectory (straight or turning, with a roll/pitch wobble), samples the INS at
125 Hz from it, and fires a spinning LiDAR column by column over a 0.1 s sweep: each raw
point is ``T_lidar(t_i)^-1 p_world`` for a static world point, so its true position in the
scan-start frame is known exactly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from v2xlake.tasks.interpolate import PoseTrack
from v2xlake.tasks.motion import DeskewResult, deskew_points

INS_PERIOD_NS = 8_000_000  # 125 Hz
SWEEP_NS = 100_000_000


@dataclass(frozen=True)
class Motion:
    speed: float = 20.0  # m/s
    yaw_rate: float = 0.0  # rad/s
    wobble_rad: float = np.radians(0.5)  # roll/pitch amplitude
    wobble_hz: float = 1.5


def true_pose(t_s: np.ndarray, m: Motion) -> tuple[np.ndarray, np.ndarray]:
    """Analytic ``T_world_ego``: rotations (N, 3, 3) and positions (N, 3) at times in seconds."""
    t_s = np.asarray(t_s, dtype=np.float64)
    yaw = m.yaw_rate * t_s + 0.3
    if m.yaw_rate == 0.0:
        x, y = m.speed * t_s * np.cos(0.3), m.speed * t_s * np.sin(0.3)
    else:
        r = m.speed / m.yaw_rate
        x, y = r * (np.sin(yaw) - np.sin(0.3)), r * (np.cos(0.3) - np.cos(yaw))
    w = 2 * np.pi * m.wobble_hz * t_s
    z = 0.02 * np.sin(w)
    roll, pitch = m.wobble_rad * np.sin(w), 0.7 * m.wobble_rad * np.cos(1.3 * w)
    rot = Rotation.from_euler("ZYX", np.stack([yaw, pitch, roll], axis=1)).as_matrix()
    return rot, np.stack([x + 100.0, y - 50.0, z + 3.0], axis=1)


def ins_track(m: Motion, t0_ns: int = 0, t1_ns: int = 1_000_000_000) -> PoseTrack:
    t = np.arange(t0_ns, t1_ns + 1, INS_PERIOD_NS, dtype=np.int64)
    rot, p = true_pose(t * 1e-9, m)
    return PoseTrack.create(t, p, Rotation.from_matrix(rot).as_quat(scalar_first=True))


def lidar_extrinsic() -> np.ndarray:
    e = np.eye(4)
    e[:3, :3] = Rotation.from_euler("zyx", [1.5, 0.8, -0.5], degrees=True).as_matrix()
    e[:3, 3] = [0.9, 0.05, 1.85]
    return e


def true_lidar_matrices(t_ns: np.ndarray, m: Motion, e: np.ndarray) -> np.ndarray:
    rot, p = true_pose(t_ns * 1e-9, m)
    w = np.zeros((len(t_ns), 4, 4))
    w[:, :3, :3], w[:, :3, 3], w[:, 3, 3] = rot, p, 1.0
    return w @ e


@dataclass(frozen=True)
class Sweep:
    raw: np.ndarray  # float32 (N, 3) instantaneous LiDAR frame
    t_ns: np.ndarray  # int64 (N,)
    truth: np.ndarray  # float64 (N, 3) in the LiDAR frame at t0
    t0_ns: int


def make_sweep(m: Motion, e: np.ndarray, *, n_cols: int = 1800, n_lasers: int = 128,
               dual: bool = True, t0_ns: int = 300_000_000, seed: int = 0) -> Sweep:
    """Column-major spinning-LiDAR sweep (all lasers of a column share one time)."""
    rng = np.random.default_rng(seed)
    n_ret = 2 if dual else 1
    col = np.repeat(np.arange(n_cols), n_lasers * n_ret)
    laser = np.tile(np.repeat(np.arange(n_lasers), n_ret), n_cols)
    t_ns = t0_ns + (col * SWEEP_NS) // n_cols
    az = 2 * np.pi * col / n_cols
    el = np.radians(np.linspace(-25.0, 15.0, n_lasers))[laser]
    rng_m = rng.uniform(3.0, 60.0, len(col))
    if dual:
        rng_m[1::2] = rng_m[0::2] + rng.uniform(0.3, 3.0, len(col) // 2)
    d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1)
    raw = (d * rng_m[:, None]).astype(np.float32)
    t_lidar = true_lidar_matrices(np.unique(t_ns), m, e)[np.searchsorted(np.unique(t_ns), t_ns)]
    ref = np.linalg.inv(true_lidar_matrices(np.array([t0_ns]), m, e)[0])
    rel = ref @ t_lidar  # true T_L(t0)^-1 T_L(t_i) per point
    truth = np.einsum("nij,nj->ni", rel[:, :3, :3], raw.astype(np.float64)) + rel[:, :3, 3]
    return Sweep(raw, t_ns.astype(np.int64), truth, t0_ns)


def scipy_reference(xyz: np.ndarray, t_ns: np.ndarray, track: PoseTrack, e: np.ndarray,
                    t_ref_ns: int | np.ndarray) -> np.ndarray:
    """Eq. 3 written the obvious way, one SciPy Slerp per point (the accuracy reference)."""
    slerp = Slerp(track.t_ns.astype(np.float64),
                  Rotation.from_quat(track.quat_wxyz, scalar_first=True))

    def lidar(t: np.ndarray) -> np.ndarray:
        m = np.zeros((len(t), 4, 4))
        m[:, :3, :3] = slerp(t.astype(np.float64)).as_matrix()
        m[:, :3, 3] = np.stack([np.interp(t, track.t_ns, track.xyz[:, j]) for j in range(3)], 1)
        m[:, 3, 3] = 1.0
        return m @ e

    t_ref = np.broadcast_to(np.asarray(t_ref_ns, dtype=np.int64), t_ns.shape)
    rel = np.linalg.inv(lidar(t_ref)) @ lidar(t_ns)
    return np.einsum("nij,nj->ni", rel[:, :3, :3], xyz.astype(np.float64)) + rel[:, :3, 3]


def _err_mm(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    d = np.linalg.norm(np.asarray(a, np.float64) - b, axis=1) * 1e3
    return float(np.sqrt(np.mean(d**2))), float(d.max())


@pytest.mark.parametrize("motion", [Motion(), Motion(yaw_rate=0.6)], ids=["straight", "turning"])
def test_static_points_within_1mm_of_truth_at_20mps(motion: Motion) -> None:
    e = lidar_extrinsic()
    sw = make_sweep(motion, e, n_cols=900, n_lasers=32)
    res = deskew_points(sw.raw, sw.t_ns, ins_track(motion), e, sw.t0_ns)
    rms, mx = _err_mm(res.xyz, sw.truth)
    raw_rms, raw_max = _err_mm(sw.raw, sw.truth)
    print(f"deskew error RMS {rms:.3f} mm max {mx:.3f} mm; raw skew RMS {raw_rms:.0f} mm "
          f"max {raw_max:.0f} mm")
    assert res.valid.all() and res.n_uncovered == 0 and res.n_nan == 0
    assert rms < 1.0 and mx < 5.0
    assert raw_max > 1500.0  # 20 m/s over 0.1 s: the skew being removed is ~2 m
    assert res.max_shift_m == pytest.approx(raw_max / 1e3, rel=0.02)


def test_exact_against_per_point_scipy_slerp_reference() -> None:
    m, e = Motion(yaw_rate=0.6), lidar_extrinsic()
    sw = make_sweep(m, e, n_cols=600, n_lasers=16)
    track = ins_track(m)
    ours = deskew_points(sw.raw, sw.t_ns, track, e, sw.t0_ns)
    _, mx = _err_mm(ours.xyz, scipy_reference(sw.raw, sw.t_ns, track, e, sw.t0_ns))
    assert mx < 0.1


def test_any_point_order_and_any_reference_time_is_exact() -> None:
    m, e = Motion(yaw_rate=-0.4), lidar_extrinsic()
    sw = make_sweep(m, e, n_cols=300, n_lasers=16)
    track = ins_track(m)
    base = deskew_points(sw.raw, sw.t_ns, track, e, sw.t0_ns)
    perm = np.random.default_rng(3).permutation(len(sw.t_ns))  # e.g. ring-major drivers
    shuffled = deskew_points(sw.raw[perm], sw.t_ns[perm], track, e, sw.t0_ns)
    np.testing.assert_array_equal(shuffled.xyz, base.xyz[perm])
    # arbitrary per-point times (not on a column grid) still follow eq. 3 exactly
    t_odd = sw.t_ns + np.random.default_rng(4).integers(0, 50_000, len(sw.t_ns))
    got = deskew_points(sw.raw, t_odd, track, e, 350_000_000)
    _, mx = _err_mm(got.xyz, scipy_reference(sw.raw, t_odd, track, e, 350_000_000))
    assert mx < 0.1
    # default reference is the scan start
    assert deskew_points(sw.raw, sw.t_ns, track, e).t_ref_ns == sw.t0_ns


def test_per_point_reference_times() -> None:
    m, e = Motion(yaw_rate=0.6), lidar_extrinsic()
    sw = make_sweep(m, e, n_cols=300, n_lasers=8)
    track = ins_track(m)
    const = deskew_points(sw.raw, sw.t_ns, track, e, np.full(len(sw.t_ns), sw.t0_ns))
    np.testing.assert_allclose(const.xyz, deskew_points(sw.raw, sw.t_ns, track, e, sw.t0_ns).xyz,
                               atol=1e-6)
    assert const.t_ref_ns is None
    # each point to its own camera time (30 Hz frames around the sweep)
    cams = sw.t0_ns + np.array([0, 33_333_333, 66_666_667, 100_000_000])
    t_ref = cams[np.random.default_rng(5).integers(0, 4, len(sw.t_ns))]
    got = deskew_points(sw.raw, sw.t_ns, track, e, t_ref)
    _, mx = _err_mm(got.xyz, scipy_reference(sw.raw, sw.t_ns, track, e, t_ref))
    assert mx < 0.1


def test_uncovered_nan_and_empty_are_counted_not_extrapolated() -> None:
    m, e = Motion(), lidar_extrinsic()
    sw = make_sweep(m, e, n_cols=100, n_lasers=4, dual=False, t0_ns=950_000_000)
    track = ins_track(m, 0, 1_000_000_000)  # INS ends mid-sweep
    raw = sw.raw.copy()
    raw[5] = np.nan
    res: DeskewResult = deskew_points(raw, sw.t_ns, track, e, sw.t0_ns)
    beyond = sw.t_ns > 1_000_000_000
    assert res.n_uncovered == int(beyond.sum()) > 0 and res.n_nan == 1
    assert not res.valid[beyond].any() and np.isnan(res.xyz[beyond]).all()
    assert res.uncovered_min_ns == int(sw.t_ns[beyond].min())
    assert res.uncovered_max_ns == int(sw.t_ns.max()) == res.t_max_ns
    ok = ~beyond
    ok[5] = False
    assert res.valid[ok].all() and _err_mm(res.xyz[ok], sw.truth[ok])[1] < 1.0
    # reference time itself uncovered: nothing can be compensated
    none = deskew_points(sw.raw, sw.t_ns, track, e, 2_000_000_000)
    assert none.n_uncovered == len(sw.t_ns) and not none.valid.any()
    empty = deskew_points(np.zeros((0, 3), np.float32), np.zeros(0, np.int64), track, e)
    assert empty.n_points == 0 and empty.n_uncovered == 0 and empty.t_min_ns is None
