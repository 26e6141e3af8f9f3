"""A stationary agent's scan takes its surfaces from its previous scan where they cannot
differ (issue #21 item 5, speed only: ``stationary.inherit_surfaces``,
:class:`sparse.Predecessor`): exactly the surfaces of a store of its own, fewer searches."""

from __future__ import annotations

import numpy as np

from v2xlake.tasks.register.backends import SparseGicpBackend
from v2xlake.tasks.register.config import GicpSection
from v2xlake.tasks.register.sparse import Surfaces
from v2xlake.tasks.register.voxel import VoxelGrid, voxel_downsample


def _street(seed: int) -> np.ndarray:
    """Raw points of a road, a wall and a pole (the static scene a mast sees)."""
    rng = np.random.default_rng(seed)
    road = np.c_[rng.uniform(-30, 30, (20000, 2)), rng.normal(0, 0.02, 20000)]
    wall = np.c_[rng.uniform(-30, 30, 6000), np.full(6000, 8.0), rng.uniform(0, 6, 6000)]
    pole = np.c_[rng.normal(3, 0.1, (500, 2)), rng.uniform(0, 5, 500)]
    return np.concatenate([road, wall, pole])


def _counting(prep: object) -> list[int]:
    searched: list[int] = []
    tree = prep.tree  # type: ignore[attr-defined]
    search = tree.batch_knn_search

    def counted(q: np.ndarray, k: int, num_threads: int = 1) -> tuple[np.ndarray, np.ndarray]:
        searched.append(len(q))
        return search(q, k, num_threads)

    tree.batch_knn_search = counted
    return searched


def test_the_next_scan_inherits_exactly_what_it_would_compute() -> None:
    static = _street(1)
    rng = np.random.default_rng(2)
    car_a = np.c_[rng.uniform(-10, -6, (800, 1)), rng.uniform(1, 3, (800, 1)),
                  rng.uniform(0, 1.5, (800, 1))]
    car_b = car_a + np.array([12.0, 0.0, 0.0])  # where the car stood first, hiding the road
    hidden = (static[:, 0] > 2) & (static[:, 0] < 6) & (static[:, 1] > 0.5) \
        & (static[:, 1] < 3.5)
    first = voxel_downsample(np.concatenate([static[~hidden], car_b]), 0.3)
    second = voxel_downsample(np.concatenate([static, car_a]), 0.3)
    backend = SparseGicpBackend(GicpSection())
    old, new = backend.prepare_points(first), backend.prepare_points(second)
    rows_old = np.arange(len(first))
    old.handle.ensure(old.points, old.tree, rows_old, 10)
    backend.follow([(new, old)])
    searched = _counting(new)
    rows = np.arange(len(second))
    new.handle.ensure(new.points, new.tree, rows, 10)
    alone = Surfaces.empty(len(second))
    alone.ensure(second, VoxelGrid(second, 1.0), rows, 10)
    assert np.array_equal(new.handle.known, alone.known)
    assert np.array_equal(new.handle.normals, alone.normals)
    assert np.array_equal(new.handle.ratio, alone.ratio, equal_nan=True)
    # most points and their surroundings did not change; those near both cars did
    assert 0 < searched[0] < 0.2 * len(second)
    near_cars = (np.abs(second[:, 1] - 2) < 3) & ((np.abs(second[:, 0] + 8) < 4)
                                                   | (np.abs(second[:, 0] - 4) < 4))
    assert searched[0] >= int(near_cars.sum()) // 4


def test_another_number_of_neighbours_or_a_dropped_link_inherits_nothing() -> None:
    pts = voxel_downsample(_street(3), 0.3)
    backend = SparseGicpBackend(GicpSection())
    old, new = backend.prepare_points(pts), backend.prepare_points(pts.copy())
    rows = np.arange(0, len(pts), 7)
    old.handle.ensure(old.points, old.tree, rows, 6)
    backend.follow([(new, old)])
    searched = _counting(new)
    new.handle.ensure(new.points, new.tree, rows, 10)  # 10 neighbours: none taken
    assert searched == [len(rows)]
    again = backend.prepare_points(pts.copy())
    backend.follow([(again, old)])
    backend.follow([(again, None)])
    searched = _counting(again)
    again.handle.ensure(again.points, again.tree, rows, 6)
    assert searched == [len(rows)]
    same = backend.prepare_points(pts.copy())
    backend.follow([(same, old)])
    searched = _counting(same)
    same.handle.ensure(same.points, same.tree, rows, 6)  # identical scan: every one taken
    assert searched == []
    assert np.array_equal(same.handle.normals, old.handle.normals)


def test_reach_is_the_kth_neighbour_squared_distance() -> None:
    """``Surfaces.reach`` (what inheritance trusts): each computed row's squared distance to
    its k-th nearest point, by brute force; NaN where no surface was computed."""
    pts = voxel_downsample(_street(3), 0.3)
    s = Surfaces.empty(len(pts))
    rows = np.arange(0, len(pts), 50)
    s.ensure(pts, VoxelGrid(pts, 1.0), rows, 10)
    d2 = sum((pts[rows, c, None] - pts[None, :, c]) ** 2 for c in range(3))
    kth = np.sort(d2, axis=1)[:, 9]
    assert s.reach is not None
    assert np.allclose(s.reach[rows], kth, rtol=1e-12, atol=1e-12)
    rest = np.ones(len(pts), dtype=bool)
    rest[rows] = False
    assert np.isnan(s.reach[rest]).all()


def test_a_repeated_point_counts_as_changed() -> None:
    """A point twice in the new scan, once in the old: one copy is matched, the other is a
    point the old scan did not have (its neighbours' lists differ), so it is changed."""
    from v2xlake.tasks.register.sparse import Predecessor

    old_pts = voxel_downsample(_street(4), 0.3)
    new_pts = np.concatenate([old_pts, old_pts[5:6]])
    pred = Predecessor.of(new_pts, old_pts, Surfaces.empty(len(old_pts)))
    assert pred.row[5] == 5 and pred.row[-1] == -1
    assert np.array_equal(pred.row[:-1], np.arange(len(old_pts)))
    assert len(pred.changed) == 1 and np.array_equal(pred.changed[0], old_pts[5])
