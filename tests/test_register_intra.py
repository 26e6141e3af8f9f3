"""Several LiDARs on one agent (issue #27): intra-agent extrinsic refinement on real scans
(../shared/data/real/lidar2lidar, read in place) and on simulated rigs.

Real files: two scenes of one vehicle (top + two tilted side LiDARs, published extrinsics
~45 deg / 10 cm off) and a Pandar64 + QT64 pair with a manual calibration. Simulated: the
ray-cast street of tests/test_register.py seen by a top LiDAR and a tilted side LiDAR whose
true mounting is known, so recovery is measured against the truth, not against a file.
"""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest

from tests.fixtures.real import require_real_data, requires_real_data
from tests.test_register import Street, cast_scan, lidar_pose, make_street
from v2xlake.tasks.geometry import invert, so3_exp
from v2xlake.tasks.register.intra import (
    IntraConfig,
    IntraResult,
    combine,
    euler_zyx,
    nearest_rigid,
    pose_distance,
    refine_extrinsic,
)
from v2xlake.tasks.register.intra_data import (
    read_initial_extrinsics,
    read_json_extrinsic,
    read_pcd_xyz,
)

L2L = "lidar2lidar"
SCENES = ("scene_0001", "scene_0002")
SIDES = {"left": 1, "right": 2}  # device ids in initial_extrinsic.txt


def perturb(T: np.ndarray, deg: float, m: float, rng: np.random.Generator) -> np.ndarray:
    """``T`` moved by ``deg`` about a random axis (sensor frame) and ``m`` along a random
    direction."""
    a = rng.normal(size=3)
    b = rng.normal(size=3)
    P = np.eye(4)
    P[:3, :3] = so3_exp(np.radians(deg) * a / np.linalg.norm(a))
    P[:3, 3] = m * b / np.linalg.norm(b)
    return T @ P


# ---------------------------------------------------------------------------- real scenes


@cache
def _scene_result(scene: str, side: str) -> IntraResult:
    root = require_real_data(f"{L2L}/{scene}") / L2L / scene
    init = read_initial_extrinsics(root / "initial_extrinsic.txt")[SIDES[side]]
    return refine_extrinsic(read_pcd_xyz(root / "top.pcd"), read_pcd_xyz(root / f"{side}.pcd"),
                            init)


@requires_real_data(f"{L2L}/scene_0001", f"{L2L}/scene_0002")
@pytest.mark.parametrize("side", sorted(SIDES))
def test_real_scenes_agree_between_scenes(side: str) -> None:
    """Each scene refined on its own from the published start (~45 deg off): both accepted,
    both ~45 deg from the start, and they agree within 2 cm / 0.4 deg (issue #27 item 2)."""
    a, b = (_scene_result(s, side) for s in SCENES)
    for r in (a, b):
        assert r.accepted, r.reason
        deg, m = r.correction
        assert 40.0 < deg < 50.0 and 0.05 < m < 0.2, (deg, m)  # the real mounting's offset
        assert r.std_deg < 0.5 and r.std_m < 0.05
    deg, m = pose_distance(a.T, b.T)
    assert deg < 0.4 and m < 0.02, (deg, m)
    # the reported 1-sigma is honest: the disagreement is within 3 sigma of the difference
    assert deg < 3 * np.hypot(a.std_deg, b.std_deg) and m < 3 * np.hypot(a.std_m, b.std_m)
    pooled = combine([a, b])
    assert pooled.accepted, pooled.reason
    assert pooled.T is not None and pose_distance(pooled.T, a.T)[0] < 0.4


@requires_real_data(f"{L2L}/scene_0001", f"{L2L}/scene_0002")
def test_real_scenes_wrong_rig_disagrees() -> None:
    """The left LiDAR's estimate of one scene pooled with the right LiDAR's of the other is
    the same 'rig' disagreeing by metres: refused, nothing vouched for."""
    pooled = combine([_scene_result("scene_0001", "left"), _scene_result("scene_0002", "right")])
    assert not pooled.accepted and pooled.T is None
    assert "disagree" in pooled.reason


