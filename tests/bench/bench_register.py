"""Registration speed and accuracy of both GICP backends on the same frame pairs, one core.

    python tests/bench/bench_register.py [--frames 10] [--voxel 0.3] [--beams 128 --cols 2048]

Ray-cast synthetic street (tests/test_register.py), two agents 10-20 m apart, straight and
turning, eq. 1a initial estimate off by ~0.15 m / 0.5 deg (INS-like bias + jitter). Per
pair: preparing both clouds (downsample, covariances, tree), GICP, quality evaluation,
end to end; the "reference" rows are the one-call APIs a user would reach for first
(small_gicp.align on NumPy arrays; Open3D voxel + GICP with covariances computed inside),
at our target voxel and at a common 0.25 m.
The process is pinned to one CPU (Open3D ignores OMP_NUM_THREADS).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np

from tests.test_register import drive
from v2xlake.tasks.register.backends import GicpParams, make_backend
from v2xlake.tasks.register.core import QualityLimits, refine, transform_delta


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--beams", type=int, default=128)
    ap.add_argument("--cols", type=int, default=2048)
    ap.add_argument("--voxel", type=float, default=GicpParams().voxel_m)
    ap.add_argument("--source-voxel", type=float, default=GicpParams().source_voxel_m)
    args = ap.parse_args()
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})
    t = time.perf_counter()
    cases = [c for sc in ("straight", "turning")
             for c in drive(sc, args.frames, beams=args.beams, cols=args.cols)]
    n_pts = np.mean([len(c.ref) for c in cases] + [len(c.other) for c in cases])
    print(f"{len(cases)} pairs, {n_pts:.0f} points per scan on average "
          f"(ray casting took {time.perf_counter() - t:.1f} s), voxel {args.voxel} m, one core")
    params = GicpParams(voxel_m=args.voxel, source_voxel_m=args.source_voxel)
    rows: list[tuple[Any, ...]] = []
    for name in ("small_gicp", "open3d"):
        be = make_backend(name, params)  # type: ignore[arg-type,unused-ignore]
        prep, reg, tot, errs, init_errs, acc = [], [], [], [], [], 0
        warm = None
        for c in cases:
            t0 = time.perf_counter()
            a, b = be.prepare(c.ref), be.prepare(c.other, as_target=False)
            t1 = time.perf_counter()
            res = refine(be, a, b, c.T_init, QualityLimits(), warm)
            t2 = time.perf_counter()
            warm = res.correction if res.accepted else None
            prep.append(t1 - t0)
            reg.append(t2 - t1)
            tot.append(t2 - t0)
            errs.append(transform_delta(c.T_true, res.T_final))
            init_errs.append(transform_delta(c.T_true, c.T_init))
            acc += res.accepted
        e, ie = np.array(errs), np.array(init_errs)
        rows.append((f"ours/{name}", np.median(prep), np.median(reg), np.median(tot),
                     e[:, 0].mean() * 100, e[:, 0].max() * 100, e[:, 1].mean(), e[:, 1].max(), acc))
        print(f"  {name}: initial error mean {ie[:, 0].mean() * 100:.1f} cm / "
              f"{ie[:, 1].mean():.2f} deg; accepted {acc}/{len(cases)}")
    # the one-call reference APIs, end to end, at our voxel and at a common 0.25 m
    import open3d as o3d
    import small_gicp

    o3reg = o3d.pipelines.registration
    for vox in (args.voxel, 0.25):
        tm, errs = [], []
        for c in cases:
            t0 = time.perf_counter()
            r = small_gicp.align(c.ref.astype(np.float64), c.other.astype(np.float64), c.T_init,
                                 registration_type="GICP", downsampling_resolution=vox,
                                 max_correspondence_distance=1.0, num_threads=1)
            tm.append(time.perf_counter() - t0)
            errs.append(transform_delta(c.T_true, r.T_target_source))
        e = np.array(errs)
        rows.append((f"small_gicp.align v={vox}", np.nan, np.nan, np.median(tm),
                     e[:, 0].mean() * 100, e[:, 0].max() * 100, e[:, 1].mean(), e[:, 1].max(),
                     len(cases)))
        tm, errs = [], []
        for c in cases:
            t0 = time.perf_counter()
            s = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(c.other.astype(np.float64)))
            d = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(c.ref.astype(np.float64)))
            s, d = s.voxel_down_sample(vox), d.voxel_down_sample(vox)
            r3 = o3reg.registration_generalized_icp(s, d, 1.0, c.T_init)
            tm.append(time.perf_counter() - t0)
            errs.append(transform_delta(c.T_true, np.asarray(r3.transformation)))
        e = np.array(errs)
        rows.append((f"open3d GICP v={vox}", np.nan, np.nan, np.median(tm),
                     e[:, 0].mean() * 100, e[:, 0].max() * 100, e[:, 1].mean(), e[:, 1].max(),
                     len(cases)))
    ref_tot = rows[0][3]
    print(f"\n{'method':26s} {'prep s':>7s} {'reg s':>7s} {'pair s':>7s} {'x ours':>7s} "
          f"{'cm mean':>8s} {'cm max':>7s} {'deg mean':>9s} {'deg max':>8s}")
    for name, p, r_, t_, cm, cmx, dg, dgx, _ in rows:
        print(f"{name:26s} {p:7.3f} {r_:7.3f} {t_:7.3f} {t_ / ref_tot:7.2f} {cm:8.2f} {cmx:7.2f} "
              f"{dg:9.4f} {dgx:8.4f}")


if __name__ == "__main__":
    main()
