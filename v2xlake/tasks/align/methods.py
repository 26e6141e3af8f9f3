"""Stamp-, frame- and target-based LiDAR-camera temporal alignment (CATS-V2V main paper Sec. 5).

Frames and times. A box is annotated in the LiDAR frame at scan start ``t0`` (the deskewed
frame, "L0"); its state refers to ``t_ns``, the moment the beam swept the object. L0 is a
frame fixed in the world (the LiDAR pose frozen at t0), so ego motion never moves a box in
L0, only the object's own motion does. A camera frame at ``t_cam`` sees the world from the
camera pose at ``t_cam``:

    T_cam(t_cam)_L0 = T_ego_cam^-1 . T_world_ego(t_cam)^-1 . T_world_ego(t0) . T_ego_lidar

* stamp: the camera frame nearest the LiDAR stamp (scan start), boxes projected with the
  static extrinsics only (what most datasets do; exact for static objects when the camera
  fires at t0, off by the object's motion since t0 otherwise).
* frame: the camera frame closest to the acquisition times of the LiDAR points in that
  camera's field of view (a vote of the points, see :func:`associate`; a camera whose view
  holds the scan seam goes with the scan start, as the paper's forward cameras do); boxes
  (and points) ego-motion compensated from t0 to t_cam.
* target: per object, the camera frame closest to the times of the object's own points
  (the paper averages them; the vote is the same for an object seen in one run of the spin
  and right for one split by the seam); ego motion compensated to t_cam and, where the
  object's velocity is known (annotated, else from its track), the object moved from its
  box time to t_cam, so that it sits where the camera saw it.

All functions are pure (arrays in, arrays out); the lake I/O lives in ``stage.py``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from v2xlake.tasks.align.boxes import BoxArray
from v2xlake.tasks.align.config import AssociationConfig, TimeStat
from v2xlake.tasks.geometry import compose, invert, points_in_boxes
from v2xlake.tasks.interpolate import PoseTrack
from v2xlake.tasks.motion import deskew_points
from v2xlake.tasks.projection import Camera, points_in_fov, project_boxes_2d

Method = Literal["stamp", "frame", "target"]
METHODS: tuple[Method, ...] = ("stamp", "frame", "target")


@dataclass(frozen=True)
class CameraStream:
    """One camera of one agent: geometry plus the stamps of its frames (sorted)."""

    camera: Camera
    frame_idx: np.ndarray  # (F,) int
    stamp_ns: np.ndarray  # (F,) int64, sorted

    def nearest(self, t_ns: np.ndarray | float) -> np.ndarray:
        """Position (into frame_idx / stamp_ns) of the frame nearest each query time."""
        t = np.atleast_1d(np.asarray(t_ns, dtype=np.float64))
        s = self.stamp_ns.astype(np.float64)
        j = np.clip(np.searchsorted(s, t), 1, max(s.size - 1, 1))
        if s.size == 1:
            return np.zeros(t.shape, dtype=np.int64)
        left = s[j - 1]
        right = s[j]
        return np.where(np.abs(t - left) <= np.abs(right - t), j - 1, j).astype(np.int64)


@dataclass(frozen=True)
class LidarScan:
    """One deskewed LiDAR frame: points in L0 with their acquisition times."""

    frame_idx: int
    t0_ns: int  # deskew reference = scan start = the frame's stamp
    xyz: np.ndarray  # (N, 3) in L0
    t_ns: np.ndarray  # (N,) int64 per-point acquisition time
    period_ns: int = 100_000_000


@dataclass(frozen=True)
class Association:
    """Result of one method for one (scan, camera): per box the frame it goes with and where
    its projection lands."""

    method: Method
    camera: str
    frame_pos: np.ndarray  # (M,) position into CameraStream arrays
    points_t_ns: np.ndarray  # (M,) int64: the time the association was made on
    boxes2d: np.ndarray  # (M, 4) x0 y0 x1 y1, NaN if not visible
    n_points: np.ndarray  # (M,) points the association time came from (FOV or object)
    scan_frame_pos: int = -1  # stamp / frame: the one frame of the whole scan (-1: target)
    scan_points_t_ns: int = 0  # stamp / frame: the time that frame was chosen on


def scan_time(t_ns: np.ndarray, t0_ns: int, period_ns: int, stat: TimeStat,
              unwrap: bool = True) -> float:
    """A representative acquisition time of a set of points of one scan.

    A spinning LiDAR's times are phases of one revolution: a camera (or an object) that
    straddles the azimuth where the scan starts gets points from the very start *and* the
    very end of the scan; their plain mean lands mid-scan, at a moment that matches none of
    them. With ``unwrap`` the set is cut at its largest gap on the circle of phases (the
    part of the revolution it was not seen in), so a straddling set becomes one contiguous
    run of times that may extend past t0 + period, towards the next camera frame that did
    see it.
    """
    t = np.asarray(t_ns, dtype=np.int64)
    rel = (t - t0_ns).astype(np.float64)
    if unwrap and rel.size > 1:
        phase = np.mod(rel, period_ns)
        order = np.sort(phase)
        gaps = np.diff(np.concatenate([order, [order[0] + period_ns]]))
        k = int(np.argmax(gaps))
        if k != order.size - 1:  # largest gap is inside the scan, not across its seam
            cut = order[k]  # phases <= cut belong after the seam
            rel = np.where(phase <= cut, phase + period_ns, phase)
        else:
            rel = phase
    val = np.mean(rel) if stat == "mean" else np.median(rel)
    return float(t0_ns + val)


def associate(t_ns: np.ndarray, t0_ns: int, period_ns: int, stream: CameraStream,
              stat: TimeStat, unwrap: bool = True) -> tuple[int, int]:
    """The camera frame "closest to the acquisition times" of a set of points, and the time
    the choice was made on: (position into ``stream``, ns).

    ``vote`` (default): every point picks its nearest camera frame and the frame most points
    picked wins (ties: the earlier frame), reported with the median time of its voters. A
    set seen in two runs of the spin, e.g. a forward camera split by the scan seam into
    points from the very start and the very end of the scan, then goes with the frame that
    is right for most of its points, instead of a mid-scan frame that matches none of them
    (mean / median) or, after unwrapping, the next scan's first frame even when most of the
    points were taken at this scan's start. ``median`` / ``mean``: a single representative
    time (see :func:`scan_time`), then its nearest frame.
    """
    t = np.asarray(t_ns, dtype=np.int64)
    if stat != "vote":
        tr = scan_time(t, t0_ns, period_ns, stat, unwrap)
        return int(stream.nearest(tr)[0]), round(tr)
    pos = stream.nearest(t)
    lo = int(pos.min())
    counts = np.bincount(pos - lo)
    win = lo + int(np.argmax(counts))
    return win, int(np.median(t[pos == win]))


def camera_from_l0(
    traj: PoseTrack, T_ego_lidar: np.ndarray, T_ego_cam: np.ndarray, t0_ns: int,
    t_cam_ns: np.ndarray,
) -> np.ndarray:
    """(K, 4, 4) ``T_cam(t_cam)_L0``: ego-motion compensation from t0 to each camera time."""
    t_cam = np.atleast_1d(np.asarray(t_cam_ns, dtype=np.int64))
    T_w_e0 = traj.matrices(int(t0_ns))[0]
    T_w_ec = traj.matrices(t_cam)
    return compose(invert(T_ego_cam), invert(T_w_ec), T_w_e0, T_ego_lidar)


def compensate_points(
    xyz_l0: np.ndarray, traj: PoseTrack, T_ego_lidar: np.ndarray, t0_ns: int,
    t_ref_ns: int,
) -> np.ndarray:
    """Deskewed points (L0) -> the LiDAR frame at ``t_ref`` (frame-based compensation).

    The deskewed points all live at t0, so eq. 3 with every point time set to t0 and the
    reference time set to the camera stamp is exactly the ego motion between the two.
    """
    t = np.full(len(xyz_l0), t0_ns, dtype=np.int64)
    return deskew_points(xyz_l0, t, traj, T_ego_lidar, int(t_ref_ns)).xyz


def _project_at(
    boxes: BoxArray, stream: CameraStream, traj: PoseTrack, T_ego_lidar: np.ndarray,
    t0_ns: int, frame_pos: np.ndarray, move_objects: bool,
) -> np.ndarray:
    t_cam = stream.stamp_ns[frame_pos]
    uniq, inv = np.unique(t_cam, return_inverse=True)
    T_u = camera_from_l0(traj, T_ego_lidar, stream.camera.T_ego_cam, t0_ns, uniq)
    center = boxes.center
    if move_objects:
        v = np.nan_to_num(boxes.velocity, nan=0.0)
        dt = (t_cam - boxes.t_ns).astype(np.float64) * 1e-9
        center = center + v * dt[:, None]
    return project_boxes_2d(
        center, boxes.size, boxes.quat, T_u[inv.reshape(-1)], stream.camera.intrinsics,
    )


def align_stamp(scan: LidarScan, boxes: BoxArray, stream: CameraStream,
                T_ego_lidar: np.ndarray) -> Association:
    m = len(boxes)
    pos = int(stream.nearest(scan.t0_ns)[0])
    T_cam_lidar = compose(invert(stream.camera.T_ego_cam), T_ego_lidar)
    b2d = project_boxes_2d(boxes.center, boxes.size, boxes.quat, T_cam_lidar,
                           stream.camera.intrinsics)
    return Association(
        "stamp", stream.camera.name, np.full(m, pos, dtype=np.int64),
        np.full(m, scan.t0_ns, dtype=np.int64), b2d, np.zeros(m, dtype=np.int64),
        pos, int(scan.t0_ns),
    )


def frame_association(scan: LidarScan, stream: CameraStream, T_ego_lidar: np.ndarray,
                      params: AssociationConfig) -> tuple[int, int, int]:
    """Frame-based choice for one camera: (frame position, association time, FOV points)."""
    T_cam_lidar = compose(invert(stream.camera.T_ego_cam), T_ego_lidar)
    fov = points_in_fov(scan.xyz, T_cam_lidar, stream.camera.intrinsics, params.fov_near_m)
    n = int(fov.sum())
    if n == 0:  # nothing in view: fall back to the scan start, like the stamp method
        return int(stream.nearest(scan.t0_ns)[0]), scan.t0_ns, 0
    t_fov = scan.t_ns[fov]
    if params.seam_camera == "start":
        phase = np.mod(t_fov - scan.t0_ns, scan.period_ns)
        w = params.seam_window * scan.period_ns
        if phase.min() < w and phase.max() > scan.period_ns - w:
            return int(stream.nearest(scan.t0_ns)[0]), scan.t0_ns, n
    pos, t = associate(t_fov, scan.t0_ns, scan.period_ns, stream, params.frame_time_stat,
                       params.unwrap_seam)
    return pos, t, n


def align_frame(scan: LidarScan, boxes: BoxArray, stream: CameraStream, traj: PoseTrack,
                T_ego_lidar: np.ndarray, params: AssociationConfig) -> Association:
    m = len(boxes)
    p0, t_fov, n = frame_association(scan, stream, T_ego_lidar, params)
    pos = np.full(m, p0, dtype=np.int64)
    b2d = _project_at(boxes, stream, traj, T_ego_lidar, scan.t0_ns, pos, move_objects=False)
    return Association("frame", stream.camera.name, pos, np.full(m, t_fov, dtype=np.int64),
                       b2d, np.full(m, n, dtype=np.int64), p0, t_fov)


def object_points(scan: LidarScan, boxes: BoxArray, params: AssociationConfig) -> list[np.ndarray]:
    """Indices of each object's points (its box grown by ``box_margin_m``)."""
    return points_in_boxes(scan.xyz, boxes.center, boxes.size, boxes.quat, params.box_margin_m)


