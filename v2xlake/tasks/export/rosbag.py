"""Per-agent ROS 2 bag for SLAM / odometry (CATS-V2V supplementary B.3) and ROS 1 <-> 2.

One bag per agent with standard message types only, so any SLAM front end subscribes
without custom packages:

* ``/<agent>/lidar/points``  sensor_msgs/msg/PointCloud2: the RAW scan (sensor frame, not
  deskewed: SLAM systems deskew themselves), fields x y z intensity (f32), ring (u16) and
  ``time`` (f32 seconds since the header stamp = scan start), the Velodyne layout that
  LIO-SAM and FAST-LIO read;
* ``/<agent>/camera/<CAM>/image/compressed`` sensor_msgs/msg/CompressedImage (the anonymized
  PNG bytes, lossless) + ``/<agent>/camera/<CAM>/camera_info`` (calibration as recorded);
* ``/<agent>/radar/<RADAR>/points`` sensor_msgs/msg/PointCloud2 per radar (clips with
  ``radar_frames``): one message per scan stamped at the scan's time (a radar reports one
  time per scan), frame ``<agent>/<radar lower-case>``, fields x y z (radar frame),
  ``velocity`` (measured radial / Doppler speed, m/s, positive away) and ``rcs`` (dBsm, NaN
  where the radar gives none), all f32 -- the lake's ``radar_points`` unchanged;
* ``/<agent>/imu`` sensor_msgs/msg/Imu (clean imu table, orientation from the interpolated
  INS pose);
* ``/<agent>/ins/odometry`` nav_msgs/msg/Odometry: ``T_world_ego`` in the clip's local ENU
  (frame ``map``, child ``<agent>/base_link``), twist in the body frame;
* ``/tf`` (tf2_msgs/msg/TFMessage) ``map -> <agent>/base_link`` at every pose sample and
  ``/tf_static`` ``<agent>/base_link -> <agent>/<sensor>`` for every sensor: the frame tree
  that Foxglove's 3D panel, RViz and tf2 listeners use (Odometry alone gives none);
* ``/<agent>/boxes`` visualization_msgs/msg/MarkerArray: the annotated boxes of each LiDAR
  frame (a DELETEALL, then one CUBE and one label per box, ``ns`` = category, ``id`` = a
  stable number per global instance id, the id itself in the label), in the LiDAR frame at
  the frame's time.

Frame ids carry the agent as a prefix (``red/base_link``, ``red/lidar_top``, ``red/cam_front``;
the world is ``map``), so the agents' bags can be played or opened together without their
frames colliding; ``combine_agents`` writes all agents into one bag on one timeline.

Stamps and bag times are the clip's relative time (0.1 s is the clip's first instant;
docs/architecture.md, Time): absolute time never leaves the raw zone. Foxglove shows them as
elapsed seconds with its timestamp format set to "seconds" (as a date they read 1970-01-01
00:00:00.1). MCAP chunks are zstd-compressed. Streams are merged lazily in time order, so
memory stays at about one scan.
"""

from __future__ import annotations

import heapq
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pyarrow.compute as pc
from pydantic import BaseModel, ConfigDict, Field
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from v2xlake.schemas.errors import ClipError
from v2xlake.schemas.stage import StageReport
from v2xlake.storage.lake import Lake
from v2xlake.storage.reader import (
    DESKEWED,
    CameraCalib,
    RadarFrames,
    RadarScan,
    iter_point_frames,
    read_radar_scans,
)
from v2xlake.tasks.export.common import file_output, report_step
from v2xlake.tasks.geometry import matrix_to_quat
from v2xlake.tasks.reader import AgentData, ClipData, boxes_matrices, load_clip

POINT_DTYPE = np.dtype({"names": ["x", "y", "z", "intensity", "ring", "time"],
                        "formats": ["<f4", "<f4", "<f4", "<f4", "<u2", "<f4"],
                        "offsets": [0, 4, 8, 12, 16, 18], "itemsize": 24})
