"""Ingest throughput against its floor: rosbags merely reading and deserializing the bag.

Builds a CATS-scale LiDAR bag (128 beams x 1,800 columns = 230,400 points per scan, 10 Hz,
fields x y z intensity ring return_type timestamp(f64 absolute s), 32 bytes per point) with
NumPy and rosbags' writers, for ROS 2 sqlite3 and MCAP and for ROS 1, then times:

- floor: ``AnyReader`` iterating every message and ``deserialize``-ing it (nothing else);
- read + parse + decode: what ingest's reading thread does (payloads read in place from the
  bag, the PointCloud2 wire format parsed, points decoded to columns), nothing else;
- ingest: ``run_ingest`` (parse the PointCloud2 wire format, decode to columns in one
  compiled pass, drop NaN, time to int64 ns, one Parquet row group per frame with the raw
  zone's encoding on a second thread, checksum + write of every output on a third, raw-zone
  tables, staging + publish), without and with the landing copy of the bag (a hard link
  when the lake is on the bag's filesystem);
- stage key: checksums of the clip's input files, which the flow takes before deciding
  whether ingest must run at all (first call; later calls are remembered per size + mtime);
- manifest: ``v2xlake.storage.manifest.record`` (the checksums come from the ingest report).

Each figure is the median of ``--repeat`` runs, floor and ingest interleaved so both see the
same neighbours. Prints bag MB/s and the ratio ingest / floor (target: <= 2x) in wall time and
in CPU time (user + system, all threads of the process): on a shared, busy machine wall time
mostly says how much CPU the neighbours left us, the CPU ratio says what ingest costs. Two
clip lengths, because the floor's fixed cost (opening the bag, ~25 ms) flatters short bags.

The camera case (``run_camera_case``, ROS 2 only) times raw 1080p frames of the real street
photo, where lossless PNG encoding, not reading, sets the pace.

    python tests/bench/bench_ingest.py [--frames 30 100] [--storage sqlite3 mcap ros1]
                                       [--camera-frames 60] [--repeat 5]
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

from rosbags.highlevel import AnyReader  # noqa: E402
from rosbags.rosbag1 import Writer as Writer1  # noqa: E402
from rosbags.rosbag2 import StoragePlugin, Writer  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

from v2xlake.schemas.stage import StageReport  # noqa: E402
from v2xlake.storage import manifest as mf  # noqa: E402
from v2xlake.storage.lake import Lake  # noqa: E402
from v2xlake.tasks.ingest import IngestConfig, clip_inputs, run_ingest  # noqa: E402

BEAMS, COLS = 128, 1800
T0 = 1_700_000_000 * 1_000_000_000


def store(storage: str) -> Any:
    """The standard types of a storage's ROS generation."""
    return get_typestore(Stores.ROS1_NOETIC if storage == "ros1" else Stores.ROS2_HUMBLE)


def bag_name(storage: str) -> str:
    return "red.bag" if storage == "ros1" else "red"