def align_target(scan: LidarScan, boxes: BoxArray, stream: CameraStream, traj: PoseTrack,
                 T_ego_lidar: np.ndarray, params: AssociationConfig,
                 obj_idx: list[np.ndarray] | None = None) -> Association:
    m = len(boxes)
    idx = obj_idx if obj_idx is not None else object_points(scan, boxes, params)
    pos = np.empty(m, dtype=np.int64)
    t_obj = np.empty(m, dtype=np.int64)
    n = np.array([i.size for i in idx], dtype=np.int64)
    for k, ii in enumerate(idx):
        if ii.size:
            pos[k], t_obj[k] = associate(scan.t_ns[ii], scan.t0_ns, scan.period_ns, stream,
                                         params.target_time_stat, params.unwrap_seam)
        else:  # no points (occluded, deskew dropped them): the box's own time
            t_obj[k] = int(boxes.t_ns[k])
            pos[k] = int(stream.nearest(t_obj[k])[0])
    b2d = _project_at(boxes, stream, traj, T_ego_lidar, scan.t0_ns, pos,
                      move_objects=params.use_velocity)
    return Association("target", stream.camera.name, pos, t_obj, b2d, n)


def align_all(scan: LidarScan, boxes: BoxArray, stream: CameraStream, traj: PoseTrack,
              T_ego_lidar: np.ndarray, params: AssociationConfig,
              obj_idx: list[np.ndarray] | None = None) -> dict[str, Association]:
    """The three methods for one scan and one camera."""
    return {
        "stamp": align_stamp(scan, boxes, stream, T_ego_lidar),
        "frame": align_frame(scan, boxes, stream, traj, T_ego_lidar, params),
        "target": align_target(scan, boxes, stream, traj, T_ego_lidar, params, obj_idx),
    }


def estimate_velocities(instance_id: np.ndarray, t_ns: np.ndarray,
                        center_world: np.ndarray) -> np.ndarray:
    """(M, 3) world velocity of each box from its neighbours in the same instance's track.

    Central differences where an instance has boxes before and after, one-sided at track
    ends, NaN for an instance seen once. Used when annotations carry no velocity.
    """
    m = instance_id.shape[0]
    v = np.full((m, 3), np.nan)
    for inst in np.unique(instance_id):
        rows = np.flatnonzero(instance_id == inst)
        if rows.size < 2:
            continue
        rows = rows[np.argsort(t_ns[rows], kind="stable")]
        t = t_ns[rows].astype(np.float64) * 1e-9
        p = center_world[rows]
        for k, r in enumerate(rows):
            a, b = max(k - 1, 0), min(k + 1, rows.size - 1)
            dt = t[b] - t[a]
            if dt > 0:
                v[r] = (p[b] - p[a]) / dt
    return v
