"""Per-agent ROS 2 bag for SLAM / odometry (CATS-V2V supplementary B.3) and ROS 1 <-> 2.

One bag per agent with standard message types only, so any SLAM front end subscribes
without custom packages:

* ``/<agent>/lidar/points``  sensor_msgs/msg/PointCloud2: the RAW scan (sensor frame, not
  deskewed: SLAM systems deskew themselves), fields x y z intensity (f32), ring (u16) and
  ``time`` (f32 seconds since the header stamp = scan start), the Velodyne layout that
  LIO-SAM and FAST-LIO read;
* ``/<agent>/camera/<CAM>/image/compressed`` sensor_msgs/msg/CompressedImage (the anonymized
  PNG bytes, lossless) + ``/<agent>/camera/<CAM>/camera_info`` (calibration as recorded);
* ``/<agent>/imu`` sensor_msgs/msg/Imu (clean imu table, orientation from the interpolated
  INS pose);
* ``/<agent>/ins/odometry`` nav_msgs/msg/Odometry: ``T_world_ego`` in the clip's local ENU
  (frame ``map``, child ``base_link``), twist in the body frame;
* ``/tf_static`` base_link -> each sensor.

Stamps and bag times are the clip's relative time (starts at 0.1 s): absolute time never
leaves the raw zone. Streams are merged lazily in time order, so memory stays at one scan.
"""

from __future__ import annotations

import heapq
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from v2xlake.schemas.errors import ClipError
from v2xlake.schemas.stage import StageReport
from v2xlake.storage.lake import Lake
from v2xlake.storage.reader import CameraCalib, iter_point_frames
from v2xlake.tasks.export.common import file_output
from v2xlake.tasks.geometry import matrix_to_quat
from v2xlake.tasks.reader import AgentData, ClipData, load_clip

POINT_DTYPE = np.dtype({"names": ["x", "y", "z", "intensity", "ring", "time"],
                        "formats": ["<f4", "<f4", "<f4", "<f4", "<u2", "<f4"],
                        "offsets": [0, 4, 8, 12, 16, 18], "itemsize": 24})
_FIELD_OFFSETS = (("x", 0), ("y", 4), ("z", 8), ("intensity", 12), ("ring", 16), ("time", 18))
_PF_FLOAT32, _PF_UINT16 = 7, 4


