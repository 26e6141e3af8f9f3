"""``python -m v2xlake.tasks.simulate OUT [--preset small|street|coop|cats] [--seconds S] ...``.

The same options as ``v2xlake simulate``; prints time, counts and size of the clip.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from v2xlake.tasks.simulate import SimConfig, simulate


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m v2xlake.tasks.simulate", description=__doc__)
    ap.add_argument("out", type=Path)
    ap.add_argument("--preset", default="small", choices=["small", "street", "coop", "cats"])
    ap.add_argument("--seconds", type=float)
    ap.add_argument("--storage", choices=["sqlite3", "mcap", "ros1"])
    ap.add_argument("--seed", type=int)
    ap.add_argument("--agents", help="comma list from red,black,rsu (red required)")
    ap.add_argument("--cameras", help="how many cameras (N) or a comma list of names")
    ap.add_argument("--camera-hz", type=float)
    ap.add_argument("--pose-format", choices=["inspva", "odometry", "navsat-imu", "tf"])
    ap.add_argument("--radar", action="store_true", help="a front 4D radar per vehicle")
    a = ap.parse_args(argv)
    cfg = SimConfig.preset(a.preset, seconds=a.seconds, storage=a.storage, seed=a.seed,
                           agents=a.agents, cameras=a.cameras, camera_hz=a.camera_hz,
                           pose_format=a.pose_format, radar=a.radar or None)
    t = time.perf_counter()
    out = simulate(a.out, cfg)
    stats = json.loads((out / "truth" / "stats.json").read_text())
    size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    print(f"wrote {out} in {time.perf_counter() - t:.1f} s: {stats['n_scans']} scans/agent, "
          f"{stats['n_points']} points, {stats['n_images']} images, "
          f"{stats['n_annotations']} boxes, {size / 1e6:.1f} MB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