@requires_real_data(f"{L2L}/scene_0001")
def test_real_beyond_search_is_refused() -> None:
    """A start 150 deg off (beyond the searched +-60 deg): whatever minimum the search finds
    there is refused, never accepted."""
    root = require_real_data(f"{L2L}/scene_0001") / L2L / "scene_0001"
    truth = _scene_result("scene_0001", "left").T
    start = perturb(truth, 150.0, 0.1, np.random.default_rng(7))
    r = refine_extrinsic(read_pcd_xyz(root / "top.pcd"), read_pcd_xyz(root / "left.pcd"), start)
    assert not r.accepted, (r.reason, pose_distance(truth, r.T))
    assert r.reason


# ------------------------------------------------------------------------ Pandar64 / QT64


@cache
def _p64_qt() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    root = require_real_data(f"{L2L}/p64_qt_manual") / L2L / "p64_qt_manual"
    # the JSON's matrix takes Pandar64 points into the QT64 frame: T_qt_p64 (its inverse
    # overlaps the clouds, the matrix itself does not); primary = Pandar64. Its 3x3 is not a
    # rotation (singular values 0.989-0.990): the nearest rigid transform is the calibration
    T_qt_p64, scale_dev = nearest_rigid(read_json_extrinsic(root / "p64-to-qt-extrinsic.json"))
    assert 0.009 < scale_dev < 0.012, scale_dev
    T_p64_qt = invert(T_qt_p64)
    return read_pcd_xyz(root / "p64.pcd"), read_pcd_xyz(root / "qt.pcd"), T_p64_qt


@requires_real_data(f"{L2L}/p64_qt_manual")
def test_p64_qt_perturbed_manual_calibration() -> None:
    """Perturbed by up to 20 cm / 5 deg (fixed seeds), the refinement lands on one and the same
    minimum from every start (within 2 cm / 0.2 deg of each other) and the manual
    calibration lies within 3 of its reported 1-sigma.

    Measured (docs/registration.md): that minimum is 0.76 deg / 13.9 cm from the manual
    calibration (made rigid: the file's 3x3 carries a 1.1% scale, which, kept, put it 0.8 deg /
    19.5 cm away), and this pair does not pin the extrinsic down to the issue's 2 cm / 0.2 deg:
    GICP on half of the QT64 scan moves 0.4-0.8 deg / 4-10 cm, point-to-plane ICP lands 0.1 deg
    / 2 cm from GICP and 0.83 deg / 12 cm from the manual one, the reverse direction (QT64 as
    primary) 0.73 deg / 11.8 cm from it. So the honest 1-sigma is ~0.6 deg / 6 cm and the
    default thresholds REFUSE the pair (half-scans disagree); looser ones accept it."""
    p64, qt, manual = _p64_qt()
    rng = np.random.default_rng(2027)
    loose = IntraConfig(max_std_deg=2.0, max_std_m=0.3, split_halves=2)
    results = []
    for k in range(3):
        start = perturb(manual, 5.0 * (1 - 0.3 * k), 0.2 * (1 - 0.3 * k), rng)
        r = refine_extrinsic(p64, qt, start, loose)
        assert r.accepted, r.reason
        results.append(r)
    for r in results[1:]:
        deg, m = pose_distance(results[0].T, r.T)
        assert deg < 0.2 and m < 0.02, (deg, m)
    for r in results:
        deg, m = pose_distance(manual, r.T)
        assert deg < 3 * r.std_deg and m < 3 * r.std_m, (deg, m, r.std_deg, r.std_m)
    strict = refine_extrinsic(p64, qt, perturb(manual, 3.0, 0.1, rng))
    assert not strict.accepted and "half-scans disagree" in strict.reason, strict.reason


