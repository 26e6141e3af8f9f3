"""Export benchmark (helper E): nuScenes export vs the devkit loading it, and .pcd.bin writing
against a plain NumPy ``tofile`` floor.

    python tests/bench/bench_export.py [--seconds 5] [--points 40000]

Builds a synthetic clean clip (tests/export_fixtures.py: two agents, 10 Hz LiDAR, 30 Hz
camera), then times:
* export_nuscenes end to end, and nuscenes-devkit ``NuScenes(...)`` on the same export;
* the .pcd.bin path (column_stack x,y,z,intensity,ring -> float32 -> tofile) in points/s vs
  ``tofile`` of an already packed (N, 5) float32 array (the floor: pure disk write);
* reading the deskewed points back from the lake frame by frame (iter_point_frames).
Prints ratios. Not run by pytest.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

from tests.export_fixtures import build_clean_clip  # noqa: E402
from v2xlake.storage.lake import Lake  # noqa: E402
from v2xlake.storage.reader import iter_point_frames  # noqa: E402
from v2xlake.tasks.export.nuscenes import (  # noqa: E402
    NuScenesExportConfig,
    export_nuscenes,
    write_pcd_bin,
)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--points", type=int, default=40000, help="ground points per scan")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--lake", help="an existing lake (clean zone deskewed) instead of synthetic")
    ap.add_argument("--clip", default="bench")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(tmp)
        if args.lake:
            lake = Lake(args.lake)
            print(f"lake {args.lake}, clip {args.clip}")
        else:
            lake = Lake(base / "lake")
            t = time.perf_counter()
            build_clean_clip(lake, args.clip, seconds=args.seconds, n_ground=args.points)
            print(f"synthetic clip: {time.perf_counter() - t:.1f} s to build")
        agents = sorted(set(lake.read_table("clean", "agents", clip_id=args.clip)["agent_id"]
                            .to_pylist()))

        # ---- reading points from the lake
        t = time.perf_counter()
        frames = [f for a in agents for f in iter_point_frames(lake, args.clip, a)]
        t_read = time.perf_counter() - t
        n_pts = sum(len(f.xyz) for f in frames)
        print(f"lake read (deskewed, per frame): {n_pts / t_read / 1e6:.1f} M points/s "
              f"({n_pts} points, {len(frames)} frames)")

        # ---- .pcd.bin vs tofile floor
        out = base / "pcd"
        out.mkdir()
        best_ours, best_floor = np.inf, np.inf
        packed = [np.column_stack([f.xyz, f.intensity, f.ring.astype(np.float32)])
                  .astype(np.float32) for f in frames]
        for _ in range(args.repeat):
            t = time.perf_counter()
            for i, f in enumerate(frames):
                write_pcd_bin(out / f"{i}.pcd.bin", f.xyz, f.intensity, f.ring)
            best_ours = min(best_ours, time.perf_counter() - t)
            t = time.perf_counter()
            for i, p in enumerate(packed):
                p.tofile(out / f"floor{i}.bin")
            best_floor = min(best_floor, time.perf_counter() - t)
        print(f".pcd.bin writer: {n_pts / best_ours / 1e6:.1f} M points/s; numpy tofile "
              f"floor {n_pts / best_floor / 1e6:.1f} M points/s; ratio ours/floor "
              f"{best_floor / best_ours:.2f}")

        # ---- nuScenes export and devkit load
        t = time.perf_counter()
        rep = export_nuscenes(lake, [args.clip], base / "nus",
                              NuScenesExportConfig(write_lake_tables=not args.lake))
        t_export = time.perf_counter() - t
        from nuscenes.nuscenes import NuScenes

        t = time.perf_counter()
        nusc = NuScenes("v1.0-trainval", str(base / "nus"), verbose=False)
        t_load = time.perf_counter() - t
        print(f"export_nuscenes: {t_export:.2f} s ({int(rep.metrics['sample_data'])} "
              f"sample_data, {int(rep.metrics['sample_annotations'])} annotations, "
              f"{n_pts / t_export / 1e6:.2f} M points/s end to end)")
        print(f"nuscenes-devkit NuScenes() load: {t_load:.2f} s "
              f"({len(nusc.sample)} samples); ratio export/load {t_export / t_load:.1f}")


if __name__ == "__main__":
    main()
