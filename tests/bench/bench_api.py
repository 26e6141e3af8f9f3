"""First access to a lake through ``v2xlake.open`` vs ``NuScenes(...)`` on the same metadata.

    python tests/bench/bench_api.py [--scale 0.1] [--keep DIR]

Writes, cheaply (metadata only: no points, no images), a clean zone of nuScenes-trainval-like
size and the equivalent nuScenes tables (JSON), then, each in a fresh process:

* v2xlake: ``v2xlake.open(lake)``, the list of clips, one clip's first cooperative sample
  (both agents' frames and relative transform) and its boxes; then a lake-wide SQL frame
  index (every reference frame of every clip in one query);
* nuscenes-devkit: ``NuScenes(version, dataroot)`` (loads every table and builds its
  indexes), the first sample and its boxes (``get_boxes``).

Scale 1.0 = 850 scenes (425 two-agent clips): per scene 40 samples (2 Hz), 400 LiDAR frames
(20 Hz) and 6 x 240 camera frames (12 Hz), one ego pose per sample_data in the devkit's
tables and 125 Hz INS in the lake, 1,372 boxes and 76 instances: nuScenes trainval's
1,166,187 sample_annotations and 64,386 instances (its 1.3 M radar sample_data are left out
on both sides). Prints wall time and peak RSS of each process, and the ratios. Not run by
pytest.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

SAMPLES, LIDAR, CAMS, CAM_FRAMES, BOXES, INSTANCES, INS_HZ = 40, 400, 6, 240, 1372, 76, 125
CAM_NAMES = ["CAM_FRONT", "CAM_FRONT_LEFT", "CAM_FRONT_RIGHT", "CAM_BACK", "CAM_BACK_LEFT",
             "CAM_BACK_RIGHT"]
T0 = 100_000_000


def write_lake(root: Path, n_clips: int) -> dict[str, int]:
    from v2xlake.schemas.arrow import columns_to_table, rows_to_table
    from v2xlake.schemas.tables import LAKE_TABLES
    from v2xlake.storage.lake import Lake

    lake = Lake(root)
    rows: dict[str, int] = {}

    def put(name: str, cols: dict, clip: str, agent: str | None = None) -> None:
        t = columns_to_table(LAKE_TABLES[name], cols)
        rows[name] = rows.get(name, 0) + t.num_rows
        lake.write_table("clean", name, t, clip_id=clip, agent_id=agent)

    rng = np.random.default_rng(0)
    for c in range(n_clips):
        cid = f"clip-{c:04d}"
        lake.write_table("clean", "clips", rows_to_table(LAKE_TABLES["clips"], [dict(
            clip_id=cid, location="bench", road_type="urban", weather="sunny", lighting="day",
            work_zone=False, n_agents=2, reference_agent="a0", duration_s=20.0,
            source="simulated", status="ok")]), clip_id=cid)
        lake.write_table("clean", "agents", rows_to_table(LAKE_TABLES["agents"], [
            dict(clip_id=cid, agent_id=a, kind="vehicle", role="reference" if a == "a0"
                 else "cooperative", has_ins=True) for a in ("a0", "a1")]), clip_id=cid)
        ann: dict[str, list] = {k: [] for k in ("agent_id", "sensor", "frame_idx", "t_ns",
                                                "instance_id", "category")}
        for ai, a in enumerate(("a0", "a1")):
            n = INS_HZ * 20 + 10
            t = T0 - 16_000_000 + np.arange(n, dtype=np.int64) * (1_000_000_000 // INS_HZ)
            x = 10.0 * (t - T0) / 1e9
            z = np.zeros(n)
            put("ego_poses", dict(clip_id=[cid] * n, agent_id=[a] * n, t_ns=t, x=x,
                                  y=z + 3.5 * ai, z=z, qw=z + 1, qx=z, qy=z, qz=z, vx=z + 10,
                                  vy=z, vz=z, rtk_status=np.full(n, 2)), cid, a)
            cal = [dict(clip_id=cid, agent_id=a, sensor="LIDAR_TOP", modality="lidar",
                        source="clip.yaml", tx=0.9, ty=0.0, tz=1.8, qw=1.0, qx=0.0, qy=0.0,
                        qz=0.0)]
            cal += [dict(clip_id=cid, agent_id=a, sensor=s, modality="camera",
                         source="camera_info", tx=1.5, ty=0.0, tz=1.5, qw=0.5, qx=-0.5, qy=0.5,
                         qz=-0.5, width=1600, height=900, fx=1266.0, fy=1266.0, cx=800.0,
                         cy=450.0, distortion_model="none", distortion=[]) for s in CAM_NAMES]
            lake.write_table("clean", "calibrated_sensors",
                             rows_to_table(LAKE_TABLES["calibrated_sensors"], cal),
                             clip_id=cid, agent_id=a)
            rows["calibrated_sensors"] = rows.get("calibrated_sensors", 0) + len(cal)
            fi = np.arange(LIDAR, dtype=np.int32)
            ts = T0 + fi.astype(np.int64) * 50_000_000
            put("lidar_frames", dict(clip_id=[cid] * LIDAR, agent_id=[a] * LIDAR,
                                     sensor=["LIDAR_TOP"] * LIDAR, frame_idx=fi, stamp_ns=ts,
                                     t_start_ns=ts, t_end_ns=ts + 49_000_000,
                                     n_points=np.full(LIDAR, 34_000), n_nan=np.zeros(LIDAR)),
                cid, a)
            put("deskew_frames", dict(clip_id=[cid] * LIDAR, agent_id=[a] * LIDAR,
                                      sensor=["LIDAR_TOP"] * LIDAR, frame_idx=fi,
                                      n_uncovered=np.zeros(LIDAR), deskew_ref_ns=ts), cid, a)
            m = CAMS * CAM_FRAMES
            ci = np.tile(np.arange(CAM_FRAMES, dtype=np.int32), CAMS)
            put("camera_frames", dict(
                clip_id=[cid] * m, agent_id=[a] * m,
                sensor=np.repeat(CAM_NAMES, CAM_FRAMES).tolist(), frame_idx=ci,
                stamp_ns=T0 + ci.astype(np.int64) * 83_333_333, width=np.full(m, 1600),
                height=np.full(m, 900),
                blob=[f"{cid}/{a}/{s}/{k:06d}.png" for s in CAM_NAMES for k in range(CAM_FRAMES)],
                sha256=["0" * 64] * m), cid, a)
            per = BOXES // SAMPLES
            kf = np.repeat(np.arange(SAMPLES) * (LIDAR // SAMPLES), per)
            ann["agent_id"] += [a] * len(kf)
            ann["sensor"] += ["LIDAR_TOP"] * len(kf)
            ann["frame_idx"].append(kf.astype(np.int32))
            ann["t_ns"].append(T0 + kf.astype(np.int64) * 50_000_000)
            ann["instance_id"] += [f"i{k % INSTANCES}" for k in range(len(kf))]
            ann["category"] += ["Car"] * len(kf)
        n = len(ann["agent_id"])
        cols = {k: (np.concatenate(v) if k in ("frame_idx", "t_ns") else v)
                for k, v in ann.items()}
        r = rng.normal(size=(n, 3))
        one = np.ones(n)
        put("annotations", dict(clip_id=[cid] * n, **cols, cx=r[:, 0] * 20, cy=r[:, 1] * 20,
                                cz=r[:, 2], w=one * 1.9, l=one * 4.5, h=one * 1.6, qw=one,
                                qx=0 * one, qy=0 * one, qz=0 * one, vx=0 * one, vy=0 * one,
                                vz=0 * one, links=[[] for _ in range(n)],
                                num_lidar_pts=np.full(n, 50)), cid)
        put("instances", dict(clip_id=[cid] * INSTANCES,
                              instance_id=[f"i{k}" for k in range(INSTANCES)],
                              category=["Car"] * INSTANCES,
                              n_annotations=np.full(INSTANCES, 36),
                              agents=[["a0", "a1"]] * INSTANCES,
                              first_t_ns=np.full(INSTANCES, T0),
                              last_t_ns=np.full(INSTANCES, T0 + 19_500_000_000),
                              links=[[] for _ in range(INSTANCES)]), cid)
    return rows


def write_nuscenes(root: Path, version: str, n_scenes: int) -> dict[str, int]:
    """The same metadata as nuScenes JSON tables, every reference the devkit indexes valid."""
    import cv2

    tok = iter(range(1, 1 << 62))

    def new() -> str:
        return f"{next(tok):032x}"

    tabs: dict[str, list[dict]] = {k: [] for k in (
        "attribute", "calibrated_sensor", "category", "ego_pose", "instance", "log", "map",
        "sample", "sample_annotation", "sample_data", "scene", "sensor", "visibility")}
    cat = new()
    tabs["category"].append(dict(token=cat, name="vehicle.car", description="car", index=0))
    attr = new()
    tabs["attribute"].append(dict(token=attr, name="vehicle.moving", description=""))
    tabs["visibility"].append(dict(token="4", level="v80-100", description=""))
    sensors = {ch: new() for ch in ["LIDAR_TOP", *CAM_NAMES]}
    for ch, st in sensors.items():
        tabs["sensor"].append(dict(token=st, channel=ch,
                                   modality="lidar" if ch == "LIDAR_TOP" else "camera"))
    logs = []
    K = [[1266.0, 0, 800.0], [0, 1266.0, 450.0], [0, 0, 1]]
    for s in range(n_scenes):
        log, scene = new(), new()
        logs.append(log)
        tabs["log"].append(dict(token=log, logfile=f"s{s}", vehicle="a", date_captured="1970",
                                location="bench"))
        cs = {ch: new() for ch in sensors}
        for ch, ct in cs.items():
            tabs["calibrated_sensor"].append(dict(
                token=ct, sensor_token=sensors[ch], translation=[1.0, 0.0, 1.5],
                rotation=[1.0, 0.0, 0.0, 0.0],
                camera_intrinsic=[] if ch == "LIDAR_TOP" else K))
        samples = [new() for _ in range(SAMPLES)]
        for k, st in enumerate(samples):
            tabs["sample"].append(dict(token=st, timestamp=100_000 + k * 500_000 + s,
                                       prev=samples[k - 1] if k else "",
                                       next=samples[k + 1] if k + 1 < SAMPLES else "",
                                       scene_token=scene))
        tabs["scene"].append(dict(token=scene, log_token=log, nbr_samples=SAMPLES,
                                  first_sample_token=samples[0], last_sample_token=samples[-1],
                                  name=f"scene-{s:04d}", description=""))
        for ch in sensors:
            n, period = (LIDAR, 50_000) if ch == "LIDAR_TOP" else (CAM_FRAMES, 83_333)
            toks = [new() for _ in range(n)]
            for k, t in enumerate(toks):
                ts = 100_000 + k * period + s
                si = min(ts // 500_000, SAMPLES - 1)
                tabs["ego_pose"].append(dict(token=t, timestamp=ts,
                                             rotation=[1.0, 0.0, 0.0, 0.0],
                                             translation=[ts / 1e5, 0.0, 0.0]))
                tabs["sample_data"].append(dict(
                    token=t, sample_token=samples[si], ego_pose_token=t,
                    calibrated_sensor_token=cs[ch], timestamp=ts, fileformat="pcd",
                    is_key_frame=(k % (n // SAMPLES) == 0), height=0, width=0,
                    filename=f"samples/{ch}/{t}.bin", prev=toks[k - 1] if k else "",
                    next=toks[k + 1] if k + 1 < n else ""))
        insts = [new() for _ in range(INSTANCES)]
        per = BOXES // SAMPLES
        anns: dict[str, list[str]] = {i: [] for i in insts}
        rows = []
        for k, st in enumerate(samples):
            for b in range(per):
                at, it = new(), insts[(k * per + b) % INSTANCES]
                anns[it].append(at)
                rows.append(dict(token=at, sample_token=st, instance_token=it,
                                 visibility_token="4", attribute_tokens=[attr],
                                 translation=[float(b), 1.0, 0.5], size=[1.9, 4.5, 1.6],
                                 rotation=[1.0, 0.0, 0.0, 0.0], prev="", next="",
                                 num_lidar_pts=50, num_radar_pts=0))
        tabs["sample_annotation"] += rows
        for it in insts:
            a = anns[it] or [rows[0]["token"]]
            tabs["instance"].append(dict(token=it, category_token=cat, nbr_annotations=len(a),
                                         first_annotation_token=a[0],
                                         last_annotation_token=a[-1]))
    (root / "maps").mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(root / "maps" / "bench.png"), np.zeros((100, 100), np.uint8))
    tabs["map"].append(dict(token=new(), log_tokens=logs, category="semantic_prior",
                            filename="maps/bench.png"))
    (root / version).mkdir(parents=True, exist_ok=True)
    for name, rows_ in tabs.items():
        (root / version / f"{name}.json").write_text(json.dumps(rows_))
    return {k: len(v) for k, v in tabs.items()}


# peak RSS of this process: VmHWM (Linux keeps ru_maxrss across exec, so a child would
# report its parent's peak)
PEAK = "int(open('/proc/self/status').read().split('VmHWM:')[1].split()[0]) / 1024"

V2X_PROBE = """
import sys, time
t0 = time.perf_counter()
import v2xlake
lake = v2xlake.open(sys.argv[1])
clips = lake.clips
s = lake.clip(clips[0]).sample(0)
boxes = s.boxes("world")
T = s.T("a0", "a1")
t1 = time.perf_counter()
idx = lake.frame_index()
t2 = time.perf_counter()
print(len(clips), len(boxes["a0"]), idx.num_rows, t1 - t0, t2 - t1,
      PEAK)
