"""``simulate(out_dir, config)``: write one multi-agent clip folder (COMMON.md contract).

Order of work: build the world and rigs, pre-compute all INS / IMU / GNSS samples, then walk
the clip one 100 ms LiDAR period at a time: cast each agent's scan, derive its annotations,
render the camera frames triggered in that period, and stream everything into the per-agent
bags (re-ordered by log time in a small heap). Truth and metadata are written last.

Clip extent: ``n = floor(seconds * 10)`` LiDAR scans starting at ``start_s`` (a PPS); cameras at
every ``30 / camera_hz``-th trigger of ``sec * 1e9 + round(k * 1e9 / 30)`` inside
[start, end) with ``end = start + n * 100 ms`` (unchanged). The navigation streams run like a
real, continuously recording INS: INS/IMU every 8 ms and GNSS every 100 ms over
[start, end + NAV_TAIL_NS), i.e. the first sample is still at the clip-start PPS edge (= the
first scan start, so ``clip_t0_abs`` is unchanged) and the last INS sample is at
``end + 16 ms``, at least two INS periods after the last LiDAR point (< end), so the final scan
is bracketed by INS samples and can be deskewed like every other (before, INS stopped at the
last scan's start and deskew had to skip that scan). GNSS gains the fix at ``end``. A 1 s clip
thus has 128 INS / IMU and 11 GNSS messages per agent (was 125 / 10). ``truth/poses.parquet``
covers the same extended span.
"""

from __future__ import annotations

import json
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from v2xlake.schemas.annotation import AnnotationFile, Box3D, BoxAnnotation
from v2xlake.schemas.clip import FixedPose
from v2xlake.tasks.geodesy import LocalFrame
from v2xlake.tasks.geometry import compose, invert, matrix_to_quat, rigid, rotation_angle
from v2xlake.tasks.pngcodec import encode_png
from v2xlake.tasks.simulate import navformats
from v2xlake.tasks.simulate.bagwrite import POINT_DTYPE, BagSink
from v2xlake.tasks.simulate.camera import CameraRenderer
from v2xlake.tasks.simulate.clipmeta import (
    EGO_FRAME,
    bag_name,
    build_clip_config,
    image_topic,
    info_topic,
    lidar_topic,
    radar_topic,
    side_lidar_topic,
    write_msg_definition,
)
from v2xlake.tasks.simulate.config import AGENT_NAMES, SimConfig
from v2xlake.tasks.simulate.ins import (
    GNSS_PERIOD_NS,
    INS_PERIOD_NS,
    gnss_fixes,
    ins_error,
    ins_samples,
)
from v2xlake.tasks.simulate.lidar import LidarCaster, Scan
from v2xlake.tasks.simulate.radar import RADAR_FIELDS, RADAR_SPEC, T_EGO_RADAR, RadarSim
from v2xlake.tasks.simulate.rig import build_rigs, frame_name
from v2xlake.tasks.simulate.scene import World, build_world
from v2xlake.tasks.simulate.truth import ins_matrix, pose_columns, transform_dict, write_parquet

LAT_LIDAR_NS = 105_000_000
LAT_CAM_NS = 25_000_000
LAT_INS_NS = 1_000_000
LAT_GNSS_NS = 40_000_000
LAT_RADAR_NS = 30_000_000
S = 1_000_000_000
# navigation streams keep recording this long after the last scan's end (> 1 INS period)
NAV_TAIL_NS = 20_000_000