def make_bag(path: Path, frames: int, storage: str) -> int:
    """The LiDAR bag at ``path`` (a ROS 2 folder, or a ROS 1 ``.bag`` file)."""
    ts = store(storage)
    T = ts.types
    ros1 = storage == "ros1"
    dt = np.dtype({"names": ["x", "y", "z", "intensity", "ring", "return_type", "timestamp"],
                   "formats": ["<f4", "<f4", "<f4", "<f4", "<u2", "u1", "<f8"],
                   "offsets": [0, 4, 8, 12, 16, 18, 24], "itemsize": 32})
    fields = [T["sensor_msgs/msg/PointField"](name=n, offset=o, datatype=c, count=1)
              for n, o, c in (("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 12, 7),
                              ("ring", 16, 4), ("return_type", 18, 2), ("timestamp", 24, 8))]
    rng = np.random.default_rng(0)
    az = np.repeat(np.linspace(0, 2 * np.pi, COLS, endpoint=False)[:, None], BEAMS, 1).ravel()
    el = np.tile(np.deg2rad(np.linspace(-22.5, 22.5, BEAMS)), COLS)
    col = np.repeat(np.arange(COLS), BEAMS)
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    total = 0
    with Writer1(path) if ros1 else Writer(path, version=8, storage_plugin=plugin) as w:
        conn = w.add_connection("/lidar/points", "sensor_msgs/msg/PointCloud2", typestore=ts)
        for i in range(frames):
            start = T0 + i * 100_000_000
            # a street: ground at -1.8 m, walls at +-8 m, sky = no return (NaN)
            down = np.sin(el) < -1e-3
            r_ground = np.where(down, -1.8 / np.minimum(np.sin(el), -1e-3), np.inf)
            r_wall = 8.0 / np.maximum(np.abs(np.sin(az)) * np.cos(el), 1e-3)
            r = np.minimum(np.minimum(r_ground, r_wall), 120.0) + rng.normal(0, 0.02, az.size)
            a = np.zeros(az.size, dt)
            a["x"] = r * np.cos(el) * np.cos(az)
            a["y"] = r * np.cos(el) * np.sin(az)
            a["z"] = r * np.sin(el)
            a["x"][r >= 119.0] = np.nan
            a["intensity"] = rng.gamma(2.0, 20.0, az.size)
            a["ring"] = np.tile(np.arange(BEAMS), COLS)
            a["return_type"] = 1
            a["timestamp"] = (start + col * (100_000_000 // COLS)) / 1e9
            stamp = T["builtin_interfaces/msg/Time"](sec=start // 10**9, nanosec=start % 10**9)
            header = (T["std_msgs/msg/Header"](seq=i, stamp=stamp, frame_id="lidar") if ros1
                      else T["std_msgs/msg/Header"](stamp=stamp, frame_id="lidar"))
            msg = T["sensor_msgs/msg/PointCloud2"](
                header=header, height=1, width=az.size, fields=fields, is_bigendian=False,
                point_step=32, row_step=32 * az.size, data=a.view(np.uint8), is_dense=False)
            raw = (ts.serialize_ros1 if ros1 else ts.serialize_cdr)(
                msg, "sensor_msgs/msg/PointCloud2")
            total += len(raw)
            w.write(conn, start + 99_000_000, raw)
    return total


STREET = REPO.parent / "shared" / "data" / "real" / "images" / "street_plate_small_pjlab_0.png"
CAM_W, CAM_H = 1920, 1080


def street_frame(i: int) -> np.ndarray:
    """Camera frame ``i``: the real street photo at 1080p, shifted by 3 px per frame so that
    no two frames are equal."""
    import cv2

    img = cv2.imread(str(STREET), cv2.IMREAD_COLOR)
    assert img is not None, STREET
    return np.roll(cv2.resize(img, (CAM_W, CAM_H)), 3 * i, axis=1)


def make_camera_bag(path: Path, frames: int, storage: str) -> int:
    """A 30 Hz camera of raw 1080p ``bgr8`` Image messages (``street_frame``)."""
    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    total = 0
    with Writer(path, version=8, storage_plugin=plugin) as w:
        conn = w.add_connection("/cam/image", "sensor_msgs/msg/Image", typestore=ts)
        for i in range(frames):
            t = T0 + i * 33_333_333
            img = street_frame(i)
            msg = T["sensor_msgs/msg/Image"](
                header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](
                    sec=t // 10**9, nanosec=t % 10**9), frame_id="cam"),
                height=CAM_H, width=CAM_W, encoding="bgr8", is_bigendian=0, step=3 * CAM_W,
                data=np.ascontiguousarray(img).reshape(-1))
            raw = ts.serialize_cdr(msg, "sensor_msgs/msg/Image")
            total += len(raw)
            w.write(conn, t, raw)
    return total


CAMERA_SENSOR = {
    "name": "CAM_FRONT", "modality": "camera", "topic": "/cam/image",
    "msg_type": "sensor_msgs/msg/Image", "rate_hz": 30,
    "extrinsic": {"translation": [1.5, 0, 1.5], "rotation": [0.5, -0.5, 0.5, -0.5]},
    "intrinsics": {"width": CAM_W, "height": CAM_H, "fx": 1000.0, "fy": 1000.0,
                   "cx": CAM_W / 2, "cy": CAM_H / 2}}


def clip_yaml(d: Path, bag: str, camera: bool = False) -> None:
    (d / "clip.yaml").write_text(yaml.safe_dump({
        "clip_id": "bench", "location": "bench", "road_type": "local", "weather": "clear",
        "lighting": "day", "agents": [{
            "agent_id": "red", "kind": "vehicle", "role": "reference", "bag": bag,
            "tf_static_topic": None, "sensors": [CAMERA_SENSOR] if camera else [{
                "name": "LIDAR_TOP", "modality": "lidar", "topic": "/lidar/points",
                "msg_type": "sensor_msgs/msg/PointCloud2", "rate_hz": 10,
                "extrinsic": {"translation": [0, 0, 1.8], "rotation": [1, 0, 0, 0]},
                "fields": {"return_id": "return_type", "time": {
                    "field": "timestamp", "unit": "s", "reference": "absolute"}}}]}]}))


def cpu_s() -> float:
    """CPU seconds of this process so far, every thread (user + system)."""
    ru = resource.getrusage(resource.RUSAGE_SELF)
    return ru.ru_utime + ru.ru_stime


def settled() -> float:
    """Start a measurement with no dirty pages left by the previous one: otherwise the kernel
    writes the last run's output back to disk during this one, on the same two cores, and
    whichever measurement comes later pays for it. Returns the start time."""
    os.sync()
    return time.perf_counter()


def floor(bag: Path, storage: str) -> tuple[float, float]:
    ts = store(storage)
    t0, c0 = settled(), cpu_s()
    with AnyReader([bag], default_typestore=ts) as r:
        for c, _t, raw in r.messages():
            r.deserialize(raw, c.msgtype)
    return time.perf_counter() - t0, cpu_s() - c0


def decode_only(bag: Path, storage: str) -> tuple[float, float]:
    """Reading plus ingest's parse + decode_cloud (columns, NaN drop, int64 ns time): no
    Parquet, no I/O."""
    from v2xlake.schemas.clip import LidarFields, PointTimeField, TimeReference, TimeUnit
    from v2xlake.tasks.ingest.bagopen import header_stamp_ns
    from v2xlake.tasks.ingest.payloads import messages
    from v2xlake.tasks.ingest.pointcloud import decode_cloud
    from v2xlake.tasks.ingest.rawmsg import parser_for

    lf = LidarFields(return_id="return_type", time=PointTimeField(
        field="timestamp", unit=TimeUnit.S, reference=TimeReference.ABSOLUTE))
    t0, c0 = settled(), cpu_s()
    with AnyReader([bag], default_typestore=store(storage)) as r:
        for c, _t, raw in messages(r, r.connections):
            fast = parser_for(r.typestore.fielddefs, c.msgtype, bool(r.is2))
            m: Any = fast(raw) if fast else None
            m = m or r.deserialize(bytes(raw), c.msgtype)
            decode_cloud(m, lf, header_stamp_ns(m))
    return time.perf_counter() - t0, cpu_s() - c0


def print_ratios(runs: dict[str, list[tuple[float, float]]], rows: list[tuple[str, str]],
                 rate: str, amount: float) -> None:
    """One line per ``(label, key)`` of ``runs``: median wall and CPU time, ``amount`` per
    second (column ``rate``) and both ratios to the floor (``runs["floor"]``)."""
    f, f_cpu = median(runs["floor"])
    print(f"  {'':34s} {'wall s':>7s} {rate:>6s} {'ratio':>6s} {'CPU s':>6s} {'ratio':>6s}")
    for name, key in rows:
        w, c = median(runs[key])
        print(f"  {name:34s} {w:7.2f} {amount / w:6.0f} {w / f:5.2f}x {c:6.2f} {c / f_cpu:5.2f}x")


def median(runs: list[tuple[float, float]]) -> tuple[float, float]:
    """Median wall time and median CPU time (each on its own)."""
    return statistics.median(r[0] for r in runs), statistics.median(r[1] for r in runs)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, nargs="*", default=[30, 100],
                    help="LiDAR bags of N scans (none: cameras only)")
    ap.add_argument("--storage", nargs="+", default=["sqlite3", "mcap", "ros1"])
    ap.add_argument("--camera-frames", type=int, nargs="*", default=[60],
                    help="raw 1080p camera bags of N frames (none: LiDAR only)")
    ap.add_argument("--repeat", type=int, default=5, help="median of N (noisy machines)")
    args = ap.parse_args()
    for frames in args.frames:
        for storage in args.storage:
            with tempfile.TemporaryDirectory() as tmp:
                run_case(Path(tmp), frames, storage, args.repeat)
    for frames in args.camera_frames:
        for storage in (s for s in args.storage if s != "ros1"):
            with tempfile.TemporaryDirectory() as tmp:
                run_camera_case(Path(tmp), frames, storage, args.repeat)


def run_camera_case(tmp: Path, frames: int, storage: str, repeat: int) -> None:
    """Camera ingest is PNG encoding (lossless blobs are the contract): floor against ingest,
    and PNG encoding of the same frames on one thread, with libpng's defaults (what ingest
    did before ``tasks.pngcodec``) and with ``tasks.pngcodec`` (the cost one thread could not
    go below; ingest encodes on every core)."""
    import cv2

    from v2xlake.tasks.pngcodec import encode_png

    d = tmp / "clip"
    d.mkdir()
    mb = make_camera_bag(d / "red", frames, storage) / 1e6
    clip_yaml(d, "red", camera=True)
    imgs = [street_frame(i) for i in range(frames)]

    def ingest() -> tuple[float, float]:
        lake = Lake(tmp / f"lake-{time.time_ns()}")
        t0, c0 = settled(), cpu_s()
        run_ingest(lake, d, IngestConfig(copy_to_landing=False))
        out = time.perf_counter() - t0, cpu_s() - c0
        shutil.rmtree(lake.base, ignore_errors=True)
        return out

    level = IngestConfig().png_compression

    def png_serial(ours: bool) -> tuple[float, float]:
        t0, c0 = settled(), cpu_s()
        for img in imgs:
            if ours:
                encode_png(img, level)
            else:
                cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, level])
        return time.perf_counter() - t0, cpu_s() - c0

    ingest()  # warm-up
    runs: dict[str, list[tuple[float, float]]] = {"floor": [], "libpng": [], "png": [], "ing": []}
    for _ in range(repeat):
        runs["floor"].append(floor(d / "red", storage))
        runs["libpng"].append(png_serial(False))
        runs["png"].append(png_serial(True))
        runs["ing"].append(ingest())
    print(f"[{storage}, camera] {frames} raw {CAM_W}x{CAM_H} bgr8 frames, bag {mb:.0f} MB")
    print_ratios(runs, [("floor (rosbags read+deserialize)", "floor"),
                        ("PNG, libpng defaults, one thread", "libpng"),
                        ("PNG, tasks.pngcodec, one thread", "png"),
                        ("run_ingest (no landing copy)", "ing")], "fps", frames)


def run_case(tmp: Path, frames: int, storage: str, repeat: int) -> None:
    d = tmp / "clip"
    d.mkdir()
    bag = d / bag_name(storage)
    size = make_bag(bag, frames, storage)
    clip_yaml(d, bag.name)
    mb = size / 1e6
    runs: dict[str, list[tuple[float, float]]] = {k: [] for k in ("floor", "dec", "ing", "land")}
    reports: list[StageReport] = []
    manifest_s: list[float] = []

    def ingest(landing: bool) -> tuple[float, float]:
        lake = Lake(tmp / f"lake-{time.time_ns()}")
        t0, c0 = settled(), cpu_s()
        rep = run_ingest(lake, d, IngestConfig(copy_to_landing=landing))
        out = time.perf_counter() - t0, cpu_s() - c0
        t1 = time.perf_counter()
        mf.record(lake, rep, mf.stage_key(lake, "bench", "ingest", IngestConfig()))
        manifest_s.append(time.perf_counter() - t1)
        reports.append(rep)
        shutil.rmtree(lake.base, ignore_errors=True)
        return out

    t_key = time.perf_counter()
    mf.stage_key(Lake(tmp / "keys"), "bench", "ingest", IngestConfig(),
                 input_files=clip_inputs(d)[1])
    key_s = time.perf_counter() - t_key
    decode_only(bag, storage)  # warm-up: load (or compile) the numba kernel, fill the page cache
    ingest(False)
    reports.clear()
    manifest_s.clear()
    for _ in range(repeat):
        runs["floor"].append(floor(bag, storage))
        runs["dec"].append(decode_only(bag, storage))
        runs["ing"].append(ingest(False))
        runs["land"].append(ingest(True))
    lake = Lake(tmp / "last")
    run_ingest(lake, d, IngestConfig(copy_to_landing=False))
    pts = reports[0].metrics["lidar_points"]
    out = next(Path(lake.base).glob("raw/lidar_points/**/*.parquet"))
    out_mb = out.stat().st_size / 1e6
    print(f"[{storage}, {frames} frames] {frames} scans x {BEAMS * COLS} points = "
          f"{pts / 1e6:.1f} M finite points, bag {mb:.0f} MB -> lidar_points {out_mb:.0f} MB "
          f"({out_mb * 1e6 / pts:.1f} B/point)")
    print_ratios(runs, [("floor (rosbags read+deserialize)", "floor"),
                        ("read + parse + decode to columns", "dec"),
                        ("run_ingest (no landing copy)", "ing"),
                        ("run_ingest (with landing copy)", "land")], "MB/s", mb)
    ing = median(runs["ing"])[0]
    print(f"  + stage key (input checksums, first call) {key_s:.3f} s; manifest record "
          f"{statistics.median(manifest_s):.3f} s; {pts / ing / 1e6:.1f} M points/s")


if __name__ == "__main__":
    main()
