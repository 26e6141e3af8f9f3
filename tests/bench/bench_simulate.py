"""Benchmark of the recorder simulator: ``python tests/bench/bench_simulate.py [--quick]``.

Times ``small`` 2 s (all seven cameras and the default two) and ``cats`` 1 s, and prints wall
and CPU time, LiDAR points per second of CPU, images, bag sizes. As a reference point it also
times the two floors the simulator cannot beat: writing the same number of PointCloud2 bytes
with rosbags alone, and PNG-encoding the same number of images of the same size.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from v2xlake.tasks.simulate import SimConfig, simulate
from v2xlake.tasks.simulate.bagwrite import POINT_DTYPE, BagSink


def _size(p: Path) -> int:
    return sum(f.stat().st_size for f in p.rglob("*") if f.is_file())


def run(name: str, cfg: SimConfig, tmp: Path) -> dict[str, float]:
    out = tmp / name
    w0, c0 = time.perf_counter(), time.process_time()
    simulate(out, cfg)
    wall, cpu = time.perf_counter() - w0, time.process_time() - c0
    st = json.loads((out / "truth" / "stats.json").read_text())
    bags = sum(_size(out / a) if (out / a).is_dir() else (out / f"{a}.bag").stat().st_size
               for a in cfg.agents)
    res = {"wall_s": wall, "cpu_s": cpu, "points": st["n_points"], "images": st["n_images"],
           "bag_mb": bags / 1e6, "clip_mb": _size(out) / 1e6,
           "points_per_cpu_s": st["n_points"] / cpu}
    print(f"{name:28s} wall {wall:7.1f} s  cpu {cpu:7.1f} s  points {st['n_points']:>9d} "
          f"({res['points_per_cpu_s'] / 1e3:7.0f} k/s cpu)  images {st['n_images']:4d}  "
          f"bags {res['bag_mb']:7.1f} MB  clip {res['clip_mb']:7.1f} MB")
    return res


def floor_rosbags(n_points: int, tmp: Path) -> float:
    """rosbags alone writing the same number of 32-byte points as PointCloud2 messages."""
    sink = BagSink(tmp / "floor_bag", "sqlite3")
    sink.topic("/p", "sensor_msgs/msg/PointCloud2")
    per = 230_000
    pts = np.zeros(per, POINT_DTYPE)
    t0 = time.perf_counter()
    for k in range(max(1, n_points // per)):
        sink.put("/p", k, sink.f.pointcloud2(k, "l", pts, "/p"))
        sink.flush()
    sink.close()
    return time.perf_counter() - t0


def floor_png(shape: tuple[int, int], n: int) -> float:
    img = np.zeros((*shape, 3), np.uint8)
    img[: shape[0] // 2] = (200, 150, 110)
    img[shape[0] // 2:] = (62, 62, 62)
    t0 = time.perf_counter()
    for _ in range(n):
        cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    return time.perf_counter() - t0


def geometry(tmp: Path) -> None:
    """Interpolation error of 8 ms INS samples + linear/SLERP, and the raw sweep gap, at 20 m/s."""
    from scipy.spatial.transform import Rotation, Slerp

    from v2xlake.tasks.simulate import load_truth

    cfg = SimConfig.preset("small", seconds=1, speed_mps=20.0, cameras=("CAM_FRONT",),
                           camera_hz=5, write_lidar_truth=False)
    truth = load_truth(simulate(tmp / "geom", cfg))
    for agent in cfg.agents:
        tk = truth.start_ns + 8_000_000 * np.arange(126)
        tq = truth.start_ns + np.arange(1, 10**9, 997_003)
        Tk, Tq = truth.T_world_lidar(agent, tk), truth.T_world_lidar(agent, tq)
        pos = np.column_stack([np.interp(tq, tk, Tk[:, i, 3]) for i in range(3)])
        rot = Slerp(tk.astype(float), Rotation.from_matrix(Tk[:, :3, :3]))(tq.astype(float))
        dp = np.linalg.norm(pos - Tq[:, :3, 3], axis=1)
        da = (rot.inv() * Rotation.from_matrix(Tq[:, :3, :3])).magnitude()
        t0 = truth.start_ns + 100_000_000 * np.arange(10)
        gap = np.linalg.norm(truth.T_world_lidar(agent, t0 + 99_944_444)[:, :3, 3]
                             - truth.T_world_lidar(agent, t0)[:, :3, 3], axis=1)
        print(f"{agent}: 8 ms INS + lerp/SLERP error: position max {dp.max() * 1e3:.4f} mm, "
              f"rotation max {np.degrees(da.max()) * 3600:.3f} arcsec "
              f"({da.max() * 50e3:.4f} mm at 50 m); sweep gap at 20 m/s {gap.mean():.3f} m")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="small preset only")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        run("small 2 s, 2 cameras", SimConfig.preset("small", seconds=2,
                                                      cameras=("CAM_FRONT", "CAM_BACK")), tmp)
        run("small 2 s, 7 cameras (default)", SimConfig.preset("small", seconds=2), tmp)
        geometry(tmp)
        if not a.quick:
            res = run("cats 1 s (Tab. 2 rig)", SimConfig.preset("cats", seconds=1), tmp)
            fb = floor_rosbags(res["points"], tmp)
            fp = floor_png((2160, 3840), 30)
            print(f"floor: rosbags sqlite3 write of the same points {fb:.1f} s "
                  f"(ratio sim/floor {res['wall_s'] / fb:.1f}); PNG encode of one flat 4K image "
                  f"{fp / 30 * 1e3:.0f} ms")


if __name__ == "__main__":
    main()
