"""The geometry vocabulary (tasks/geometry.py) against SciPy's ``Rotation``/``RigidTransform``.

    python tests/bench/bench_geometry.py [--repeat 7]

Why this exists: the issue asked to use SciPy's ``RigidTransform`` where it serves and is fast
enough. Every function of the vocabulary is timed (best of N) against the SciPy call a user
would otherwise write, at the sizes the pipeline uses: one transform (calibration, one box,
a frame's pose), a batch (a clip's poses or a frame's boxes) and a scan of points
(225k, one 128-beam sweep). Ratios > 1 mean SciPy is slower. Both sides are checked to give
the same numbers before anything is timed.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np
from scipy.spatial.transform import RigidTransform, Rotation

from v2xlake.tasks.geometry import (
    apply,
    compose,
    invert,
    matrix_to_quat,
    quat_to_matrix,
    rotation_angle,
    transform,
)


def best_of(fn: Callable[[], object], repeat: int) -> float:
    fn()
    best = float("inf")
    for _ in range(repeat):
        t = time.perf_counter()
        n = 0
        while True:  # at least 20 ms per sample so that microsecond calls are measurable
            fn()
            n += 1
            if time.perf_counter() - t > 0.02:
                break
        best = min(best, (time.perf_counter() - t) / n)
    return best


def batch(n: int, rng: np.random.Generator, repeat: int) -> None:
    """One transform and a 1000-batch: the vocabulary against SciPy, same numbers first."""
    t = rng.normal(size=(n, 3)) * 10
    q = Rotation.random(n, random_state=1).as_quat(scalar_first=True)
    T = transform(t, q)
    T2 = transform(rng.normal(size=(n, 3)), Rotation.random(n, random_state=2)
                   .as_quat(scalar_first=True))
    cases: list[tuple[str, Callable[[], np.ndarray], Callable[[], np.ndarray]]] = [
        ("transform(t, q) -> 4x4", lambda: transform(t, q),
         lambda: RigidTransform.from_components(
             t, Rotation.from_quat(q, scalar_first=True)).as_matrix()),
        ("invert", lambda: invert(T),
         lambda: RigidTransform.from_matrix(T).inv().as_matrix()),
        ("compose", lambda: compose(T, T2),
         lambda: (RigidTransform.from_matrix(T) * RigidTransform.from_matrix(T2))
         .as_matrix()),
        ("quat_to_matrix", lambda: quat_to_matrix(q),
         lambda: Rotation.from_quat(q, scalar_first=True).as_matrix()),
        ("matrix_to_quat", lambda: matrix_to_quat(T[:, :3, :3]),
         lambda: Rotation.from_matrix(T[:, :3, :3]).as_quat(scalar_first=True,
                                                            canonical=True)),
        ("np.linalg.inv (what it replaced)", lambda: invert(T), lambda: np.linalg.inv(T)),
        ("rotation_angle", lambda: rotation_angle(T),
         lambda: Rotation.from_matrix(T[:, :3, :3]).magnitude()),
    ]
    for name, ours, theirs in cases:
        a, b = ours(), theirs()
        if "matrix_to_quat" not in name:  # quaternion sign conventions differ
            np.testing.assert_allclose(a, b, atol=1e-9)
        to, ts = best_of(ours, repeat), best_of(theirs, repeat)
        print(f"{name:34s} {n:7d} {to * 1e6:8.1f}us {ts * 1e6:8.1f}us {ts / to:10.2f}")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=int, default=7)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    print(f"{'operation':34s} {'size':>7s} {'ours':>10s} {'scipy':>10s} {'scipy/ours':>10s}")
    for n in (1, 1000):
        batch(n, rng, args.repeat)
    xyz = rng.normal(size=(225_000, 3)).astype(np.float32) * 30
    T1 = transform(np.array([1.0, 2.0, 0.5]), Rotation.random(random_state=3)
                   .as_quat(scalar_first=True))
    rt = RigidTransform.from_matrix(T1)

    def column_loop() -> np.ndarray:  # what v2xlake/tasks/projection.transform_points did
        x = np.asarray(xyz, dtype=np.float64)
        out = np.empty((x.shape[0], 3))
        for i in range(3):
            out[:, i] = x[:, 0] * T1[i, 0] + x[:, 1] * T1[i, 1] + x[:, 2] * T1[i, 2] + T1[i, 3]
        return out

    pts: list[tuple[str, Callable[[], np.ndarray]]] = [
        ("RigidTransform.apply", lambda: rt.apply(xyz)),
        ("xyz @ R.T + t (BLAS)", lambda: xyz.astype(np.float64) @ T1[:3, :3].T + T1[:3, 3]),
        ("column loop (old align helper)", column_loop),
        ("einsum (old export helper)", lambda: np.einsum(
            "ij,nj->ni", T1[:3, :3], xyz.astype(np.float64)) + T1[:3, 3]),
    ]
    ref = apply(T1, xyz)
    to = best_of(lambda: apply(T1, xyz), args.repeat)
    for name, fn in pts:
        np.testing.assert_allclose(fn(), ref, atol=1e-9)
        ts = best_of(fn, args.repeat)
        print(f"apply vs {name:25s} {len(xyz):7d} {to * 1e3:8.2f}ms {ts * 1e3:8.2f}ms "
              f"{ts / to:10.2f}")


if __name__ == "__main__":
    main()
