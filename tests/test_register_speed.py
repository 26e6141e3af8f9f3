"""The register stage's speed work must not change its results: the sparse backend's hash
grid searches are exact, the voxel and sample passes are deterministic, and the per-frame
work gives the same registrations on any number of worker threads."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from v2xlake.tasks.register.sparse import spread_sample
from v2xlake.tasks.register.voxel import VoxelGrid, voxel_downsample_t


def _brute(points: np.ndarray, q: np.ndarray) -> np.ndarray:
    return np.asarray(((q[:, None, :] - points[None, :, :]) ** 2).sum(-1))


@pytest.mark.parametrize("cell", [0.35, 1.0, 3.0])
def test_grid_searches_are_exact(cell: float) -> None:
    rng = np.random.default_rng(3)
    # a wall, a ground patch and scattered points, queries inside and far outside the cloud
    pts = np.concatenate([
        np.c_[rng.uniform(-10, 10, 800), np.full(800, 4.0), rng.uniform(0, 5, 800)],
        np.c_[rng.uniform(-10, 10, (800, 2)), rng.normal(0, 0.02, 800)],
        rng.uniform(-15, 15, (200, 3))])
    q = np.concatenate([pts[::7] + rng.normal(0, 0.1, (len(pts[::7]), 3)),
                        rng.uniform(-30, 30, (100, 3))])
    D = _brute(pts, q)
    g = VoxelGrid(pts, cell)
    idx, d2 = g.batch_nearest_neighbor_search(q)
    assert np.array_equal(idx, D.argmin(1))
    assert np.allclose(d2, D.min(1), rtol=1e-12, atol=1e-12)
    idx, d2 = g.batch_nearest_neighbor_search(q, max_dist_m=0.3)
    near = D.min(1) <= 0.09
    assert np.array_equal(idx[near], D.argmin(1)[near]) and (idx[~near] == -1).all()
    assert np.isinf(d2[~near]).all()
    knn, kd2 = g.batch_knn_search(q, 10)
    assert np.allclose(kd2, np.sort(D, 1)[:, :10], rtol=1e-12, atol=1e-12)
    assert all(set(row) == set(np.argsort(D[i])[:10]) for i, row in enumerate(knn))
    few = VoxelGrid(pts[:4], cell).batch_knn_search(q[:3], 10)[0]
    assert few.shape == (3, 4) and all(set(r) == {0, 1, 2, 3} for r in few)


def test_bounded_search_skips_only_what_cannot_match() -> None:
    """``nearest_bounded`` on a source moving step by step (as in GICP iterations) gives the
    plain bounded search's answer every time, while skipping queries that found nothing
    and queries that cannot have a new nearest point."""
    from v2xlake.tasks.register.voxel import _grid_nn_held

    rng = np.random.default_rng(7)
    pts = np.concatenate([
        np.c_[rng.uniform(-10, 10, 1500), np.full(1500, 4.0), rng.uniform(0, 5, 1500)],
        np.c_[rng.uniform(-10, 10, (1500, 2)), rng.normal(0, 0.02, 1500)]])
    src = np.concatenate([pts[::5] + rng.normal(0, 0.3, (len(pts[::5]), 3)),
                          rng.uniform(-25, 25, (400, 3))])
    g = VoxelGrid(pts, 1.0)
    state = (np.zeros((len(src), 3)), np.zeros(len(src)),
             np.full(len(src), -1, dtype=np.int64), np.zeros(len(src)))
    # the same with the held points forgotten before every call: the misses' bounds alone
    misses = (np.zeros((len(src), 3)), np.zeros(len(src)),
              np.full(len(src), -1, dtype=np.int64), np.zeros(len(src)))
    skipped = skipped_misses = 0
    for it in range(12):
        # shrinking steps, as GICP's, with one large jump that must invalidate bounds
        step = 0.6 if it == 6 else 0.2 / (it + 1)
        src = src + rng.normal(0, step, 3)
        want_i, want_d = g.batch_nearest_neighbor_search(src, max_dist_m=1.0)
        a0, l0, h0, s0 = (x.copy() for x in state)
        i, d2, sk = _grid_nn_held(g._bits, g._rank, g._start, g._order, g._sp, g._lo,
                                  g._hi, g.inv_cell, src, 1.0, a0, l0, h0, s0)
        assert np.array_equal(i, want_i) and np.array_equal(d2, want_d)
        got_i, got_d = g.nearest_bounded(src, 1.0, *state)
        assert np.array_equal(got_i, want_i) and np.array_equal(got_d, want_d)
        for x, y in zip(state, (a0, l0, h0, s0), strict=True):
            assert np.array_equal(x, y)
        found = want_i >= 0
        lb, hold = state[1], state[2]
        assert (lb[found] == 0).all() and (lb[~found] > 1.0).all()
        assert np.array_equal(g._order[hold[found]], want_i[found])
        assert (hold[~found] == -1).all()
        skipped += sk
        misses[2][:] = -1
        i, d2, sk = _grid_nn_held(g._bits, g._rank, g._start, g._order, g._sp, g._lo,
                                  g._hi, g.inv_cell, src, 1.0, *misses)
        assert np.array_equal(i, want_i) and np.array_equal(d2, want_d)
        skipped_misses += sk
    # the bounds skip the far misses' searches (400 far queries x 11 iterations), and the
    # held nearest points the near queries' searches in the small steps too
    assert skipped_misses > 1000 and skipped > skipped_misses + 500
    with pytest.raises(ValueError):
        g.nearest_bounded(src, 1.0, *state[:3], np.zeros(3))


def test_voxel_table_growth_and_sample_are_first_seen() -> None:
    rng = np.random.default_rng(5)
    xyz = rng.uniform(-60, 60, (200_000, 3))  # ~190k voxels of 0.2 m: the table grows twice
    xyz[::11] = np.nan
    val = rng.normal(size=len(xyz))
    pts, mean = voxel_downsample_t(xyz, val, 0.2, 100.0)
    ok = np.isfinite(xyz).all(1) & ((xyz**2).sum(1) <= 100.0**2)
    key = np.floor(xyz[ok] / 0.2).astype(np.int64)
    _, first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)  # first-seen order
    cnt = np.bincount(inv.ravel())
    cen = np.stack([np.bincount(inv.ravel(), xyz[ok][:, a]) / cnt for a in range(3)], 1)
    assert len(pts) == len(first)
    assert np.allclose(pts, cen[order], atol=1e-9)
    assert np.allclose(mean, (np.bincount(inv.ravel(), val[ok]) / cnt)[order], atol=1e-9)
    s = spread_sample(pts, 0.9)
    k = np.floor(pts / 0.9).astype(np.int64)
    assert np.array_equal(s, np.sort(np.unique(k, axis=0, return_index=True)[1]))


@pytest.fixture(scope="module")
def deskewed_pair(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The three-frame two-agent street of test_register_stage, deskewed once."""
    from tests.test_register_stage import write_clip
    from v2xlake.storage.lake import Lake
    from v2xlake.tasks.deskew.stage import run_deskew

    root = tmp_path_factory.mktemp("register_workers") / "lake"
    lake = Lake(root)
    write_clip(lake)
    run_deskew(lake, "street1")
    return root


