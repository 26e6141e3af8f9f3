"""The k-nearest-neighbour searches behind the surfaces (issue #21 item 5, speed only): a
coarser grid of their own (``gicp.knn_grid_cell_m``) and a scan's near and far surface
stores sharing them (:class:`sparse.Neighbours`) must give exactly the surfaces computed
without either."""

from __future__ import annotations

import numpy as np
import pytest

from v2xlake.tasks.register.backends import SparseGicpBackend
from v2xlake.tasks.register.config import GicpSection
from v2xlake.tasks.register.sparse import Surfaces
from v2xlake.tasks.register.voxel import VoxelGrid, voxel_downsample


def _scan(seed: int) -> np.ndarray:
    """Voxel centroids of a road, a wall, a pole and far sparse rings, as a scan's are."""
    rng = np.random.default_rng(seed)
    road = np.c_[rng.uniform(-30, 30, (20000, 2)), rng.normal(0, 0.02, 20000)]
    wall = np.c_[rng.uniform(-30, 30, 6000), np.full(6000, 8.0), rng.uniform(0, 6, 6000)]
    pole = np.c_[rng.normal(3, 0.1, (500, 2)), rng.uniform(0, 5, 500)]
    ang = rng.uniform(0, 2 * np.pi, 3000)
    rings = np.c_[np.cos(ang), np.sin(ang), np.zeros(3000)] * rng.choice([45.0, 52, 60], 3000)[
        :, None]
    return voxel_downsample(np.concatenate([road, wall, pole, rings]), 0.3)


@pytest.mark.parametrize("knn_cell", [0.5, 1.6, 2.5])
def test_knn_grid_finds_the_same_neighbours_in_the_same_order(knn_cell: float) -> None:
    pts = _scan(1)
    q = pts[::5]
    plain = VoxelGrid(pts, 1.0)
    other = VoxelGrid(pts, 1.0, knn_cell)
    for k in (6, 10):
        a, da = plain.batch_knn_search(q, k)
        b, db = other.batch_knn_search(q, k)
        assert np.array_equal(a, b) and np.array_equal(da, db)
    # the nearest-neighbour searches stay on the first grid, the answers as without it
    assert all(np.array_equal(x, y) for x, y in zip(
        plain.batch_nearest_neighbor_search(q + 0.05, max_dist_m=1.0),
        other.batch_nearest_neighbor_search(q + 0.05, max_dist_m=1.0), strict=True))
    few = VoxelGrid(pts[:4], 1.0, knn_cell).batch_knn_search(q[:3], 10)[0]
    assert few.shape == (3, 4)


def test_the_first_columns_of_more_neighbours_are_the_fewer() -> None:
    """What :class:`sparse.Neighbours` relies on: the 6 nearest are the first 6 of the 10
    nearest, in the same order, distances equal included (a grid of repeated spacing)."""
    g = np.stack(np.meshgrid(np.arange(30) * 0.3, np.arange(30) * 0.3, [0.0]), -1)
    for pts in (_scan(2), g.reshape(-1, 3)):
        grid = VoxelGrid(pts, 1.0, 1.6)
        a, da = grid.batch_knn_search(pts, 6)
        b, db = grid.batch_knn_search(pts, 10)
        assert np.array_equal(a, b[:, :6]) and np.array_equal(da, db[:, :6])


def test_far_store_takes_the_near_stores_searches_and_computes_the_same() -> None:
    pts = _scan(3)
    near = SparseGicpBackend(GicpSection())
    far_p = GicpSection().far_pair()
    assert far_p is not None
    far = SparseGicpBackend(far_p)
    base = near.prepare_points(pts)
    fb = far.own_surfaces(base)
    nb = base.handle.neighbours
    assert nb is not None and fb.handle.neighbours is nb
    rng = np.random.default_rng(4)
    first = np.sort(rng.choice(len(pts), 3000, replace=False))
    later = np.sort(rng.choice(len(pts), 3000, replace=False))
    searched: list[int] = []
    search = base.tree.batch_knn_search

    def counted(q: np.ndarray, k: int, num_threads: int = 1) -> tuple[np.ndarray, np.ndarray]:
        searched.append(len(q))
        return search(q, k, num_threads)

    base.tree.batch_knn_search = counted
    base.handle.ensure(base.points, base.tree, first, 10)
    fb.handle.ensure(fb.points, fb.tree, later, 6)
    # the far store searched only the rows the near store had not
    assert searched == [len(first), len(np.setdiff1d(later, first))]
    # and both hold exactly what stores of their own compute
    for rows, k, store in ((first, 10, base.handle), (later, 6, fb.handle)):
        alone = Surfaces.empty(len(pts))
        alone.ensure(pts, VoxelGrid(pts, 1.0), rows, k)
        assert np.array_equal(store.known, alone.known)
        assert np.array_equal(store.normals, alone.normals)
        assert np.array_equal(store.ratio, alone.ratio, equal_nan=True)
