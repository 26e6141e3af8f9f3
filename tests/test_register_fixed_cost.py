"""The register stage's per-clip and per-frame bookkeeping made cheaper (issue #21 item 5,
speed only): each shortcut must give exactly what the work it replaces gave."""

from __future__ import annotations

import numpy as np
import pytest

from v2xlake.tasks.interpolate import PoseTrack
from v2xlake.tasks.register import raster
from v2xlake.tasks.register.scans import AgentScans
from v2xlake.tasks.register.voxel import VoxelGrid, _grid_build, first_per_cell


def _runs(seed: int) -> np.ndarray:
    """Points in runs along rings (consecutive points share a cell, as a scan's centroids
    do), coming back to cells seen before, and a few single points anywhere."""
    rng = np.random.default_rng(seed)
    ang = np.repeat(rng.uniform(0, 2 * np.pi, 300), 6) + rng.normal(0, 1e-3, 1800)
    r = np.repeat(rng.uniform(3, 40, 300), 6)
    ring = np.c_[r * np.cos(ang), r * np.sin(ang), rng.normal(0, 0.3, 1800)]
    pts = np.concatenate([ring, ring[::-7] + 0.05, rng.uniform(-40, 40, (200, 3))])
    return np.ascontiguousarray(pts)


@pytest.mark.parametrize("cell", [0.3, 1.0, 1.6])
def test_first_per_cell_is_the_first_point_of_each_cell(cell: float) -> None:
    pts = _runs(1)
    key = np.floor(pts / cell).astype(np.int64)
    _, first = np.unique(key, axis=0, return_index=True)
    assert np.array_equal(first_per_cell(pts, 1.0 / cell), np.sort(first))