@pytest.mark.parametrize("backend", ["sparse", "small_gicp"])
def test_any_number_of_workers_gives_the_same_registrations(
        deskewed_pair: Path, tmp_path: Path, backend: str) -> None:
    import shutil

    from v2xlake.storage.lake import Lake
    from v2xlake.tasks.register.stage import RegisterConfig, run_register

    rows = {}
    for workers in (1, 2):
        shutil.copytree(deskewed_pair, tmp_path / str(workers))
        lake = Lake(tmp_path / str(workers))
        # odometry over consecutive frames, so its GICP also runs on the pool
        rep = run_register(lake, "street1", RegisterConfig.model_validate({
            "workers": workers, "write_bev": False, "gicp": {"backend": backend},
            "odometry": {"every": 1, "gap": 1, "straight_every": 1}}))
        assert rep.metrics["n_pairs"] == 3 and rep.metrics["n_odometry"] >= 2
        rows[workers] = (lake.read_table("clean", "registrations", clip_id="street1")
                         .sort_by("frame_idx").to_pylist(),
                         lake.read_table("clean", "calibration_refined", clip_id="street1")
                         .to_pylist())
    assert rows[1] == rows[2]


def test_three_agents_register_the_same_with_their_pairs_in_parallel(tmp_path: Path) -> None:
    """With several other agents each frame's cross pairs run side by side (the first on the
    calling thread, the others on a pool of their own): the registrations must be those of
    one worker, where they run one after the other. The third agent is a stationary mast, so
    its scan is prepared on frame 0 and reused by frames 1 and 2 (``stationary``), with any
    number of workers; with ``reuse_frames: 1`` each frame has its own scan."""
    import shutil

    import tests.test_register_stage as rs
    from tests.test_register import lidar_pose
    from v2xlake.storage.lake import Lake
    from v2xlake.tasks.deskew.stage import run_deskew
    from v2xlake.tasks.register.stage import RegisterConfig, run_register

    # a third agent: a roadside unit on a 4 m mast, its INS exact (surveyed)
    rs.EXTR["mast"] = lidar_pose(0.0, 0.0, 0.0, pitch_deg=2.0, height=4.0)
    rs.BIAS["mast"] = np.eye(4)
    try:
        lake = Lake(tmp_path / "base")
        rs.write_clip(lake, ("red", "black", "mast"))
    finally:
        del rs.EXTR["mast"], rs.BIAS["mast"]
    run_deskew(lake, rs.CLIP)
    # the stage's links between a stationary agent's prepared scans (``backend.follow``):
    # with reuse_frames 2 the mast's anchors are frames 0 and 2, and 2 follows 0
    from v2xlake.tasks.register.backends import SparseGicpBackend

    links: list[bool] = []
    follow = SparseGicpBackend.follow

    def spy(pairs: list[tuple[object, object]]) -> None:
        links.extend(old is not None for _new, old in pairs)
        follow(pairs)  # type: ignore[arg-type]

    rows = {}
    for workers, reuse, inherit in ((1, 5, True), (2, 5, True), (1, 1, True), (1, 2, True),
                                    (1, 2, False)):
        key = (workers, reuse) if inherit else (workers, reuse, "off")
        shutil.copytree(tmp_path / "base", tmp_path / "_".join(map(str, key)))
        lk = Lake(tmp_path / "_".join(map(str, key)))
        links.clear()
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(SparseGicpBackend, "follow", staticmethod(spy))
            rep = run_register(lk, rs.CLIP, RegisterConfig.model_validate(
                {"workers": workers, "write_bev": False,
                 "stationary": {"reuse_frames": reuse, "inherit_surfaces": inherit}}))
        assert rep.metrics["n_pairs"] == 6
        # one link per store (near and far) from frame 2's anchor to frame 0's, only there
        assert links == ([True, True] if key == (1, 2) else []), (key, links)
        rows[key] = (lk.read_table("clean", "registrations", clip_id=rs.CLIP)
                     .sort_by([("agent_other", "ascending"),
                               ("frame_idx", "ascending")]).to_pylist())
    assert {r["agent_other"] for r in rows[1, 5]} == {"black", "mast"}
    assert rows[1, 5] == rows[2, 5]
    assert rows[1, 2] == rows[1, 2, "off"]  # inherited surfaces: the same registrations

    def mast_points(rr: list[dict[str, object]]) -> list[object]:
        return [r["n_points_other"] for r in rr if r["agent_other"] == "mast"]
    assert len(set(mast_points(rows[1, 5]))) == 1  # frame 0's scan stands for 1 and 2
    assert len(set(mast_points(rows[1, 1]))) == 3  # each its own (ray noise differs)
    # black moves: its GICP is what it was (the clip solve, shared with the mast, may move)
    keys = ("gicp_tx", "gicp_ty", "gicp_tz", "gicp_qw", "fitness", "n_points_other")
    assert [[r[k] for k in keys] for r in rows[1, 5] if r["agent_other"] == "black"] == \
        [[r[k] for k in keys] for r in rows[1, 1] if r["agent_other"] == "black"]