def camera_stamps(start_ns: int, end_ns: int, step: int) -> list[int]:
    """PPS + round(k * 1e9 / 30) for every trigger in [start, end), every ``step``-th one."""
    out = []
    for sec in range(start_ns // S, (end_ns - 1) // S + 1):
        for k in range(0, 30, step):
            t = sec * S + round(k * S / 30)
            if start_ns <= t < end_ns:
                out.append(t)
    return out


def _annotations(world: World, agent: str, caster: LidarCaster, scan: Scan,
                 ) -> list[BoxAnnotation]:
    """Boxes of every actor hit by this scan, in the TRUE LiDAR frame at the scan start.

    The box state is taken at the column whose beam azimuth is closest to the azimuth of the
    box centre seen from the sensor at that same column time (``t_ns`` = that column's time).
    """
    sc = world.scene
    st = caster.last
    ids, counts = np.unique(scan.obj_id, return_counts=True)
    cnt = dict(zip(ids.tolist(), counts.tolist(), strict=True))
    T_l0w = invert(rigid(st.rot[0], st.origin[0]))
    ncol = len(st.t_ns)
    col_az = 2 * np.pi * np.arange(ncol) / ncol
    out = []
    for k, (i, act) in enumerate(caster.actors):
        n = cnt.get(sc.actor_id(i), 0)
        if n == 0:
            continue
        d = np.einsum("cji,cj->ci", st.rot, st.actor_center[:, k] - st.origin)
        az = np.mod(np.arctan2(-d[:, 1], d[:, 0]), 2 * np.pi)
        j = int(np.argmin(np.abs(np.mod(az - col_az + np.pi, 2 * np.pi) - np.pi)))
        c, yaw = st.actor_center[j, k], float(st.actor_yaw[j, k])
        rw = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1.0]])
        cl = T_l0w[:3, :3] @ c + T_l0w[:3, 3]
        q = matrix_to_quat(T_l0w[:3, :3] @ rw)
        q = q / np.linalg.norm(q)
        j0, j1 = max(j - 1, 0), min(j + 1, ncol - 1)
        v = (st.actor_center[j1, k] - st.actor_center[j0, k]) / ((st.t_ns[j1] - st.t_ns[j0]) / 1e9)
        ln, wd, ht = act.size
        out.append(BoxAnnotation(
            agent_id=agent, sensor="LIDAR_TOP", frame_idx=scan.frame_idx, t_ns=int(st.t_ns[j]),
            instance_id=act.instance_id, category=act.category,
            box=Box3D(center=cl.tolist(), size=[wd, ln, ht], rotation=q.tolist()),
            velocity=(T_l0w[:3, :3] @ v).tolist(), links=list(act.links), num_lidar_pts=int(n)))
    return out


