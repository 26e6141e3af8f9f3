"""The sparse GICP's faster forms of NumPy expressions (issue #21 item 5, speed only) must
give the bits of the expressions they replace: the registrations are compared byte for
byte before and after such changes."""

from __future__ import annotations

import numpy as np

from v2xlake.tasks.geometry import so3_exp
from v2xlake.tasks.register.sparse import _moved, _shift_rows, _so3_exp1, _unknown


def _rigid(rng: np.random.Generator) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    T[:3, 3] = rng.normal(size=3) * 50.0
    return T


def test_moved_and_shifted_rows_are_numpys_bits() -> None:
    rng = np.random.default_rng(0)
    for n in (0, 1, 2, 7, 1000, 12000):
        p = rng.normal(size=(n, 3)) * 40.0
        T = _rigid(rng)
        assert _moved(T, p).tobytes() == (p @ T[:3, :3].T + T[:3, 3]).tobytes()
        assert _shift_rows(p, T[:3, 3], -1.0).tobytes() == (p - T[:3, 3]).tobytes()
        p32 = p.astype(np.float32)
        assert _shift_rows(p32, T[:3, 3], 1.0).tobytes() == (p32 + T[:3, 3]).tobytes()


def test_unknown_rows_are_the_sorted_unique_unknown_ones() -> None:
    rng = np.random.default_rng(1)
    known = rng.random(5000) < 0.6
    for m in (0, 1, 50, 4000, 20000):
        rows = rng.integers(0, len(known), m)
        want = np.flatnonzero(np.isin(np.arange(len(known)), rows[~known[rows]]))
        got = _unknown(rows, known)
        assert got.dtype == np.int64 and np.array_equal(got, want)


def test_so3_exp1_is_so3_exps_bits() -> None:
    rng = np.random.default_rng(2)
    ws = [rng.normal(size=3) * 10.0 ** rng.uniform(-12, 0.5) for _ in range(3000)]
    ws += [np.zeros(3), np.array([1e-8, 0.0, 0.0]), np.array([0.0, 2e-8, 0.0]),
           np.array([np.nan, 0.0, 0.0]), np.array([np.inf, 1.0, 0.0])]
    with np.errstate(all="ignore"):
        for w in ws:
            assert _so3_exp1(w).tobytes() == so3_exp(w).tobytes()