def _cascade(primary: np.ndarray, secondary: np.ndarray, T0: np.ndarray) -> np.ndarray:
    """The refinement's multi-scale GICP finish alone (small_gicp), from ``T0``."""
    import small_gicp

    T = T0
    for voxel, _, corr in IntraConfig().fine_stages:
        r = small_gicp.align(primary, secondary, init_T_target_source=T,
                             registration_type="GICP", downsampling_resolution=voxel,
                             max_correspondence_distance=corr, max_iterations=100,
                             num_threads=1)
        T = np.asarray(r.T_target_source)
    return T


@requires_real_data(f"{L2L}/p64_qt_manual")
def test_p64_qt_offset_is_not_ours() -> None:
    """Why the data's minimum sits ~14 cm from the manual calibration -- the suspects on our
    side, each checked on the real pair:

    * a non-rigid matrix (found, fixed): the file's 3x3 has singular values 0.989-0.990;
      GICP started from it kept the 1.1% scale in every result and ``invert`` (a transpose)
      assumed a rotation: the minimum sat 0.8 deg / 19.5 cm away, from the nearest rigid
      transform it sits 0.74 deg / 13.6 cm away (``nearest_rigid``, ``_p64_qt``);
    * frame convention: the file's matrix maps Pandar64 points into the QT64 frame (the
      upstream manual tool applies it to its source cloud, p64.pcd, over the target qt.pcd);
      its inverse overlaps the clouds, the matrix itself does not (measured: 21% vs 0.4% of
      the QT64 points within 20 cm of a Pandar64 point);
    * the QT64's near field / the vehicle body (its median range is 2.9 m, and it sees the
      car behind it): dropping every QT64 point within 3 m moves the minimum by 0.01 deg /
      0.8 cm;
    * ground vs structure: either alone lands 11.5-11.7 cm from the manual calibration too.
    (Measured besides, docs/registration.md: deskewing both scans at any speed up to 4 m/s moves the
    minimum by up to 10 cm but never onto the manual calibration; the two scans' clocks are
    2.8 years apart, so their pairing in time cannot be checked.)"""
    from scipy.spatial import cKDTree

    p64, qt, manual = _p64_qt()
    tree = cKDTree(p64)

    def close(T: np.ndarray) -> float:
        d, _ = tree.query(qt @ T[:3, :3].T + T[:3, 3], distance_upper_bound=0.2)
        return float(np.isfinite(d).mean())

    assert close(manual) > 10 * close(invert(manual))
    full = _cascade(p64, qt, manual)
    assert abs(np.linalg.det(full[:3, :3]) - 1.0) < 1e-9  # rigid in, rigid out
    far = _cascade(p64, qt[np.linalg.norm(qt, axis=1) >= 3.0], manual)
    deg, m = pose_distance(full, far)
    assert deg < 0.1 and m < 0.02, (deg, m)
    z = qt @ manual[2, :3] + manual[2, 3]  # height in the Pandar64 frame
    ground = z < np.percentile(z, 20) + 0.3
    for part in (qt[ground], qt[~ground]):
        deg, m = pose_distance(manual, _cascade(p64, part, manual))
        assert m > 0.08, (deg, m)
    assert pose_distance(manual, full)[1] > 0.1


@requires_real_data(f"{L2L}/p64_qt_manual")
def test_p64_qt_beyond_recovery_is_refused() -> None:
    """150 deg off the manual calibration: refused (ambiguous or out of the searched region)."""
    p64, qt, manual = _p64_qt()
    r = refine_extrinsic(p64, qt, perturb(manual, 150.0, 0.2, np.random.default_rng(3)))
    assert not r.accepted and r.reason


# ---------------------------------------------------------------------------- simulated rig

T_TOP_SIDE = np.eye(4)
T_TOP_SIDE[:3, :3] = euler_zyx(40.0, 5.0, 90.0)  # a side LiDAR rolled 40 deg down to the left
T_TOP_SIDE[:3, 3] = (0.3, 0.9, -0.4)


