"""Bag writing for ROS 2 (sqlite3, MCAP) and ROS 1 through ``rosbags`` 0.11.

One :class:`BagSink` per agent. Messages are built with the typestore's generated classes and
serialized with ``serialize_cdr`` (ROS 2) or ``serialize_ros1``; PointCloud2 ``data`` is the
raw bytes of a NumPy structured array (no per-point Python). The custom
``v2xlake_msgs/msg/InsPva`` and, for ROS 1 (whose Noetic store lacks it), ``tf2_msgs/msg/TFMessage``
are registered from their .msg text. ROS 1 connections get the ROS 1 names
(``sensor_msgs/PointCloud2``) from rosbags itself.

Log (receive) times are header stamps plus a fixed, realistic latency per sensor (LiDAR: the
end of the sweep + 5 ms; cameras 25 ms; INS/IMU 1 ms; GNSS 40 ms); consumers must use header
stamps. A small heap re-orders messages by log time before they are written.
"""

from __future__ import annotations

import heapq
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

INS_MSG_TYPE = "v2xlake_msgs/msg/InsPva"
INS_MSG_TEXT = """\
# Vendor-style INS solution: position, velocity, attitude (simulated, v2xlake).
# Attitude is relative to the local-level ENU frame at the vehicle position:
# roll about body x (forward), pitch about body y (left, positive nose-up),
# azimuth clockwise from true north; R_enu_body = Rz(pi/2 - azimuth) Ry(-pitch) Rx(roll).
std_msgs/Header header
float64 latitude        # deg, WGS84
float64 longitude       # deg, WGS84
float64 altitude        # m, ellipsoidal height
float64 roll            # rad
float64 pitch           # rad
float64 azimuth         # rad, clockwise from north, [0, 2 pi)
float64 east_velocity   # m/s
float64 north_velocity  # m/s
float64 up_velocity     # m/s
uint8 rtk_status        # 0 none, 1 float, 2 fixed
"""
TF_MSG_TEXT = "geometry_msgs/TransformStamped[] transforms\n"

POINT_DTYPE = np.dtype({
    "names": ["x", "y", "z", "intensity", "ring", "return_type", "timestamp"],
    "formats": ["<f4", "<f4", "<f4", "<f4", "<u2", "u1", "<f8"],
    "offsets": [0, 4, 8, 12, 16, 18, 24],
    "itemsize": 32,
})
# PointField datatypes: INT8=1 UINT8=2 INT16=3 UINT16=4 INT32=5 UINT32=6 FLOAT32=7 FLOAT64=8
POINT_FIELDS = [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 12, 7), ("ring", 16, 4),
                ("return_type", 18, 2), ("timestamp", 24, 8)]


def make_typestore(ros1: bool) -> Any:
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    add = dict(get_types_from_msg(INS_MSG_TEXT, INS_MSG_TYPE))
    if "tf2_msgs/msg/TFMessage" not in ts.types:
        add.update(get_types_from_msg(TF_MSG_TEXT, "tf2_msgs/msg/TFMessage"))
    ts.register(add)
    return ts


