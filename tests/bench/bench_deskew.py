"""Deskew speed and accuracy against the reference ways of doing it, in one run.

    NUMBA_NUM_THREADS=1 python tests/bench/bench_deskew.py [--points-dual] [--repeat 7]

One 128-beam x 1800-column dual-return sweep (460,800 points, 20 m/s, turning, wobbling)
from the analytic generator of tests/test_deskew.py; every method is timed on the same
arrays (best of N) and its output compared with the analytic truth in the scan-start frame:
  scipy   per-point SciPy Slerp (eq. 3 written the obvious way; the exactness reference)
  numpy   NumPy, one interpolated pose per unique timestamp, gathered per point
  kiss    kiss-icp Preprocessor.preprocess (constant velocity over the sweep, time rescaled
          to [0, 1], output in the scan-END frame; given the TRUE start->end motion, its
          output is moved to the start frame before comparing)
  copy    copying the input arrays (memory floor)
  ours    tasks.deskew.deskew_points (numba, one transform per run of equal times)
  ours-shuffled   ours on the same points in random order (worst case for the run cache)
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np

from tests.test_deskew import (
    Motion,
    ins_track,
    lidar_extrinsic,
    make_sweep,
    scipy_reference,
    true_lidar_matrices,
)
from v2xlake.tasks.geometry import transform as pose_matrices
from v2xlake.tasks.interpolate import PoseTrack, interpolate_poses
from v2xlake.tasks.motion import deskew_points


def numpy_gather(xyz: np.ndarray, t_ns: np.ndarray, track: PoseTrack, e: np.ndarray,
                 t_ref: int) -> np.ndarray:
    uniq, inv = np.unique(t_ns, return_inverse=True)
    p, q = interpolate_poses(track.t_ns, track.xyz, track.quat_wxyz, np.append(uniq, t_ref))
    m = pose_matrices(p, q) @ e
    rel = np.linalg.inv(m[-1]) @ m[:-1]
    r = rel[inv]
    return np.einsum("nij,nj->ni", r[:, :3, :3], xyz.astype(np.float64)) + r[:, :3, 3]


def best_of(fn: Callable[[], object], repeat: int) -> tuple[float, object]:
    out = fn()
    best = float("inf")
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def err_mm(a: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    d = np.linalg.norm(np.asarray(a, np.float64) - truth, axis=1) * 1e3
    return float(np.sqrt(np.mean(d**2))), float(d.max())


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--lasers", type=int, default=128)
    ap.add_argument("--cols", type=int, default=1800)
    args = ap.parse_args()
    m, e = Motion(yaw_rate=0.6), lidar_extrinsic()
    sw = make_sweep(m, e, n_cols=args.cols, n_lasers=args.lasers, dual=True)
    track = ins_track(m)
    n = len(sw.t_ns)
    t_end = int(sw.t_ns.max())
    print(f"{n} points, {len(np.unique(sw.t_ns))} unique times, "
          f"NUMBA_NUM_THREADS={os.environ['NUMBA_NUM_THREADS']}")
    rows: list[tuple[str, float, float | None, float | None]] = []

    def record(name: str, secs: float, out: np.ndarray | None, truth: np.ndarray | None) -> None:
        rms, mx = err_mm(out, truth) if out is not None and truth is not None else (None, None)
        rows.append((name, secs, rms, mx))

    raw_rms, raw_max = err_mm(sw.raw, sw.truth)
    print(f"raw skew (no compensation): RMS {raw_rms:.1f} mm, max {raw_max:.1f} mm")

    s, out = best_of(lambda: scipy_reference(sw.raw, sw.t_ns, track, e, sw.t0_ns),
                     max(1, args.repeat // 3))
    ref = np.asarray(out)
    record("scipy per-point Slerp", s, ref, sw.truth)
    s, out = best_of(lambda: numpy_gather(sw.raw, sw.t_ns, track, e, sw.t0_ns), args.repeat)
    record("numpy gather (pose/unique t)", s, np.asarray(out), sw.truth)

    try:
        from kiss_icp.preprocess import Preprocessor

        pre = Preprocessor(max_range=1e4, min_range=0.0, deskew=True, max_num_threads=1)
        ends = true_lidar_matrices(np.array([sw.t0_ns, t_end]), m, e)
        motion = np.linalg.inv(ends[0]) @ ends[1]  # the TRUE start->end motion (best case)
        raw64, ts = sw.raw.astype(np.float64), sw.t_ns.astype(np.float64)
        s, out = best_of(lambda: pre.preprocess(raw64, ts, motion), args.repeat)
        k = np.asarray(out)
        if len(k) == n:
            k_t0 = k @ motion[:3, :3].T + motion[:3, 3]  # scan-end frame -> scan-start frame
            record("kiss-icp preprocess (const vel)", s, k_t0, sw.truth)
        else:
            record(f"kiss-icp preprocess (kept {len(k)}/{n})", s, None, None)
    except ImportError:
        print("kiss-icp not installed")

    s, _ = best_of(lambda: (sw.raw.copy(), sw.t_ns.copy()), args.repeat)
    record("copy (floor)", s, None, None)
    deskew_points(sw.raw, sw.t_ns, track, e, sw.t0_ns)  # compile / load cache
    s, res = best_of(lambda: deskew_points(sw.raw, sw.t_ns, track, e, sw.t0_ns), args.repeat)
    ours = res.xyz  # type: ignore[attr-defined]
    record("ours (numba, t_ref given)", s, ours, sw.truth)
    s, _ = best_of(lambda: deskew_points(sw.raw, sw.t_ns, track, e), args.repeat)
    record("ours (default t_ref = min t)", s, None, None)
    perm = np.random.default_rng(0).permutation(n)
    raw_p, t_p = sw.raw[perm], sw.t_ns[perm]
    s, res_p = best_of(lambda: deskew_points(raw_p, t_p, track, e, sw.t0_ns), args.repeat)
    record("ours, shuffled point order", s, res_p.xyz, sw.truth[perm])  # type: ignore[attr-defined]

    ours_s = next(r[1] for r in rows if r[0].startswith("ours (numba"))
    print(f"\n{'method':36s} {'M pts/s':>9s} {'ours x':>8s} {'RMS mm':>8s} {'max mm':>8s}")
    for name, secs, rms, mx in rows:
        mps = n / secs / 1e6
        e_rms = f"{rms:8.3f}" if rms is not None else f"{'-':>8s}"
        e_max = f"{mx:8.3f}" if mx is not None else f"{'-':>8s}"
        print(f"{name:36s} {mps:9.1f} {secs / ours_s:8.2f} {e_rms} {e_max}")
    d = np.linalg.norm(ours.astype(np.float64) - ref, axis=1) * 1e3
    print(f"\nours vs per-point SciPy reference: max {d.max():.4f} mm (target < 0.1 mm)")


if __name__ == "__main__":
    main()