_FIELD_OFFSETS = (("x", 0), ("y", 4), ("z", 8), ("intensity", 12), ("ring", 16), ("time", 18))
_PF_FLOAT32, _PF_UINT16 = 7, 4
_RADAR_FIELDS = ("x", "y", "z", "velocity", "rcs")  # all f32, packed: offset 4 * i
RADAR_DTYPE = np.dtype({"names": list(_RADAR_FIELDS), "formats": ["<f4"] * 5,
                        "offsets": [0, 4, 8, 12, 16], "itemsize": 20})


class RosbagExportConfig(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")

    storage: Literal["sqlite3", "mcap"] = Field(
        "sqlite3", description="rosbag2 storage: sqlite3 (.db3) or mcap (zstd chunks; what "
                               "Foxglove opens)")
    lidar_sensor: str = "LIDAR_TOP"
    lidar_table: str = Field(
        "lidar_points", description="raw scans in the sensor frame with per-point time (for "
                                    "SLAM), or lidar_points_deskewed (stamped at deskew's "
                                    "reference time, for viewing)")
    rosbag2_version: Literal[8, 9] = 8
    cameras: list[str] | None = None
    boxes: bool = Field(True, description="/<agent>/boxes MarkerArray from the annotations")
    radar: bool = Field(True, description="/<agent>/radar/<RADAR>/points PointCloud2 per "
                                          "radar scan (nothing when the clip has no radar)")
    combine_agents: bool = Field(
        False, description="one bag <clip>_all with every agent on one timeline instead of "
                           "one bag per agent")
    overwrite: bool = True


def _stamp(ts: Any, t_ns: int) -> Any:
    return ts.types["builtin_interfaces/msg/Time"](sec=int(t_ns // 1_000_000_000),
                                                    nanosec=int(t_ns % 1_000_000_000))


def _header(ts: Any, t_ns: int, frame: str) -> Any:
    return ts.types["std_msgs/msg/Header"](stamp=_stamp(ts, t_ns), frame_id=frame)


WORLD_FRAME = "map"


def frame_name(agent_id: str, sensor: str = "base_link") -> str:
    """The tf frame id of an agent's sensor (or its body): ``<agent>/<sensor lower-case>``."""
    return f"{agent_id}/{sensor.lower()}"


def pointcloud_msg(ts: Any, t_ns: int, frame: str, xyz: np.ndarray, intensity: np.ndarray,
                   ring: np.ndarray, t_rel_s: np.ndarray) -> Any:
    arr = np.zeros(len(xyz), POINT_DTYPE)
    arr["x"], arr["y"], arr["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    arr["intensity"], arr["ring"], arr["time"] = intensity, ring, t_rel_s
    PF = ts.types["sensor_msgs/msg/PointField"]
    fields = [PF(name=n, offset=off, datatype=_PF_UINT16 if n == "ring" else _PF_FLOAT32,
                 count=1) for n, off in _FIELD_OFFSETS]
    return ts.types["sensor_msgs/msg/PointCloud2"](
        header=_header(ts, t_ns, frame), height=1, width=len(arr), fields=fields,
        is_bigendian=False, point_step=POINT_DTYPE.itemsize,
        row_step=POINT_DTYPE.itemsize * len(arr), data=arr.view(np.uint8).reshape(-1),
        is_dense=True)


def radar_msg(ts: Any, t_ns: int, frame: str, scan: RadarScan) -> Any:
    """One radar scan as a PointCloud2 (x, y, z, velocity, rcs; f32), stamped ``t_ns``."""
    arr = np.zeros(len(scan), RADAR_DTYPE)
    if len(scan):
        arr["x"], arr["y"], arr["z"] = scan.xyz[:, 0], scan.xyz[:, 1], scan.xyz[:, 2]
        arr["velocity"], arr["rcs"] = scan.velocity, scan.rcs
    PF = ts.types["sensor_msgs/msg/PointField"]
    fields = [PF(name=n, offset=4 * i, datatype=_PF_FLOAT32, count=1)
              for i, n in enumerate(_RADAR_FIELDS)]
    return ts.types["sensor_msgs/msg/PointCloud2"](
        header=_header(ts, t_ns, frame), height=1, width=len(arr), fields=fields,
        is_bigendian=False, point_step=RADAR_DTYPE.itemsize,
        row_step=RADAR_DTYPE.itemsize * len(arr), data=arr.view(np.uint8).reshape(-1),
        # rcs is NaN where the radar reports none, so not every field is finite
        is_dense=bool(np.isfinite(scan.rcs).all()) if len(scan) else True)


def _vec3(ts: Any, v: np.ndarray) -> Any:
    return ts.types["geometry_msgs/msg/Vector3"](x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _quat(ts: Any, q: np.ndarray) -> Any:
    return ts.types["geometry_msgs/msg/Quaternion"](x=float(q[1]), y=float(q[2]),
                                                    z=float(q[3]), w=float(q[0]))


def _streams(lake: Lake, clip: ClipData, agent: AgentData, ts: Any, cfg: RosbagExportConfig,
             ids: dict[str, int]) -> list[tuple[str, str, Iterator[tuple[int, Any]]]]:
    aid, cid = agent.agent_id, clip.clip_id
    out: list[tuple[str, str, Iterator[tuple[int, Any]]]] = []
    sensor = agent.lidar_sensor(cfg.lidar_sensor)
    lf = agent.lidar[sensor]
    # raw scans are stamped at their start (``time`` counts from it); deskewed ones at the
    # time their points are expressed at, so that tf places them right
    deskewed = cfg.lidar_table == DESKEWED
    t0 = dict(zip(lf.frame_idx.tolist(),
                  (lf.points_t_ns if deskewed else lf.t_start_ns).tolist(), strict=True))
    lidar_frame = frame_name(aid, sensor)

    def lidar() -> Iterator[tuple[int, Any]]:
        for fr in iter_point_frames(lake, cid, aid, table=cfg.lidar_table, sensor=sensor):
            ts0 = int(t0.get(fr.frame_idx, int(fr.t_ns.min()) if len(fr.t_ns) else 0))
            rel = ((fr.t_ns - ts0) / 1e9).astype(np.float32)
            yield ts0, pointcloud_msg(ts, ts0, lidar_frame, fr.xyz, fr.intensity, fr.ring,
                                      rel)

    out.append((f"/{aid}/lidar/points", "sensor_msgs/msg/PointCloud2", lidar()))
    cams = agent.cameras_calib()
    for ch, frames in agent.cameras.items():
        if cfg.cameras is not None and ch not in cfg.cameras:
            continue
        cam = cams.get(ch)

        def images(frames: Any = frames, ch: str = ch) -> Iterator[tuple[int, Any]]:
            for k in range(len(frames)):
                t = int(frames.stamp_ns[k])
                data = np.frombuffer(lake.read_blob("clean", frames.blob[k]), np.uint8)
                yield t, ts.types["sensor_msgs/msg/CompressedImage"](
                    header=_header(ts, t, frame_name(aid, ch)), format="png", data=data)

        out.append((f"/{aid}/camera/{ch}/image/compressed", "sensor_msgs/msg/CompressedImage",
                    images()))
        if isinstance(cam, CameraCalib):
            def infos(frames: Any = frames, ch: str = ch,
                      cam: CameraCalib = cam) -> Iterator[tuple[int, Any]]:
                K = cam.K
                P = np.zeros((3, 4))
                P[:, :3] = K
                for k in range(len(frames)):
                    t = int(frames.stamp_ns[k])
                    yield t, ts.types["sensor_msgs/msg/CameraInfo"](
                        header=_header(ts, t, frame_name(aid, ch)), height=cam.height,
                        width=cam.width, distortion_model=cam.distortion_model,
                        d=np.asarray(cam.distortion, np.float64), k=K.reshape(-1).astype(float),
                        r=np.eye(3).reshape(-1), p=P.reshape(-1), binning_x=0, binning_y=0,
                        roi=ts.types["sensor_msgs/msg/RegionOfInterest"](
                            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))

            out.append((f"/{aid}/camera/{ch}/camera_info", "sensor_msgs/msg/CameraInfo",
                        infos()))
    for rs, rf in sorted(agent.radar.items()) if cfg.radar else ():
        def radar(rs: str = rs, rf: RadarFrames = rf) -> Iterator[tuple[int, Any]]:
            scans = read_radar_scans(lake, cid, aid, rs)  # a few MB per clip at most
            frame = frame_name(aid, rs)
            none = np.zeros(0, np.float32)
            for k in range(len(rf)):
                f, t = int(rf.frame_idx[k]), int(rf.stamp_ns[k])
                # a scan without detections is still a scan: an empty cloud at its stamp
                scan = scans.get(f) or RadarScan(f, np.zeros(0, np.int64),
                                                 np.zeros((0, 3), np.float32), none, none)
                yield t, radar_msg(ts, t, frame, scan)

        out.append((f"/{aid}/radar/{rs}/points", "sensor_msgs/msg/PointCloud2", radar()))
    imu = lake.read_table("clean", "imu", clip_id=cid)
    if imu.num_rows:
        imu = imu.filter(imu["agent_id"].to_numpy(zero_copy_only=False) == aid).sort_by("t_ns")

    body = frame_name(aid)

    def imus() -> Iterator[tuple[int, Any]]:
        t = imu["t_ns"].to_numpy()
        cov = agent.poses.covers(t)
        q = np.full((len(t), 4), np.nan)
        if cov.any():
            q[cov] = agent.poses.at(t[cov])[1]
        c = {k: imu[k].to_numpy() for k in ("wx", "wy", "wz", "ax", "ay", "az")}
        unknown = np.zeros(9)
        unknown[0] = -1.0  # REP 145: orientation unknown
        for k in range(len(t)):
            has_q = bool(cov[k])
            yield int(t[k]), ts.types["sensor_msgs/msg/Imu"](
                header=_header(ts, int(t[k]), body),
                orientation=_quat(ts, q[k] if has_q else np.array([1.0, 0, 0, 0])),
                orientation_covariance=np.zeros(9) if has_q else unknown,
                angular_velocity=_vec3(ts, np.array([c["wx"][k], c["wy"][k], c["wz"][k]])),
                angular_velocity_covariance=np.zeros(9),
                linear_acceleration=_vec3(ts, np.array([c["ax"][k], c["ay"][k], c["az"][k]])),
                linear_acceleration_covariance=np.zeros(9))

    if imu.num_rows:
        out.append((f"/{aid}/imu", "sensor_msgs/msg/Imu", imus()))

    def odom() -> Iterator[tuple[int, Any]]:
        p = agent.poses
        from v2xlake.tasks.geometry import quat_to_matrix

        R = quat_to_matrix(p.quat_wxyz)
        for k in range(len(p)):
            t = int(p.t_ns[k])
            v_body = R[k].T @ agent.velocity[k]
            pose = ts.types["geometry_msgs/msg/Pose"](
                position=ts.types["geometry_msgs/msg/Point"](
                    x=float(p.xyz[k, 0]), y=float(p.xyz[k, 1]), z=float(p.xyz[k, 2])),
                orientation=_quat(ts, p.quat_wxyz[k]))
            yield t, ts.types["nav_msgs/msg/Odometry"](
                header=_header(ts, t, WORLD_FRAME), child_frame_id=body,
                pose=ts.types["geometry_msgs/msg/PoseWithCovariance"](
                    pose=pose, covariance=np.zeros(36)),
                twist=ts.types["geometry_msgs/msg/TwistWithCovariance"](
                    twist=ts.types["geometry_msgs/msg/Twist"](
                        linear=_vec3(ts, v_body), angular=_vec3(ts, np.zeros(3))),
                    covariance=np.zeros(36)))

    out.append((f"/{aid}/ins/odometry", "nav_msgs/msg/Odometry", odom()))

    def tf() -> Iterator[tuple[int, Any]]:
        p = agent.poses
        for k in range(len(p)):
            t = int(p.t_ns[k])
            yield t, ts.types["tf2_msgs/msg/TFMessage"](transforms=[_tf(
                ts, t, WORLD_FRAME, body, p.xyz[k], p.quat_wxyz[k])])

    out.append(("/tf", "tf2_msgs/msg/TFMessage", tf()))

    def tf_static() -> Iterator[tuple[int, Any]]:
        t = int(agent.poses.t_ns[0])
        tfs = [_tf(ts, t, body, frame_name(aid, s), cal.T_ego_sensor[:3, 3],
                   matrix_to_quat(cal.T_ego_sensor[:3, :3]))
               for s, cal in sorted(agent.sensors.items())]
        yield t, ts.types["tf2_msgs/msg/TFMessage"](transforms=tfs)

    out.append(("/tf_static", "tf2_msgs/msg/TFMessage", tf_static()))
    if cfg.boxes and agent.annotations.num_rows:
        out.append((f"/{aid}/boxes", "visualization_msgs/msg/MarkerArray",
                    box_markers(ts, agent, sensor, ids)))
    return out


def _tf(ts: Any, t_ns: int, parent: str, child: str, xyz: np.ndarray, q: np.ndarray) -> Any:
    return ts.types["geometry_msgs/msg/TransformStamped"](
        header=_header(ts, t_ns, parent), child_frame_id=child,
        transform=ts.types["geometry_msgs/msg/Transform"](translation=_vec3(ts, xyz),
                                                          rotation=_quat(ts, q)))


# one colour per category family (RGBA), the rest grey
_COLOURS = {"car": (0.2, 0.6, 1.0), "truck": (0.1, 0.3, 0.9), "bus": (0.1, 0.3, 0.9),
            "trailer": (0.9, 0.8, 0.2), "pedestrian": (1.0, 0.3, 0.3),
            "cyclist": (0.9, 0.4, 0.9), "bicycle": (0.9, 0.4, 0.9),
            "motorcycle": (0.9, 0.4, 0.9)}


def _colour(ts: Any, category: str, alpha: float) -> Any:
    c = category.lower()
    rgb = next((v for k, v in _COLOURS.items() if k in c), (0.7, 0.7, 0.7))
    return ts.types["std_msgs/msg/ColorRGBA"](r=rgb[0], g=rgb[1], b=rgb[2], a=alpha)


def box_markers(ts: Any, agent: AgentData, sensor: str,
                ids: dict[str, int]) -> Iterator[tuple[int, Any]]:
    """One MarkerArray per annotated LiDAR frame: DELETEALL, then a CUBE and a label per box,
    in the LiDAR frame at the frame's time (where the boxes were annotated)."""
    ann = agent.annotations
    lf = agent.lidar[sensor]
    t_of = dict(zip(lf.frame_idx.tolist(), lf.points_t_ns.tolist(), strict=True))
    ann = ann.filter(pc.equal(ann["sensor"], sensor))
    if ann.num_rows == 0:
        return
    B = boxes_matrices(ann)
    rows = ann.select(["frame_idx", "t_ns", "instance_id", "category", "w", "l", "h"]).to_pylist()
    order = sorted(range(len(rows)), key=lambda r: (rows[r]["frame_idx"], r))
    frame = frame_name(agent.agent_id, sensor)
    M = ts.types["visualization_msgs/msg/Marker"]
    no_time = ts.types["builtin_interfaces/msg/Duration"](sec=0, nanosec=0)

    def marker(t: int, kind: int, **kw: Any) -> Any:
        base = dict(header=_header(ts, t, frame), ns="", id=0, type=kind, action=0,
                    pose=ts.types["geometry_msgs/msg/Pose"](
                        position=ts.types["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0),
                        orientation=_quat(ts, np.array([1.0, 0, 0, 0]))),
                    scale=_vec3(ts, np.ones(3)), color=_colour(ts, "", 1.0), lifetime=no_time,
                    frame_locked=False, points=[], colors=[], texture_resource="",
                    texture=ts.types["sensor_msgs/msg/CompressedImage"](
                        header=_header(ts, t, frame), format="", data=np.zeros(0, np.uint8)),
                    uv_coordinates=[], text="", mesh_resource="",
                    mesh_file=ts.types["visualization_msgs/msg/MeshFile"](
                        filename="", data=np.zeros(0, np.uint8)),
                    mesh_use_embedded_materials=False)
        base.update(kw)
        return M(**base)

    k = 0
    while k < len(order):
        fi = rows[order[k]]["frame_idx"]
        group = []
        while k < len(order) and rows[order[k]]["frame_idx"] == fi:
            group.append(order[k])
            k += 1
        t = int(t_of.get(fi, rows[group[0]]["t_ns"]))
        markers = [marker(t, M.CUBE, action=M.DELETEALL)]
        for r in group:
            row, T = rows[r], B[r]
            pose = ts.types["geometry_msgs/msg/Pose"](
                position=ts.types["geometry_msgs/msg/Point"](
                    x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
                orientation=_quat(ts, matrix_to_quat(T[:3, :3])))
            num = ids.setdefault(row["instance_id"], len(ids))
            markers.append(marker(t, M.CUBE, ns=row["category"], id=num, pose=pose,
                                  scale=_vec3(ts, np.array([row["l"], row["w"], row["h"]])),
                                  color=_colour(ts, row["category"], 0.45)))
            label = ts.types["geometry_msgs/msg/Pose"](
                position=ts.types["geometry_msgs/msg/Point"](
                    x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3] + row["h"] / 2 + 0.4)),
                orientation=_quat(ts, np.array([1.0, 0, 0, 0])))
            markers.append(marker(t, M.TEXT_VIEW_FACING, ns="labels", id=num, pose=label,
                                  scale=_vec3(ts, np.array([0.0, 0.0, 0.6])),
                                  color=_colour(ts, row["category"], 1.0),
                                  text=f"{row['category']} {row['instance_id']}"))
        yield t, ts.types["visualization_msgs/msg/MarkerArray"](markers=markers)


def _tag(i: int, it: Iterator[tuple[int, Any]]) -> Iterator[tuple[int, int, Any]]:
    for t, msg in it:
        yield t, i, msg


def _static_qos() -> list[Any]:
    """tf2's /tf_static profile (reliable, transient local, keep last 1): a player
    re-publishes it latched, so listeners that start late still get the sensor frames."""
    from rosbags.interfaces import (
        Qos,
        QosDurability,
        QosHistory,
        QosLiveliness,
        QosReliability,
        QosTime,
    )

    zero = QosTime(0, 0)
    return [Qos(QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL,
                zero, zero, QosLiveliness.AUTOMATIC, zero, False)]


def export_rosbag(lake: Lake, clip_id: str, agent_id: str | None, out_dir: Path | str,
                  storage: Literal["sqlite3", "mcap"] | None = None,
                  config: RosbagExportConfig = RosbagExportConfig()) -> StageReport:  # noqa: B008
    """Write ``<out_dir>/<clip>_<agent>/`` (rosbag2) for one agent, or each agent if None
    (``config.combine_agents``: one ``<clip>_all`` bag with every agent). ``storage``
    overrides ``config.storage``."""
    clip = load_clip(lake, clip_id)
    agents = [agent_id] if agent_id else list(clip.agents)
    for aid in agents:
        if aid not in clip.agents:
            raise ClipError(clip_id, "unknown agent", agent_id=aid, stage="export_rosbag")
    ts = get_typestore(Stores.ROS2_HUMBLE)
    report = StageReport(stage="export_rosbag", clip_id=clip_id)
    storage = storage or config.storage
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    # marker ids: one number per global instance id, the same in every agent's bag
    ids = {str(g): i for i, g in enumerate(sorted(set(
        clip.instances["instance_id"].to_pylist() if clip.instances.num_rows else [])))}
    bags = [("all", agents)] if config.combine_agents else [(a, [a]) for a in agents]
    for name, members in bags:
        dst = Path(out_dir) / f"{clip_id}_{name}"
        if dst.exists():
            if not (config.overwrite and (dst / "metadata.yaml").exists()):
                raise ClipError(clip_id, "output exists and is not a rosbag2 to overwrite",
                                agent_id=name, path=str(dst), stage="export_rosbag")
            shutil.rmtree(dst)
        dst.parent.mkdir(parents=True, exist_ok=True)
        streams = [st for aid in members
                   for st in _streams(lake, clip, clip.agents[aid], ts, config, ids)]
        counts: dict[str, int] = {}
        w = Writer(dst, version=config.rosbag2_version, storage_plugin=plugin)
        if plugin == StoragePlugin.MCAP:
            w.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        with w:
            by_topic: dict[str, Any] = {}
            for topic, typ, _ in streams:
                if topic not in by_topic:
                    by_topic[topic] = w.add_connection(
                        topic, typ, typestore=ts,
                        offered_qos_profiles=_static_qos() if topic == "/tf_static" else ())
            conns = [by_topic[topic] for topic, _, _ in streams]
            tagged = [_tag(i, it) for i, (_, _, it) in enumerate(streams)]
            step = f"rosbag {clip_id}_{name}: messages"
            for n_written, (t, i, msg) in enumerate(
                    heapq.merge(*tagged, key=lambda x: (x[0], x[1])), start=1):
                w.write(conns[i], t, ts.serialize_cdr(msg, streams[i][1]))
                counts[streams[i][0]] = counts.get(streams[i][0], 0) + 1
                report_step(step, n_written)  # the total is known once the bag is written
        report_step(step, sum(counts.values()), sum(counts.values()))
        for f in sorted(p for p in dst.iterdir() if p.is_file()):
            report.outputs.append(file_output(f))
        for topic, n in counts.items():
            report.metrics[f"{name}:{topic}"] = float(n)
    return report


def convert_bag(src: Path | str, dst: Path | str, to: Literal["ros1", "ros2"],
                storage: Literal["sqlite3", "mcap"] = "sqlite3",
                rosbag2_version: Literal[8, 9] = 8) -> Path:
    """ROS 2 bag -> ROS 1 ``.bag`` or ROS 1 ``.bag`` -> ROS 2, with rosbags' converter.

    Message types are translated to the destination distribution's standard definitions
    (ROS 1 Noetic, ROS 2 Humble), so e.g. ``sensor_msgs/Imu`` becomes
    ``sensor_msgs/msg/Imu`` and vice versa with the proper field layouts.
    """
    from rosbags.convert import convert

    s, d = Path(src), Path(dst)
    if to == "ros1":
        if d.suffix != ".bag":
            d = d.with_suffix(".bag")
        target = get_typestore(Stores.ROS1_NOETIC)
        if "tf2_msgs/msg/TFMessage" not in target.types:
            # rosbags' Noetic store lacks tf2_msgs; without it the converter copies the ROS 2
            # definition (Header without seq) and ROS 1 nodes reject the md5. This is the
            # Noetic definition (md5 94810edda583a504dfda3829e70d7eec).
            target.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms",
                                               "tf2_msgs/msg/TFMessage"))
    else:
        if d.suffix == ".bag":
            raise ValueError(f"a ROS 2 destination is a directory, not a .bag file: {d}")
        target = get_typestore(Stores.ROS2_HUMBLE)
    if d.exists():
        raise FileExistsError(f"destination exists: {d}")
    convert(srcs=[s], dst=d, dst_storage=storage, dst_version=rosbag2_version, compress=None,
            compress_mode="file", default_typestore=None, typestore=target, exclude_topics=[],
            include_topics=[], exclude_msgtypes=[], include_msgtypes=[])
    return d