def test_a_stationary_track_is_what_its_poses_say() -> None:
    from v2xlake.tasks.register.scans import is_stationary

    n = 50
    q = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    still = np.tile([10.0, -3.0, 4.0], (n, 1))
    assert is_stationary(still, q, 0.02, 0.05)
    sway = still.copy()
    sway[n // 2, 1] += 0.03  # a mast swaying 3 cm
    assert not is_stationary(sway, q, 0.02, 0.05) and is_stationary(sway, q, 0.04, 0.05)
    turned = q.copy()
    a = np.radians(0.1) / 2  # 0.1 deg about z
    turned[-1] = [np.cos(a), 0.0, 0.0, np.sin(a)]
    assert not is_stationary(still, turned, 0.02, 0.05) and is_stationary(still, turned, 0.02,
                                                                            0.11)
    drive = still + np.linspace(0, 5, n)[:, None] * [1.0, 0.0, 0.0]
    assert not is_stationary(drive, q, 0.02, 0.05)
    assert not is_stationary(np.zeros((0, 3)), np.zeros((0, 4)), 0.02, 0.05)


def test_sample_pairs_are_read_from_the_dense_search() -> None:
    from v2xlake.tasks.register.backends import pairs_within, sample_sq_dist

    def sample_pairs(sample: np.ndarray, dense: np.ndarray, sq: np.ndarray | None,
                     max_m: float) -> int:  # as the dense pass decides a short sample
        return pairs_within(sample_sq_dist(sample, dense, sq), max_m)

    dense = np.array([0, 2, 3, 5, 8, 9])
    sq = np.array([0.1, 4.0, 0.5, np.inf, 1.0, 0.2])
    # 2: too far (2 m > 1 m), 5: none, 7: not a dense row, 8: exactly at the bound, 9: found
    assert sample_pairs(np.array([2, 5, 7, 8, 9]), dense, sq, 1.0) == 2
    assert sample_pairs(np.array([0, 3, 9, 11]), dense, sq, 1.0) == 3
    assert sample_pairs(np.array([0, 3]), dense, None, 1.0) == 0


def test_quality_figures_reuse_the_dense_search_and_search_the_rest() -> None:
    """A dense pass's last search gives its sample rows' distances; a sample row outside the
    dense rows is searched at the result, so the figures equal a search of every row."""
    from dataclasses import replace

    from v2xlake.tasks.register.backends import make_backend, sample_sq_dist
    from v2xlake.tasks.register.config import GicpSection
    from v2xlake.tasks.register.core import evaluate

    dense = np.array([0, 2, 3, 5, 8, 9])
    sq = np.array([0.1, 4.0, 0.5, np.inf, 1.0, 0.2])
    got = sample_sq_dist(np.array([2, 7, 9]), dense, sq)
    assert got is not None and got[0] == 4.0 and np.isnan(got[1]) and got[2] == 0.2
    assert sample_sq_dist(np.array([2]), dense, None) is None

    rng = np.random.default_rng(0)
    pts = rng.uniform(-10, 10, (400, 3))
    backend = make_backend("sparse", GicpSection())
    target = backend.prepare(pts)
    sample = np.arange(0, len(target.points), 2)
    source = replace(target, sample=sample)
    T = np.eye(4)
    T[:3, 3] = [0.05, 0.0, 0.0]
    full = evaluate(backend, target, source, T, 0.5)
    d2 = backend.nearest_sq_dist(target, target.points[sample] + T[:3, 3], 0.5)
    part = d2.copy()
    part[::3] = np.nan  # rows the dense search did not cover
    assert evaluate(backend, target, source, T, 0.5, part) == full


def test_workers_default_to_this_process_cores_capped() -> None:
    import os

    from v2xlake.tasks.register.stage import MAX_WORKERS, RegisterConfig, register_workers

    auto = register_workers(RegisterConfig())
    assert auto == max(1, min(len(os.sched_getaffinity(0)), MAX_WORKERS))
    assert register_workers(RegisterConfig.model_validate({"workers": 3})) == 3