class RosbagExportConfig(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")

    lidar_sensor: str = "LIDAR_TOP"
    lidar_table: str = "lidar_points"  # raw scans; "lidar_points_deskewed" for deskewed
    rosbag2_version: Literal[8, 9] = 8
    cameras: list[str] | None = None
    overwrite: bool = True


def _stamp(ts: Any, t_ns: int) -> Any:
    return ts.types["builtin_interfaces/msg/Time"](sec=int(t_ns // 1_000_000_000),
                                                    nanosec=int(t_ns % 1_000_000_000))


def _header(ts: Any, t_ns: int, frame: str) -> Any:
    return ts.types["std_msgs/msg/Header"](stamp=_stamp(ts, t_ns), frame_id=frame)


def frame_name(sensor: str) -> str:
    return sensor.lower()


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


def _vec3(ts: Any, v: np.ndarray) -> Any:
    return ts.types["geometry_msgs/msg/Vector3"](x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _quat(ts: Any, q: np.ndarray) -> Any:
    return ts.types["geometry_msgs/msg/Quaternion"](x=float(q[1]), y=float(q[2]),
                                                    z=float(q[3]), w=float(q[0]))


def _streams(lake: Lake, clip: ClipData, agent: AgentData, ts: Any, cfg: RosbagExportConfig,
             ) -> list[tuple[str, str, Iterator[tuple[int, Any]]]]:
    aid, cid = agent.agent_id, clip.clip_id
    out: list[tuple[str, str, Iterator[tuple[int, Any]]]] = []
    sensor = agent.lidar_sensor(cfg.lidar_sensor)
    lf = agent.lidar[sensor]
    t0 = dict(zip(lf.frame_idx.tolist(), lf.t_start_ns.tolist(), strict=True))

    def lidar() -> Iterator[tuple[int, Any]]:
        for fr in iter_point_frames(lake, cid, aid, table=cfg.lidar_table, sensor=sensor):
            ts0 = int(t0.get(fr.frame_idx, int(fr.t_ns.min()) if len(fr.t_ns) else 0))
            rel = ((fr.t_ns - ts0) / 1e9).astype(np.float32)
            yield ts0, pointcloud_msg(ts, ts0, frame_name(sensor), fr.xyz, fr.intensity,
                                      fr.ring, rel)

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
                    header=_header(ts, t, frame_name(ch)), format="png", data=data)

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
                        header=_header(ts, t, frame_name(ch)), height=cam.height,
                        width=cam.width, distortion_model=cam.distortion_model,
                        d=np.asarray(cam.distortion, np.float64), k=K.reshape(-1).astype(float),
                        r=np.eye(3).reshape(-1), p=P.reshape(-1), binning_x=0, binning_y=0,
                        roi=ts.types["sensor_msgs/msg/RegionOfInterest"](
                            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))

            out.append((f"/{aid}/camera/{ch}/camera_info", "sensor_msgs/msg/CameraInfo",
                        infos()))
    imu = lake.read_table("clean", "imu", clip_id=cid)
    if imu.num_rows:
        imu = imu.filter(imu["agent_id"].to_numpy(zero_copy_only=False) == aid).sort_by("t_ns")

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
                header=_header(ts, int(t[k]), "base_link"),
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
                header=_header(ts, t, "map"), child_frame_id="base_link",
                pose=ts.types["geometry_msgs/msg/PoseWithCovariance"](
                    pose=pose, covariance=np.zeros(36)),
                twist=ts.types["geometry_msgs/msg/TwistWithCovariance"](
                    twist=ts.types["geometry_msgs/msg/Twist"](
                        linear=_vec3(ts, v_body), angular=_vec3(ts, np.zeros(3))),
                    covariance=np.zeros(36)))

    out.append((f"/{aid}/ins/odometry", "nav_msgs/msg/Odometry", odom()))

    def tf_static() -> Iterator[tuple[int, Any]]:
        t = int(agent.poses.t_ns[0])
        tfs = []
        for s, cal in sorted(agent.sensors.items()):
            T = cal.T_ego_sensor
            tfs.append(ts.types["geometry_msgs/msg/TransformStamped"](
                header=_header(ts, t, "base_link"), child_frame_id=frame_name(s),
                transform=ts.types["geometry_msgs/msg/Transform"](
                    translation=_vec3(ts, T[:3, 3]),
                    rotation=_quat(ts, matrix_to_quat(T[:3, :3])))))
        yield t, ts.types["tf2_msgs/msg/TFMessage"](transforms=tfs)

    out.append(("/tf_static", "tf2_msgs/msg/TFMessage", tf_static()))
    return out


def _tag(i: int, it: Iterator[tuple[int, Any]]) -> Iterator[tuple[int, int, Any]]:
    for t, msg in it:
        yield t, i, msg


def export_rosbag(lake: Lake, clip_id: str, agent_id: str | None, out_dir: Path | str,
                  storage: Literal["sqlite3", "mcap"] = "sqlite3",
                  config: RosbagExportConfig = RosbagExportConfig()) -> StageReport:  # noqa: B008
    """Write ``<out_dir>/<clip>_<agent>/`` (rosbag2) for one agent, or each agent if None."""
    clip = load_clip(lake, clip_id)
    agents = [agent_id] if agent_id else list(clip.agents)
    ts = get_typestore(Stores.ROS2_HUMBLE)
    report = StageReport(stage="export_rosbag", clip_id=clip_id)
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    for aid in agents:
        if aid not in clip.agents:
            raise ClipError(clip_id, "unknown agent", agent_id=aid, stage="export_rosbag")
        dst = Path(out_dir) / f"{clip_id}_{aid}"
        if dst.exists():
            if not (config.overwrite and (dst / "metadata.yaml").exists()):
                raise ClipError(clip_id, "output exists and is not a rosbag2 to overwrite",
                                agent_id=aid, path=str(dst), stage="export_rosbag")
            shutil.rmtree(dst)
        dst.parent.mkdir(parents=True, exist_ok=True)
        streams = _streams(lake, clip, clip.agents[aid], ts, config)
        counts: dict[str, int] = {}
        with Writer(dst, version=config.rosbag2_version, storage_plugin=plugin) as w:
            conns = [w.add_connection(topic, typ, typestore=ts) for topic, typ, _ in streams]
            tagged = [_tag(i, it) for i, (_, _, it) in enumerate(streams)]
            for t, i, msg in heapq.merge(*tagged, key=lambda x: (x[0], x[1])):
                w.write(conns[i], t, ts.serialize_cdr(msg, streams[i][1]))
                counts[streams[i][0]] = counts.get(streams[i][0], 0) + 1
        for f in sorted(p for p in dst.iterdir() if p.is_file()):
            report.outputs.append(file_output(f))
        for topic, n in counts.items():
            report.metrics[f"{aid}:{topic}"] = float(n)
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
