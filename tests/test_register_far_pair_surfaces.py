"""A far cross pair's surfaces (``gicp.far_pair_num_neighbors``, issue #21): its own settings
and a second surface store per scan, beside the near pairs' (cheap: no clip)."""

from __future__ import annotations

import numpy as np

from v2xlake.tasks.register.backends import SparseGicpBackend
from v2xlake.tasks.register.config import GicpSection


def test_far_pair_settings_only_change_the_neighbours() -> None:
    p = GicpSection()
    far = p.far_pair()
    assert far is not None and far.num_neighbors == 6 and far.far_pair() is None
    assert far.model_dump(exclude={"num_neighbors", "far_pair_num_neighbors"}) == \
        p.model_dump(exclude={"num_neighbors", "far_pair_num_neighbors"})
    assert GicpSection.model_validate({"far_pair_num_neighbors": None}).far_pair() is None
    assert GicpSection.model_validate({"far_pair_num_neighbors": 10,
                                       "num_neighbors": 10}).far_pair() is None


def test_own_surfaces_share_the_grid_not_the_surfaces() -> None:
    """The far store shares points, grid and sample; filling it (6 neighbours) leaves the
    near store (10) as it was, so a near pair computes what it would without a far pair."""
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(-20, 20, (4000, 2)), rng.normal(0, 0.02, 4000)]
    near = SparseGicpBackend(GicpSection())
    base = near.prepare_points(pts)
    far_p = GicpSection.model_validate({"far_pair_num_neighbors": 6}).far_pair()
    assert far_p is not None
    far = SparseGicpBackend(far_p)
    fb = far.own_surfaces(base)
    assert fb.points is base.points and fb.tree is base.tree and fb.sample is base.sample
    assert fb.handle is not base.handle
    rows = np.arange(0, 4000, 7)
    fb.handle.ensure(fb.points, fb.tree, rows, 6)
    assert not base.handle.known.any()
    base.handle.ensure(base.points, base.tree, rows, 10)
    alone = near.prepare_points(pts)
    alone.handle.ensure(alone.points, alone.tree, rows, 10)
    assert np.array_equal(base.handle.normals, alone.handle.normals)
    assert not np.array_equal(base.handle.ratio[rows], fb.handle.ratio[rows])