def simulate(out_dir: str | Path, config: SimConfig | None = None) -> Path:
    """Write a clip folder to ``out_dir`` (must not exist or be empty); returns its path."""
    cfg = config or SimConfig.preset("small")
    out = Path(out_dir)
    if out.exists() and any(out.iterdir()):
        raise FileExistsError(f"simulate: output folder {out} exists and is not empty")
    out.mkdir(parents=True, exist_ok=True)
    t_wall = time.perf_counter()
    world = build_world(cfg)
    rigs = build_rigs(cfg)
    frame = LocalFrame(cfg.origin_lat, cfg.origin_lon)
    start_ns = cfg.start_s * S
    n_scans = int(np.floor(cfg.seconds * cfg.lidar.rate_hz + 1e-9))
    if n_scans < 1:
        raise ValueError(f"seconds={cfg.seconds} is shorter than one LiDAR sweep")
    period_ns = round(S / cfg.lidar.rate_hz)
    end_ns = start_ns + n_scans * period_ns
    cam_stamps = camera_stamps(start_ns, end_ns, cfg.camera_step)
    nav_end_ns = end_ns + NAV_TAIL_NS
    ins_t = np.arange(start_ns, nav_end_ns, INS_PERIOD_NS, dtype=np.int64)
    gnss_t = np.arange(start_ns, nav_end_ns, GNSS_PERIOD_NS, dtype=np.int64)

    sinks: dict[str, BagSink] = {}
    casters: dict[str, LidarCaster] = {}
    side_casters: dict[str, LidarCaster] = {}  # SimConfig.side_lidar: LIDAR_LEFT
    radars: dict[str, RadarSim] = {}
    renderers: dict[str, dict[str, CameraRenderer]] = {}
    errs = {a: ins_error(cfg, a) for a in cfg.agents}
    fixed: dict[str, FixedPose] = {}
    for agent in cfg.agents:
        rig = rigs[agent]
        sink = BagSink(out / bag_name(agent, cfg.storage), cfg.storage)
        sinks[agent] = sink
        sink.topic("/tf_static", "tf2_msgs/msg/TFMessage", latching=True)
        sink.topic(lidar_topic(agent), "sensor_msgs/msg/PointCloud2")
        for cam in rig.cameras:
            sink.topic(image_topic(agent, cam), "sensor_msgs/msg/CompressedImage")
            sink.topic(info_topic(agent, cam), "sensor_msgs/msg/CameraInfo")
        if agent != "rsu":  # a roadside unit has a surveyed pose, no navigation topics
            navformats.declare(sink, agent, cfg.pose_format)
            sink.topic(f"/{agent}/imu", "sensor_msgs/msg/Imu")
            sink.topic(f"/{agent}/gnss", "sensor_msgs/msg/NavSatFix")
        f = sink.f
        children = [(frame_name(agent, "LIDAR_TOP"), rig.T_ego_lidar_pub)]
        if rig.T_ego_side_true is not None and rig.T_ego_side_pub is not None:
            sink.topic(side_lidar_topic(agent), "sensor_msgs/msg/PointCloud2")
            children.append((frame_name(agent, "LIDAR_LEFT"), rig.T_ego_side_pub))
            side_casters[agent] = LidarCaster(world, agent, rig.T_ego_side_true,
                                              cfg.side_lidar_spec, start_ns, cfg.seed + 1)
        if cfg.radar and agent != "rsu":
            sink.topic(radar_topic(agent), "sensor_msgs/msg/PointCloud2")
            children.append((frame_name(agent, "RADAR_FRONT"), T_EGO_RADAR))
            radars[agent] = RadarSim(world, agent, start_ns, cfg.seed)
        children += [(frame_name(agent, c), cr.T_ego_cam_pub) for c, cr in rig.cameras.items()]
        sink.put("/tf_static", start_ns, f.tf_static(start_ns, EGO_FRAME, children))
        # INS / IMU / GNSS for the whole clip (small messages; the heap orders them)
        rng = np.random.default_rng([cfg.seed, 555, AGENT_NAMES.index(agent)])
        traj = world.agents[agent]
        ins = ins_samples(cfg, traj, errs[agent], frame, ins_t, rng)
        if agent == "rsu":
            fixed[agent] = navformats.fixed_pose(ins)
        else:
            navformats.put_poses(sink, cfg, agent, ins, frame)
            for i, t in enumerate(ins_t.tolist()):
                sink.put(f"/{agent}/imu", t + LAT_INS_NS, f.imu(
                    t, EGO_FRAME, ins.quat_enu_xyzw[i], ins.gyro[i], ins.accel[i],
                    f"/{agent}/imu", cfg.imu_gyro_noise ** 2, cfg.imu_accel_noise ** 2))
            lat, lon, alt = gnss_fixes(cfg, traj, errs[agent], frame, gnss_t, rng)
            for i, t in enumerate(gnss_t.tolist()):
                sink.put(f"/{agent}/gnss", t + LAT_GNSS_NS, f.navsatfix(
                    t, EGO_FRAME, lat[i], lon[i], alt[i], cfg.gnss_noise_m, f"/{agent}/gnss"))
        casters[agent] = LidarCaster(world, agent, rig.T_ego_lidar_true, cfg.lidar, start_ns,
                                     cfg.seed)
        renderers[agent] = {c: CameraRenderer(world, agent, cr) for c, cr in rig.cameras.items()}

    annotations: list[BoxAnnotation] = []
    box_rows: list[dict[str, Any]] = []
    lt: dict[str, list[np.ndarray]] = {k: [] for k in
                                       ("agent", "frame_idx", "idx", "t_ns", "wx", "wy", "wz",
                                        "obj", "is_static")}
    cam_frame_idx: dict[tuple[str, str], int] = {}
    n_points = 0
    pool = ThreadPoolExecutor(max_workers=cfg.workers)
    for k in range(n_scans):
        ts = start_ns + k * period_ns
        stats: dict[str, dict[int, tuple[int, float]]] = {}
        for agent in cfg.agents:
            sink, caster = sinks[agent], casters[agent]
            scan = caster.cast(k)
            n_points += len(scan.xyz)
            pts = np.zeros(len(scan.xyz), POINT_DTYPE)
            pts["x"], pts["y"], pts["z"] = scan.xyz[:, 0], scan.xyz[:, 1], scan.xyz[:, 2]
            pts["intensity"], pts["ring"] = scan.intensity, scan.ring
            pts["return_type"] = scan.return_type
            pts["timestamp"] = scan.t_ns / 1e9
            topic = lidar_topic(agent)
            sink.put(topic, ts + LAT_LIDAR_NS, sink.f.pointcloud2(
                ts, frame_name(agent, "LIDAR_TOP"), pts, topic))
            annotations += _annotations(world, agent, caster, scan)
            if agent in side_casters:
                s_scan = side_casters[agent].cast(k)
                n_points += len(s_scan.xyz)
                sp = np.zeros(len(s_scan.xyz), POINT_DTYPE)
                sp["x"], sp["y"], sp["z"] = s_scan.xyz[:, 0], s_scan.xyz[:, 1], s_scan.xyz[:, 2]
                sp["intensity"], sp["ring"] = s_scan.intensity, s_scan.ring
                sp["return_type"] = s_scan.return_type
                sp["timestamp"] = s_scan.t_ns / 1e9
                sink.put(side_lidar_topic(agent), ts + LAT_LIDAR_NS, sink.f.pointcloud2(
                    ts, frame_name(agent, "LIDAR_LEFT"), sp, side_lidar_topic(agent)))
            if agent in radars:  # a 20 Hz radar: two scans per LiDAR period
                n_r = round(RADAR_SPEC.rate_hz / cfg.lidar.rate_hz)
                for j in range(k * n_r, (k + 1) * n_r):
                    rs = radars[agent].scan(j)
                    sink.put(radar_topic(agent), rs.stamp_ns + LAT_RADAR_NS, sink.f.pointcloud2(
                        rs.stamp_ns, frame_name(agent, "RADAR_FRONT"), rs.points,
                        radar_topic(agent), RADAR_FIELDS))
            ids, inv, cnt = np.unique(scan.obj_id, return_inverse=True, return_counts=True)
            mean_t = np.bincount(inv, weights=(scan.t_ns - ts).astype(float)) / cnt + ts
            stats[agent] = {int(i): (int(c), float(m)) for i, c, m in zip(ids, cnt, mean_t,
                                                                            strict=True)}
            if cfg.write_lidar_truth:
                n = len(scan.xyz)
                lt["agent"].append(np.full(n, agent))
                lt["frame_idx"].append(np.full(n, k, np.int32))
                lt["idx"].append(np.arange(n, dtype=np.int32))
                lt["t_ns"].append(scan.t_ns)
                lt["wx"].append(scan.world[:, 0])
                lt["wy"].append(scan.world[:, 1])
                lt["wz"].append(scan.world[:, 2])
                lt["obj"].append(np.asarray(world.scene.names, object)[scan.obj_id])
                lt["is_static"].append(world.scene.is_static_id(scan.obj_id))
        for t_cam in (t for t in cam_stamps if ts <= t < ts + period_ns):
            tau = (t_cam - start_ns) / 1e9
            apose = world.scene.actor_poses(tau)
            jobs = [(agent, cam, rend.render(tau, apose))
                    for agent in cfg.agents for cam, rend in renderers[agent].items()]
            # OpenCV releases the GIL: PNG encoding (the floor of the camera cost) runs in parallel
            pngs = list(pool.map(lambda job: encode_png(job[2].image, cfg.png_compression), jobs))
            for (agent, cam, r), png in zip(jobs, pngs, strict=True):
                sink, rend = sinks[agent], renderers[agent][cam]
                fid = frame_name(agent, cam)
                it, io = image_topic(agent, cam), info_topic(agent, cam)
                sink.put(it, t_cam + LAT_CAM_NS, sink.f.compressed_image(t_cam, fid, png, it))
                sink.put(io, t_cam + LAT_CAM_NS,
                         sink.f.camera_info(t_cam, fid, rend.rig.intrinsics, io))
                fidx = cam_frame_idx.get((agent, cam), 0)
                cam_frame_idx[(agent, cam)] = fidx + 1
                for b in r.boxes:
                    row = {"agent": agent, "camera": cam, "frame_idx": fidx, "stamp_ns": t_cam,
                           **b, "lidar_frame_idx": k, "lidar_n_pts": 0, "lidar_mean_t_ns": -1}
                    if b["kind"] == "object":
                        oid = world.scene.names.index(b["instance_id"])
                        if oid in stats[agent]:
                            c, m = stats[agent][oid]
                            row["lidar_n_pts"], row["lidar_mean_t_ns"] = c, round(m)
                    box_rows.append(row)
        for sink in sinks.values():
            sink.flush(ts - 2 * period_ns)
    pool.shutdown()
    counts = {}
    for agent, sink in sinks.items():
        sink.close()
        counts[agent] = dict(sink.counts)

    # ---- metadata, annotations, truth
    clip = build_clip_config(cfg, rigs, fixed)
    clip.dump(out)
    write_msg_definition(out)
    af = AnnotationFile(clip_id=cfg.name, annotations=annotations)
    (out / "annotations.json").write_text(af.model_dump_json())
    tdir = out / "truth"
    tdir.mkdir()
    (tdir / "sim_config.json").write_text(cfg.model_dump_json(indent=1))
    _write_truth(tdir, cfg, world, rigs, errs, start_ns, nav_end_ns, n_scans, period_ns)
    if box_rows:
        cols = {k: [r[k] for r in box_rows] for k in box_rows[0]}
        write_parquet(tdir / "boxes2d.parquet", cols)
    if cfg.write_lidar_truth:
        write_parquet(tdir / "lidar_truth.parquet",
                      {k: np.concatenate(v) for k, v in lt.items()})
    stats_out = {"wall_s": time.perf_counter() - t_wall, "n_scans": n_scans,
                 "n_points": n_points, "n_images": sum(cam_frame_idx.values()),
                 "n_annotations": len(annotations), "messages": counts}
    (tdir / "stats.json").write_text(json.dumps(stats_out, indent=1))
    return out