"""

DEVKIT_PROBE = """
import sys, time
t0 = time.perf_counter()
from nuscenes.nuscenes import NuScenes
nusc = NuScenes(sys.argv[2], sys.argv[1], verbose=False)
s = nusc.sample[0]
boxes = nusc.get_boxes(s["data"]["LIDAR_TOP"])
t1 = time.perf_counter()
print(len(nusc.scene), len(boxes), len(nusc.sample), t1 - t0,
      PEAK)
"""

IMPORT_PROBE = """
import time
t0 = time.perf_counter()
import {mod}
print(time.perf_counter() - t0, PEAK)
"""


def _run(code: str, *args: str) -> list[float]:
    code = code.replace("PEAK", PEAK)
    out = subprocess.run([sys.executable, "-c", code, *args], check=True, capture_output=True,
                         text=True, cwd=REPO).stdout.split()
    return [float(x) for x in out]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scale", type=float, default=0.1, help="1.0 = nuScenes trainval size")
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--keep", type=Path, help="write the data here and keep it")
    args = ap.parse_args()
    n_clips = max(1, round(425 * args.scale))
    base = args.keep or Path(tempfile.mkdtemp(prefix="bench-api-"))
    try:
        lake, nus, version = base / "lake", base / "nuscenes", "v1.0-trainval"
        t = time.perf_counter()
        lrows = write_lake(lake, n_clips) if not (lake / "clean").exists() else {}
        t_lake = time.perf_counter() - t
        t = time.perf_counter()
        nrows = write_nuscenes(nus, version, 2 * n_clips) if not (nus / version).exists() \
            else {}
        t_nus = time.perf_counter() - t
        size = sum(p.stat().st_size for p in (nus / version).glob("*.json")) / 2**20
        lsize = sum(p.stat().st_size for p in lake.rglob("*.parquet")) / 2**20
        print(f"scale {args.scale}: {n_clips} clips x 2 agents = {2 * n_clips} scenes")
        if lrows:
            print(f"  lake ({t_lake:.0f} s to write, {lsize:.0f} MiB Parquet): " + ", ".join(
                f"{k} {v:,}" for k, v in sorted(lrows.items())))
        if nrows:
            print(f"  nuScenes JSON ({t_nus:.0f} s to write, {size:.0f} MiB): " + ", ".join(
                f"{k} {v:,}" for k, v in sorted(nrows.items()) if v > 1))
        imp_v = _run(IMPORT_PROBE.format(mod="v2xlake.api"))
        imp_n = _run(IMPORT_PROBE.format(mod="nuscenes.nuscenes"))
        v = min((_run(V2X_PROBE, str(lake)) for _ in range(args.repeat)), key=lambda r: r[3])
        d = min((_run(DEVKIT_PROBE, str(nus), version) for _ in range(args.repeat)),
                key=lambda r: r[3])
        print(f"  imports alone: v2xlake.api {imp_v[0]:.2f} s / {imp_v[1]:.0f} MiB, "
              f"nuscenes.nuscenes {imp_n[0]:.2f} s / {imp_n[1]:.0f} MiB")
        print(f"  v2xlake.open -> clips -> first sample + boxes: {v[3]:.2f} s "
              f"(imports included), peak RSS {v[5]:.0f} MiB ({int(v[0])} clips)")
        print(f"  lake-wide frame index (one SQL query): {v[4]:.2f} s, {int(v[2]):,} frames")
        print(f"  NuScenes(...) -> first sample + boxes: {d[3]:.2f} s (imports included), "
              f"peak RSS {d[4]:.0f} MiB ({int(d[0])} scenes, {int(d[2]):,} samples)")
        print(f"  ratio first access: devkit / v2xlake = {d[3] / v[3]:.1f}x time, "
              f"{d[4] / v[5]:.1f}x memory")
    finally:
        if args.keep is None:
            shutil.rmtree(base, ignore_errors=True)


if __name__ == "__main__":
    main()