@cache
def _sim_rig(x: float, flat: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(top scan, side scan) at street position ``x``; ``flat``: nothing but the ground."""
    street = make_street(5, length=160.0)
    if flat:
        street = Street(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))
    T_w_top = lidar_pose(x, -1.75, 2.0, roll_deg=0.3, pitch_deg=0.2, height=1.9)
    top = cast_scan(street, T_w_top, n_beams=32, n_cols=720, max_range=80.0, seed=1)
    side = cast_scan(street, T_w_top @ T_TOP_SIDE, n_beams=16, n_cols=600, max_range=40.0,
                     seed=2)
    near = np.linalg.norm(top, axis=1) > 3.0  # the top LiDAR's blind zone (the real one: 5 m)
    return top[near].astype(np.float64), side.astype(np.float64)


def test_sim_rig_recovers_truth_from_45_deg() -> None:
    """A published extrinsic 45 deg / 10 cm off the true mounting: recovered within 2 cm /
    0.2 deg at two places of the street, each with a 1-sigma that covers its error, and the
    two frames pooled."""
    rng = np.random.default_rng(11)
    results = []
    for x in (-20.0, 15.0):
        top, side = _sim_rig(x)
        start = perturb(T_TOP_SIDE, 45.0, 0.1, rng)
        r = refine_extrinsic(top, side, start)
        assert r.accepted, r.reason
        deg, m = pose_distance(T_TOP_SIDE, r.T)
        assert deg < 0.2 and m < 0.02, (deg, m)
        assert deg < 3 * r.std_deg and m < 3 * r.std_m
        results.append(r)
    pooled = combine(results)
    assert pooled.accepted and pooled.T is not None, pooled.reason
    deg, m = pose_distance(T_TOP_SIDE, pooled.T)
    assert deg < 0.2 and m < 0.02


def test_sim_plain_gicp_needs_the_search() -> None:
    """The search is what makes 45 deg recoverable: without it (a single seed, the published
    start) the same pipeline does not reach the truth from this start (measured: its finish
    slides 6 deg / 61 cm off the coarse end point, 45 deg / 3.5 m from the truth, and is
    refused for it), while the search recovers it."""
    top, side = _sim_rig(-20.0)
    start = perturb(T_TOP_SIDE, 45.0, 0.1, np.random.default_rng(11))
    single = refine_extrinsic(top, side, start, IntraConfig(seed_max_deg=0.0))
    full = refine_extrinsic(top, side, start)
    assert full.accepted
    deg_full = pose_distance(T_TOP_SIDE, full.T)[0]
    deg_single = pose_distance(T_TOP_SIDE, single.T)[0]
    assert deg_full < 0.2
    assert deg_single > 1.0  # plain GICP from the published start misses the mounting ...
    assert not single.accepted, single.reason  # ... and says so rather than accepting it


def test_sim_single_plane_is_refused() -> None:
    """Ground only: rotation about the normal and translation in the plane are unobserved
    (and every yaw seed scores alike): refused, not accepted."""
    top, side = _sim_rig(0.0, flat=True)
    r = refine_extrinsic(top, side, perturb(T_TOP_SIDE, 5.0, 0.05, np.random.default_rng(1)))
    assert not r.accepted
    assert "ambiguous" in r.reason or "not observed" in r.reason or "1-sigma" in r.reason


def test_sim_disagreeing_frames_are_refused() -> None:
    """Frames that disagree (one of them off by a wrong minimum's 16 deg) cannot be pooled
    when they are half of the estimates; a single outlier among three is left out."""
    top, side = _sim_rig(-20.0)
    good = refine_extrinsic(top, side, T_TOP_SIDE)
    assert good.accepted, good.reason
    wrong_T = T_TOP_SIDE.copy()
    wrong_T[:3, :3] = so3_exp(np.radians(16.0) * np.array([0.0, 1.0, 0.0])) @ wrong_T[:3, :3]
    wrong = IntraResult(good.T_init, wrong_T, True, "stand-in wrong minimum", good.cov,
                        good.std_deg, good.std_m)
    two = combine([good, wrong])
    assert not two.accepted and "disagree" in two.reason
    three = combine([good, good, wrong])
    assert three.accepted and three.used == (0, 1) and "disagreeing left out" in three.reason