class MsgFactory:
    """Builds messages for one typestore (ROS 1 field names differ: K/D/R/P, header.seq)."""

    def __init__(self, ros1: bool) -> None:
        self.ros1 = ros1
        self.ts = make_typestore(ros1)
        self.T = self.ts.types
        self._seq: dict[str, int] = {}

    def header(self, stamp_ns: int, frame_id: str, key: str = "") -> Any:
        t = self.T["builtin_interfaces/msg/Time"](sec=int(stamp_ns // 1_000_000_000),
                                                   nanosec=int(stamp_ns % 1_000_000_000))
        if self.ros1:
            seq = self._seq.get(key, 0)
            self._seq[key] = seq + 1
            return self.T["std_msgs/msg/Header"](seq=seq, stamp=t, frame_id=frame_id)
        return self.T["std_msgs/msg/Header"](stamp=t, frame_id=frame_id)

    def serialize(self, msg: Any, typename: str) -> bytes | memoryview:
        if self.ros1:
            return self.ts.serialize_ros1(msg, typename)
        return self.ts.serialize_cdr(msg, typename)

    def pointcloud2(self, stamp_ns: int, frame_id: str, points: np.ndarray, topic: str,
                    layout: list[tuple[str, int, int]] | None = None) -> Any:
        """``points`` (a structured array) as PointCloud2; ``layout`` (name, offset,
        datatype) defaults to the LiDAR's ``POINT_FIELDS``."""
        pf = self.T["sensor_msgs/msg/PointField"]
        fields = [pf(name=n, offset=o, datatype=d, count=1) for n, o, d in layout or POINT_FIELDS]
        step = points.dtype.itemsize
        return self.T["sensor_msgs/msg/PointCloud2"](
            header=self.header(stamp_ns, frame_id, topic), height=1, width=len(points),
            fields=fields, is_bigendian=False, point_step=step, row_step=step * len(points),
            data=np.frombuffer(points.tobytes(), np.uint8), is_dense=True)

    def compressed_image(self, stamp_ns: int, frame_id: str, png: bytes, topic: str) -> Any:
        return self.T["sensor_msgs/msg/CompressedImage"](
            header=self.header(stamp_ns, frame_id, topic), format="png",
            data=np.frombuffer(png, np.uint8))

    def camera_info(self, stamp_ns: int, frame_id: str, intr: Any, topic: str) -> Any:
        k = np.array([intr.fx, 0, intr.cx, 0, intr.fy, intr.cy, 0, 0, 1], float)
        p = np.array([intr.fx, 0, intr.cx, 0, 0, intr.fy, intr.cy, 0, 0, 0, 1, 0], float)
        roi = self.T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0,
                                                          width=0, do_rectify=False)
        d = np.asarray(intr.distortion, float)
        names = ("D", "K", "R", "P") if self.ros1 else ("d", "k", "r", "p")
        kw = dict(zip(names, (d, k, np.eye(3).ravel(), p), strict=True))
        return self.T["sensor_msgs/msg/CameraInfo"](
            header=self.header(stamp_ns, frame_id, topic), height=intr.height, width=intr.width,
            distortion_model=str(intr.distortion_model.value), binning_x=0, binning_y=0,
            roi=roi, **kw)

    def ins(self, stamp_ns: int, frame_id: str, vals: dict[str, float], topic: str) -> Any:
        return self.T[INS_MSG_TYPE](header=self.header(stamp_ns, frame_id, topic), **vals)

    def imu(self, stamp_ns: int, frame_id: str, q_xyzw: np.ndarray, gyro: np.ndarray,
            acc: np.ndarray, topic: str, gyro_var: float, acc_var: float) -> Any:
        v3 = self.T["geometry_msgs/msg/Vector3"]
        q = self.T["geometry_msgs/msg/Quaternion"](x=float(q_xyzw[0]), y=float(q_xyzw[1]),
                                                   z=float(q_xyzw[2]), w=float(q_xyzw[3]))
        return self.T["sensor_msgs/msg/Imu"](
            header=self.header(stamp_ns, frame_id, topic), orientation=q,
            orientation_covariance=np.diag([1e-6] * 3).ravel(),
            angular_velocity=v3(x=float(gyro[0]), y=float(gyro[1]), z=float(gyro[2])),
            angular_velocity_covariance=np.diag([gyro_var] * 3).ravel(),
            linear_acceleration=v3(x=float(acc[0]), y=float(acc[1]), z=float(acc[2])),
            linear_acceleration_covariance=np.diag([acc_var] * 3).ravel())

    def navsatfix(self, stamp_ns: int, frame_id: str, lat: float, lon: float, alt: float,
                  sigma: float, topic: str) -> Any:
        st = self.T["sensor_msgs/msg/NavSatStatus"](status=2, service=1)
        var = sigma * sigma
        return self.T["sensor_msgs/msg/NavSatFix"](
            header=self.header(stamp_ns, frame_id, topic), status=st, latitude=float(lat),
            longitude=float(lon), altitude=float(alt),
            position_covariance=np.diag([var, var, 2.25 * var]).ravel(),
            position_covariance_type=2)

    def tf_static(self, stamp_ns: int, parent: str, children: list[tuple[str, np.ndarray]]) -> Any:
        from v2xlake.tasks.geometry import matrix_to_quat

        out = []
        for child, m in children:
            q = matrix_to_quat(m[:3, :3])
            tr = self.T["geometry_msgs/msg/Transform"](
                translation=self.T["geometry_msgs/msg/Vector3"](x=float(m[0, 3]), y=float(m[1, 3]),
                                                                z=float(m[2, 3])),
                rotation=self.T["geometry_msgs/msg/Quaternion"](x=float(q[1]), y=float(q[2]),
                                                                z=float(q[3]), w=float(q[0])))
            out.append(self.T["geometry_msgs/msg/TransformStamped"](
                header=self.header(stamp_ns, parent, "/tf_static"), child_frame_id=child,
                transform=tr))
        return self.T["tf2_msgs/msg/TFMessage"](transforms=out)


class BagSink:
    """Writes one agent's bag; ``put`` buffers, ``flush(upto_ns)`` writes in log-time order."""

    def __init__(self, path: Path, storage: str) -> None:
        self.ros1 = storage == "ros1"
        self.f = MsgFactory(self.ros1)
        self.path = path
        if self.ros1:
            from rosbags.rosbag1 import Writer as Writer1

            self.w: Any = Writer1(path)
        else:
            from rosbags.rosbag2 import StoragePlugin, Writer

            plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
            self.w = Writer(path, version=9, storage_plugin=plugin)
        self.w.open()
        self.conns: dict[str, Any] = {}
        self.types: dict[str, str] = {}
        self.heap: list[tuple[int, int, str, bytes]] = []
        self.n = 0
        self.counts: dict[str, int] = {}

    def topic(self, name: str, msgtype: str, latching: bool = False) -> None:
        if self.ros1:
            self.conns[name] = self.w.add_connection(name, msgtype, typestore=self.f.ts,
                                                     latching=1 if latching else None)
        else:
            self.conns[name] = self.w.add_connection(name, msgtype, typestore=self.f.ts)
        self.types[name] = msgtype
        self.counts[name] = 0

    def put(self, topic: str, log_ns: int, msg: Any) -> None:
        data = bytes(self.f.serialize(msg, self.types[topic]))
        heapq.heappush(self.heap, (int(log_ns), self.n, topic, data))
        self.n += 1

    def flush(self, upto_ns: int | None = None) -> None:
        while self.heap and (upto_ns is None or self.heap[0][0] <= upto_ns):
            t, _, topic, data = heapq.heappop(self.heap)
            self.w.write(self.conns[topic], t, data)
            self.counts[topic] += 1

    def close(self) -> None:
        self.flush()
        self.w.close()