def _write_truth(tdir: Path, cfg: SimConfig, world: World, rigs: dict, errs: dict,
                 start_ns: int, end_ns: int, n_scans: int, period_ns: int) -> None:
    t_ns = np.arange(start_ns, end_ns + 1, 1_000_000, dtype=np.int64)
    tau = (t_ns - start_ns) / 1e9
    cols: dict[str, list[np.ndarray]] = {}
    for agent in cfg.agents:
        traj = world.agents[agent]
        m = traj.matrix(tau)
        v = traj.velocity(tau)
        b = errs[agent].bias(tau)
        part = {"agent": np.full(len(t_ns), agent), "t_ns": t_ns, **pose_columns(m),
                "vx": v[:, 0], "vy": v[:, 1], "vz": v[:, 2],
                "bx": b[:, 0], "by": b[:, 1], "bz": b[:, 2]}
        for k2, v2 in part.items():
            cols.setdefault(k2, []).append(np.asarray(v2))
    write_parquet(tdir / "poses.parquet", {k: np.concatenate(v) for k, v in cols.items()})

    ext: dict[str, Any] = {
        "world": {"frame": "local ENU, tasks.geodesy.LocalFrame(origin_lat, origin_lon), "
                  "z = ellipsoidal height; red's true INS position at the first PPS = (0, 0, z0)",
                  "origin_lat": cfg.origin_lat, "origin_lon": cfg.origin_lon,
                  "ground_z": world.scene.ground_z},
        "agents": {},
    }
    for agent in cfg.agents:
        rig, e = rigs[agent], errs[agent]
        ext["agents"][agent] = {
            "T_ego_lidar_true": transform_dict(rig.T_ego_lidar_true),
            "T_ego_lidar_published": transform_dict(rig.T_ego_lidar_pub),
            **({"T_ego_lidar_left_true": transform_dict(rig.T_ego_side_true),
                "T_ego_lidar_left_published": transform_dict(rig.T_ego_side_pub)}
               if rig.T_ego_side_true is not None else {}),
            "cameras": {c: {"T_ego_cam_true": transform_dict(cr.T_ego_cam_true),
                            "T_ego_cam_published": transform_dict(cr.T_ego_cam_pub),
                            "intrinsics": cr.intrinsics.model_dump(mode="json")}
                        for c, cr in rig.cameras.items()},
            "ins_error": {"b0": e.b0.tolist(), "b1": e.b1.tolist(), "phase": e.phase,
                          "drift_mps": e.drift.tolist(),
                          "step_m": e.step.tolist(), "step_at_s": e.step_at_s,
                          "period_s": e.period_s, "att_bias_rpy_rad": e.att_bias_rpy.tolist(),
                          "model": "p_ins = p_true + b0 + b1 sin(2 pi tau / period + phase) "
                                   "+ drift_mps tau + step_m [tau >= step_at_s]; "
                                   "R_ins = Rz(yaw) Ry(pitch) Rx(roll) @ R_true"},
        }
    (tdir / "extrinsics.json").write_text(json.dumps(ext, indent=1))

    rows: dict[str, list[Any]] = {}
    others = [a for a in cfg.agents if a != "red"]
    scan_t = start_ns + period_ns * np.arange(n_scans, dtype=np.int64)
    tau_s = (scan_t - start_ns) / 1e9
    T1 = world.agents["red"].matrix(tau_s)
    L1 = T1 @ rigs["red"].T_ego_lidar_true
    I1 = ins_matrix(errs["red"], T1, tau_s) @ rigs["red"].T_ego_lidar_pub
    for other in others:
        T2 = world.agents[other].matrix(tau_s)
        true = compose(invert(L1), T2, rigs[other].T_ego_lidar_true)
        I2 = ins_matrix(errs[other], T2, tau_s) @ rigs[other].T_ego_lidar_pub
        init = compose(invert(I1), I2)
        d = compose(invert(true), init)
        ang = np.degrees(rotation_angle(d))
        part = {"agent_ref": ["red"] * n_scans, "agent_other": [other] * n_scans,
                "frame_idx": np.arange(n_scans, dtype=np.int32), "t_ns": scan_t,
                **pose_columns(true),
                **{f"init_{k}": v for k, v in pose_columns(init).items()},
                "init_err_trans_m": np.linalg.norm(d[:, :3, 3], axis=1), "init_err_rot_deg": ang}
        for k2, v2 in part.items():
            rows.setdefault(k2, []).append(np.asarray(v2))
    if rows:
        write_parquet(tdir / "relative.parquet", {k: np.concatenate(v) for k, v in rows.items()})
