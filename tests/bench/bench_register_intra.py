"""Intra-agent LiDAR extrinsic refinement (issue #27): time per refinement and accuracy, on the
real lidar2lidar recordings (../shared/data/real/lidar2lidar, read in place), beside plain
small_gicp from the same start.

    python tests/bench/bench_register_intra.py [--perturbations 5] [--seed 0] [--plot P.png]

Rows:
- ``scene_000N left|right``: the published start (~45 deg / 10 cm off); time, correction,
  1-sigma, accepted; then the agreement of the two scenes' estimates (same rig).
- ``p64/qt``: the manual Pandar64 -> QT64 calibration perturbed by up to 20 cm / 5 deg
  (``--perturbations`` random ones, fixed seed): distance of each result to the manual
  calibration, spread between the results, and the same at default thresholds (refused when
  the data cannot vouch for it); then the point-to-plane residuals of the QT64 points on
  the Pandar64 surfaces under the manual calibration, the refinement's minimum and the file's
  non-rigid matrix as written (``--plot``: a picture of the same).
- ``plain``: ``small_gicp.align`` (GICP) on the same NumPy clouds from the same start, at a
  0.25 m voxel and as the same multi-scale cascade without the search: time, ratio, result.
The process is pinned to one CPU.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

from v2xlake.tasks.geometry import invert, so3_exp  # noqa: E402
from v2xlake.tasks.register.intra import (  # noqa: E402
    IntraConfig,
    combine,
    nearest_rigid,
    pose_distance,
    refine_extrinsic,
)
from v2xlake.tasks.register.intra_data import (  # noqa: E402
    read_initial_extrinsics,
    read_json_extrinsic,
    read_pcd_xyz,
)

L2L = REPO.parent / "shared" / "data" / "real" / "lidar2lidar"


def plain(primary: np.ndarray, secondary: np.ndarray, T0: np.ndarray,
          stages: tuple[tuple[float, float, float], ...]) -> tuple[np.ndarray, float, bool]:
    """small_gicp.align from ``T0`` through ``stages`` (voxel target, voxel source, max
    correspondence): (T, seconds, converged)."""
    import small_gicp

    t0 = time.perf_counter()
    T, conv = T0, False
    for vt, vs, corr in stages:
        r = small_gicp.align(primary, secondary, init_T_target_source=T,
                             registration_type="GICP", downsampling_resolution=vt,
                             max_correspondence_distance=corr, num_threads=1,
                             max_iterations=100)
        T, conv = np.asarray(r.T_target_source), bool(r.converged)
        del vs
    return T, time.perf_counter() - t0, conv


def perturb(T: np.ndarray, deg: float, m: float, rng: np.random.Generator) -> np.ndarray:
    a, b = rng.normal(size=3), rng.normal(size=3)
    P = np.eye(4)
    P[:3, :3] = so3_exp(np.radians(deg) * a / np.linalg.norm(a))
    P[:3, 3] = m * b / np.linalg.norm(b)
    return T @ P


def residuals(primary: np.ndarray, secondary: np.ndarray, Ts: dict[str, np.ndarray],
              plot: str | None) -> None:
    """Where the secondary's points land on the primary's surfaces under each transform:
    point-to-plane distance to the nearest planar primary neighbourhood (normal from 12
    neighbours) within 0.5 m -- the evidence of which extrinsic the data support -- and,
    with ``plot``, a top and a side view of both clouds under each."""
    from scipy.spatial import cKDTree

    tree = cKDTree(primary)
    _, nn = tree.query(primary, k=12)
    nb = primary[nn] - primary[nn].mean(axis=1, keepdims=True)
    w, v = np.linalg.eigh(np.einsum("nki,nkj->nij", nb, nb))
    normal, planar = v[:, :, 0], w[:, 0] < 0.2 * w[:, 1]
    print("  point-to-plane residuals of the QT64 points on the Pandar64 surfaces:")
    for name, T in Ts.items():
        X = secondary @ T[:3, :3].T + T[:3, 3]
        dist, i = tree.query(X)
        ok = (dist < 0.5) & planar[i]
        r = np.abs(np.einsum("ij,ij->i", X - primary[i], normal[i]))[ok]
        print(f"    {name:24s} matched {ok.mean():.2f}; median {np.median(r) * 100:.1f} cm, "
              f"within 3 cm {(r < 0.03).mean():.2f}, within 10 cm {(r < 0.1).mean():.2f}")
    if not plot:
        return
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(2, len(Ts), figsize=(7 * len(Ts), 12))
    for j, (name, T) in enumerate(Ts.items()):
        X = secondary @ T[:3, :3].T + T[:3, 3]
        for row, (a, b, lim) in enumerate(((0, 1, None), (0, 2, (-3.5, 3.0)))):
            sel_p = np.abs(primary[:, 1]) < 0.5 if row else np.abs(primary[:, 1]) < 14
            sel_s = np.abs(X[:, 1]) < 0.5 if row else np.abs(X[:, 1]) < 14
            axx = ax[row, j]
            axx.scatter(primary[sel_p, a], primary[sel_p, b], s=0.3, c="k", label="Pandar64")
            axx.scatter(X[sel_s, a], X[sel_s, b], s=0.3, c="r", label="QT64")
            axx.set_xlim(-6, 22)
            if lim:
                axx.set_ylim(*lim)
            else:
                axx.set_aspect("equal")
            axx.set_title(("side view |y| < 0.5 m, " if row else "top view, ") + name)
    ax[0, 0].legend(markerscale=10)
    fig.tight_layout()
    fig.savefig(plot, dpi=80)
    print(f"  picture: {plot}")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--perturbations", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--plot", default=None, help="PNG: the Pandar64/QT64 pair under the "
                    "manual calibration and the refinement's minimum")
    args = ap.parse_args()
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})
    if not L2L.exists():
        sys.exit(f"real data missing: {L2L}")
    cfg = IntraConfig()
    one = ((0.25, 0.25, 1.0),)
    fine = ((0.1, 0.1, 0.5),)  # the fine voxel alone: the wrong minimum of the issue
    cascade = cfg.fine_stages
    print(f"{'case':22s} {'method':10s} {'s':>6s} {'moved deg':>9s} {'moved cm':>8s} "
          f"{'1-sig deg':>9s} {'1-sig cm':>8s} {'acc':>4s} note")
    res: dict[tuple[str, str], object] = {}
    plains: dict[tuple[str, str, str], np.ndarray] = {}
    times: list[float] = []
    for scene in ("scene_0001", "scene_0002"):
        d = L2L / scene
        init = read_initial_extrinsics(d / "initial_extrinsic.txt")
        top = read_pcd_xyz(d / "top.pcd")
        for side, dev in (("left", 1), ("right", 2)):
            sec = read_pcd_xyz(d / f"{side}.pcd")
            r = refine_extrinsic(top, sec, init[dev], cfg)
            res[(scene, side)] = r
            times.append(r.seconds)
            deg, m = r.correction
            print(f"{scene + ' ' + side:22s} {'intra':10s} {r.seconds:6.2f} {deg:9.2f} "
                  f"{m * 100:8.1f} {r.std_deg:9.3f} {r.std_m * 100:8.2f} "
                  f"{'yes' if r.accepted else 'no':>4s} {r.reason[:70]}")
            for name, st in (("plain0.25", one), ("plain0.1", fine), ("plain-ms", cascade)):
                T, s, conv = plain(top, sec, init[dev], st)
                plains[(scene, side, name)] = T
                deg, m = pose_distance(init[dev], T)
                dr, dt = pose_distance(r.T, T)
                print(f"{'':22s} {name:10s} {s:6.2f} {deg:9.2f} {m * 100:8.1f} {'-':>9s} "
                      f"{'-':>8s} {'-':>4s} converged={conv}; {dr:.2f} deg / {dt * 100:.1f} cm "
                      f"from intra; time ratio intra/plain {r.seconds / max(s, 1e-9):.0f}x")
    print("\nagreement between the two scenes (same rig; issue: 2 cm / 0.4 deg)")
    for side in ("left", "right"):
        a, b = res[("scene_0001", side)], res[("scene_0002", side)]
        deg, m = pose_distance(a.T, b.T)  # type: ignore[attr-defined]
        pooled = combine([a, b])  # type: ignore[list-item]
        line = f"  {side:5s} intra {deg:.3f} deg / {m * 100:.2f} cm; "
        for name in ("plain0.25", "plain0.1", "plain-ms"):
            dp, mp = pose_distance(plains[("scene_0001", side, name)],
                                   plains[("scene_0002", side, name)])
            line += f"{name} {dp:.3f} deg / {mp * 100:.2f} cm; "
        print(line + f"pooled: {pooled.reason} (1-sigma {pooled.std_deg:.2f} deg / "
              f"{pooled.std_m * 100:.1f} cm, accepted={pooled.accepted})")

    d = L2L / "p64_qt_manual"
    p64, qt = read_pcd_xyz(d / "p64.pcd"), read_pcd_xyz(d / "qt.pcd")
    # T_p64_qt: the file maps Pandar64 points into the QT64 frame, with a 3x3 that is not a
    # rotation (a 1.1% scale): its nearest rigid transform, inverted
    T_qt_p64, scale_dev = nearest_rigid(read_json_extrinsic(d / "p64-to-qt-extrinsic.json"))
    manual = invert(T_qt_p64)
    rng = np.random.default_rng(args.seed)
    loose = IntraConfig(max_std_deg=2.0, max_std_m=0.3)
    print("\np64/qt: manual calibration perturbed by up to 20 cm / 5 deg (issue: recover "
          f"within 2 cm / 0.2 deg); the file's 3x3 is {scale_dev * 100:.2f}% off a rotation: "
          "its nearest rigid transform is the reference")
    Ts, Tp = [], []
    for _ in range(args.perturbations):
        start = perturb(manual, rng.uniform(1.0, 5.0), rng.uniform(0.05, 0.2), rng)
        r = refine_extrinsic(p64, qt, start, loose)
        strict = refine_extrinsic(p64, qt, start, cfg)
        times.append(r.seconds)
        T, s, conv = plain(p64, qt, start, cascade)
        Ts.append(r.T)
        Tp.append(T)
        d0, m0 = pose_distance(manual, start)
        dr, dm = pose_distance(manual, r.T)
        dp, mp = pose_distance(manual, T)
        print(f"  start {d0:4.1f} deg / {m0 * 100:4.1f} cm: intra {r.seconds:5.2f} s -> "
              f"{dr:.3f} deg / {dm * 100:.1f} cm from manual (1-sigma {r.std_deg:.2f} deg / "
              f"{r.std_m * 100:.1f} cm; default thresholds: "
              f"{'accepted' if strict.accepted else 'refused'}); plain-ms {s:5.2f} s -> "
              f"{dp:.3f} deg / {mp * 100:.1f} cm (converged={conv})")
    sp = max((pose_distance(a, b) for a in Ts for b in Ts), key=lambda x: x[0])
    spp = max((pose_distance(a, b) for a in Tp for b in Tp), key=lambda x: x[0])
    print(f"  spread between starts: intra {sp[0]:.3f} deg / {sp[1] * 100:.2f} cm; plain-ms "
          f"{spp[0]:.3f} deg / {spp[1] * 100:.2f} cm")
    residuals(p64, qt, {"manual (rigid)": manual, "intra minimum": Ts[0],
                        "file matrix as written": np.linalg.inv(
                            read_json_extrinsic(d / "p64-to-qt-extrinsic.json"))}, args.plot)
    for deg in (150.0, 90.0):
        r = refine_extrinsic(p64, qt, perturb(manual, deg, 0.2, rng), cfg)
        print(f"  start {deg:.0f} deg off: {'accepted' if r.accepted else 'refused'}: "
              f"{r.reason}")
    print(f"\ntime per refinement (one core): median {np.median(times):.2f} s, "
          f"max {np.max(times):.2f} s over {len(times)}")


if __name__ == "__main__":
    main()