@pytest.mark.parametrize("cell", [0.3, 1.0, 1.6])
def test_grid_groups_every_cell_in_input_order(cell: float) -> None:
    pts = _runs(2)
    bits, rank, start, order, sp, lo, hi = _grid_build(pts, 1.0 / cell)
    c = np.floor(pts / cell).astype(np.int64) + (1 << 20)
    # the cells numbered in box order (x, then y, then z: np.unique's order of the rows),
    # each one's points contiguous and in input order
    cells, inv = np.unique(c, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    assert np.array_equal(order, np.argsort(inv, kind="stable"))
    assert np.array_equal(np.diff(start), np.bincount(inv))
    assert np.array_equal(sp, pts[order])
    assert np.array_equal(lo, c.min(axis=0)) and np.array_equal(hi, c.max(axis=0))
    # the bitmap holds the occupied cells of the box and nothing else; a word's rank counts
    # the occupied cells before it
    at = np.ravel_multi_index(tuple((cells - lo).T), tuple(hi - lo + 1))
    on = np.flatnonzero(np.unpackbits(bits.view(np.uint8), bitorder="little"))
    assert np.array_equal(on, at)
    assert np.array_equal(rank, np.searchsorted(at, 64 * np.arange(len(rank))))
    # and the searches on it are exact
    g = VoxelGrid(pts, cell, 2 * cell)
    i, d2 = g.batch_knn_search(pts[::11], 6)
    brute = ((pts[::11, None, :] - pts[None, :, :]) ** 2).sum(-1)
    assert np.allclose(d2, np.sort(brute, axis=1)[:, :6], rtol=0, atol=1e-12)
    assert np.array_equal(brute[np.arange(len(i))[:, None], i], d2)


def test_queries_above_and_below_the_cloud_find_what_brute_force_finds() -> None:
    """A query two or more cells above or below the cloud's z range: its shells' column ends
    lie outside the grid's box, where a bitmap position is another cell's (a review found
    repeated and wrong neighbours, and an out-of-bounds read, before ``_shell_z`` clipped
    both ends). Every search against brute force; NaN queries are refused."""
    rng = np.random.default_rng(7)
    flat = np.column_stack([rng.uniform(0, 4, 300), rng.uniform(0, 4, 300),
                            rng.uniform(0, 0.5, 300)])
    four = np.array([[0.1, 0.1, 0.0], [1.1, 0.1, 0.0], [0.1, 1.1, 0.0], [1.1, 1.1, 0.0]])
    for pts in (four, flat):
        g = VoxelGrid(pts, 1.0)
        q = np.array([[0.5, 0.5, 3.5], [1.5, 1.5, 2000.0], [0.5, 0.5, -3.5],
                      [2.0, 2.0, -40.0], [3.9, 0.2, 7.3], [0.3, 3.8, -2.2]])
        d_all = ((q[:, None, :] - pts[None, :, :]) ** 2).sum(-1)
        k = len(four)
        idx, d2 = g.batch_knn_search(q, k)
        assert np.allclose(d2, np.sort(d_all, 1)[:, :k])
        for t in range(len(q)):
            assert len(set(idx[t].tolist())) == k  # no point twice
            assert np.allclose(d_all[t, idx[t]], d2[t])
        i1, d1 = g.batch_nearest_neighbor_search(q)
        assert np.allclose(d1, d_all.min(1))
        assert np.allclose(d_all[np.arange(len(q)), i1], d1)
        for radius in (3.0, 8.0):
            ib, db = g.nearest_bounded(q, radius, np.zeros_like(q), np.zeros(len(q)),
                                       np.full(len(q), -1, dtype=np.int64), np.zeros(len(q)))
            within = d_all.min(1) < radius ** 2
            assert np.array_equal(ib >= 0, within)
            assert np.allclose(db[within], d_all.min(1)[within])
    g = VoxelGrid(four, 1.0)
    for bad in ([[np.nan, 0.0, 0.0]], [[0.0, 0.0, np.inf]]):
        with pytest.raises(ValueError, match="finite"):
            g.batch_knn_search(np.array(bad), 2)
        with pytest.raises(ValueError, match="finite"):
            g.batch_nearest_neighbor_search(np.array(bad))


def test_a_cloud_wider_than_the_bitmap_takes_larger_cells() -> None:
    """Points strewn over a box of more cells than the occupancy bitmap holds are gridded
    with larger cells; the searches stay exact."""
    rng = np.random.default_rng(4)
    far = np.array([4e5, -3e5, 0.0])
    pts = np.concatenate([rng.uniform(-5, 5, (300, 3)), [far, [-2e5, 4e5, 50.0]],
                          rng.uniform(-5, 5, (50, 3)) + far])
    g = VoxelGrid(pts, 1.0)
    assert g.inv_cell < 1.0 / 64 and len(g._bits) * 64 <= 2 * (1 << 25)
    q = np.concatenate([pts[::7] + rng.normal(0, 0.2, (len(pts[::7]), 3)), [[1e5, 0, 0]]])
    brute = ((q[:, None, :] - pts[None, :, :]) ** 2).sum(-1)
    i, d2 = g.batch_knn_search(q, 5)
    assert np.array_equal(brute[np.arange(len(q))[:, None], i], d2)
    assert np.array_equal(d2, np.sort(brute, axis=1)[:, :5])
    i1, _ = g.batch_nearest_neighbor_search(q, max_dist_m=1.0)
    near = brute.min(axis=1) <= 1.0
    assert np.array_equal(i1[near], brute.argmin(axis=1)[near]) and (i1[~near] == -1).all()


def test_prefetched_poses_are_the_ones_interpolated_one_at_a_time() -> None:
    t = np.arange(0, 2_000_000_001, 10_000_000, dtype=np.int64)
    rng = np.random.default_rng(3)
    q = rng.normal(size=(len(t), 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    track = PoseTrack(t, np.cumsum(rng.normal(0, 0.1, (len(t), 3)), axis=0), q)

    def scans() -> AgentScans:
        return AgentScans("a", "LIDAR_TOP", track, np.eye(4), {}, lambda f: (
            np.zeros((0, 3), np.float32), np.zeros(0, np.int64)))

    times = [int(x) for x in rng.integers(0, 2_000_000_000, 40)]
    outside = 2_000_000_001 + 5
    one, batch = scans(), scans()
    batch.prefetch([*times, outside])
    assert all(x in batch._world_ego for x in times)  # interpolated at once, not on demand
    for x in times:
        assert np.array_equal(batch.world_ego(x)[0], one.world_ego(x)[0])
    with pytest.raises(ValueError, match="outside the pose coverage"):
        batch.world_ego(outside)  # never prefetched: it still raises where asked


def test_a_label_drawn_again_has_the_same_pixels() -> None:
    raster._glyphs.cache_clear()
    a = raster.Canvas(200, 80)
    a.text(100, 40, "x (cm) 1.5", 14, anchor="mm")
    a.text(30, 40, "y (cm)", 14, rotate=True)
    first = a.png()
    assert raster._glyphs.cache_info().misses == 2
    b = raster.Canvas(200, 80)
    b.text(100, 40, "x (cm) 1.5", 14, anchor="mm")
    b.text(30, 40, "y (cm)", 14, rotate=True)
    assert b.png() == first and raster._glyphs.cache_info().hits == 2
    mask, _, _ = raster._glyphs("y (cm)", 14, "mm", True)
    assert mask.any() and not mask.flags.writeable
