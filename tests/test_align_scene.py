"""A synthetic, physically timed scene for the align / annotate tests (no simulator needed).

One agent drives at 20 m/s on a gentle curve; a 10 Hz spinning LiDAR starts each scan at
azimuth 0 (forward) and turns clockwise, so every point's time follows its azimuth; a 30 Hz
camera looks LEFT (its field of view is swept ~62-88 ms into each scan). Objects move in
the world (a car overtaking-ish at 15 m/s, an oncoming car, a pedestrian) and one car is
parked. Deskewed points are produced as eq. 3 would: each point is where its object was at
the point's own time, expressed in the LiDAR frame at scan start (L0). Boxes are annotated
like a labeller would: in L0, at the time the beam swept the object, with world velocity
in L0 axes. The true 2D box of every object in every camera frame comes from the object's
true pose at the camera time seen from the camera's true pose at that time.
"""

from __future__ import annotations

import io
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from v2xlake.schemas.arrow import columns_to_table, rows_to_table
from v2xlake.schemas.calibration import CameraIntrinsics
from v2xlake.schemas.geometry import matrix_to_quat
from v2xlake.schemas.tables import (
    AgentRow,
    AnnotationRow,
    CalibratedSensorRow,
    CameraFrameRow,
    ClipRow,
    DeskewFrameRow,
    EgoPoseRow,
    LidarFrameRow,
    LidarPointRow,
)
from v2xlake.storage.lake import Lake
from v2xlake.tasks.align.boxes import BoxArray
from v2xlake.tasks.interpolate import PoseTrack
from v2xlake.tasks.projection import Camera, project_boxes_2d

V_EGO = 20.0
YAW_RATE = 0.15  # rad/s
PERIOD_NS = 100_000_000
T0S = [100_000_000 + k * PERIOD_NS for k in range(3)]
CAM_STAMPS = np.array([100_000_000 + round(k * 1e9 / 30) for k in range(14)], dtype=np.int64)
T_EGO_LIDAR = np.eye(4)
T_EGO_LIDAR[:3, 3] = (0.5, 0.0, 1.9)
INTR = CameraIntrinsics(width=1280, height=720, fx=640.0, fy=640.0, cx=640.0, cy=360.0)


def t_ego_cam_left() -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])  # columns: cam x, y, z
    T[:3, 3] = (0.3, 0.9, 1.5)
    return T


def ego_pose(t_ns: np.ndarray | int) -> np.ndarray:
    """(K, 4, 4) exact T_world_ego: 20 m/s on a circle of yaw rate 0.15 rad/s."""
    t = np.atleast_1d(np.asarray(t_ns, dtype=np.float64)) * 1e-9
    psi = YAW_RATE * t
    T = np.tile(np.eye(4), (t.size, 1, 1))
    c, s = np.cos(psi), np.sin(psi)
    T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = c, -s, s, c
    T[:, 0, 3] = V_EGO / YAW_RATE * np.sin(psi)
    T[:, 1, 3] = V_EGO / YAW_RATE * (1 - np.cos(psi))
    return T


def pose_track() -> PoseTrack:
    t = np.arange(0, 600_000_001, 8_000_000, dtype=np.int64)
    T = ego_pose(t)
    return PoseTrack.create(t, T[:, :3, 3], matrix_to_quat(T[:, :3, :3]))


@dataclass(frozen=True)
class Obj:
    instance_id: str
    category: str
    p0: tuple[float, float, float]  # world centre at t = 0
    v: tuple[float, float, float]  # world velocity
    yaw: float
    size: tuple[float, float, float]  # w, l, h
    links: tuple[str, ...] = ()

    def center(self, t_ns: np.ndarray) -> np.ndarray:
        t = np.asarray(t_ns, dtype=np.float64)[..., None] * 1e-9
        return np.asarray(self.p0) + t * np.asarray(self.v)


OBJECTS = [
    Obj("car-overtaken", "Car", (2.0, 7.5, 0.8), (15.0, 0.0, 0.0), 0.0, (1.9, 4.6, 1.6)),
    Obj("car-oncoming", "Car", (12.0, 11.0, 0.8), (-12.0, 0.0, 0.0), np.pi, (1.9, 4.6, 1.6)),
    Obj("car-parked", "Car", (6.5, 4.8, 0.8), (0.0, 0.0, 0.0), 0.1, (1.8, 4.3, 1.5)),
    Obj("trailer-parked", "Trailer", (1.5, 4.8, 0.8), (0.0, 0.0, 0.0), 0.1, (1.8, 3.5, 1.6),
        ("car-parked",)),
    Obj("ped", "Pedestrian", (4.0, 3.0, 0.9), (0.0, 1.4, 0.0), np.pi / 2, (0.6, 0.6, 1.8)),
]


def _yaw_quat(yaw: float) -> np.ndarray:
    return np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])


def _lidar_world(t_ns: np.ndarray) -> np.ndarray:
    return ego_pose(t_ns) @ T_EGO_LIDAR


def _time_of(p_world: np.ndarray, t0: int, approx_t: np.ndarray) -> np.ndarray:
    """Acquisition time of world points by their azimuth in the LiDAR frame at approx_t."""
    T = np.linalg.inv(_lidar_world(approx_t))
    q = np.einsum("kij,kj->ki", T[:, :3, :3], p_world) + T[:, :3, 3]
    cw = np.mod(-np.arctan2(q[:, 1], q[:, 0]), 2 * np.pi)
    return (t0 + cw / (2 * np.pi) * PERIOD_NS).astype(np.int64)


@dataclass
class Scan:
    t0: int
    xyz: np.ndarray  # deskewed, L0
    t_ns: np.ndarray
    boxes: BoxArray
    categories: list[str] = field(default_factory=list)
    links: list[list[str]] = field(default_factory=list)
    n_obj_pts: list[int] = field(default_factory=list)


def make_scan(t0: int, rng: np.random.Generator, n_ground: int = 12000,
              n_obj: int = 400) -> Scan:
    T_w_l0 = _lidar_world(np.array([t0]))[0]
    T_l0_w = np.linalg.inv(T_w_l0)
    # static ground ring around the ego at scan start
    r = rng.uniform(3.0, 30.0, n_ground)
    a = rng.uniform(-np.pi, np.pi, n_ground)
    g_l0 = np.stack([r * np.cos(a), r * np.sin(a), np.full(n_ground, -2.0)], 1)
    g_w = g_l0 @ T_w_l0[:3, :3].T + T_w_l0[:3, 3]
    t_g = _time_of(g_w, t0, np.full(n_ground, t0))
    xyz, ts = [g_l0], [t_g]
    centers, sizes, quats, tb, vels, cats, links, npts, ids = [], [], [], [], [], [], [], [], []
    for o in OBJECTS:
        local = rng.uniform(-0.5, 0.5, (n_obj, 3)) * np.array([o.size[1], o.size[0], o.size[2]])
        c, s = np.cos(o.yaw), np.sin(o.yaw)
        rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
        t = np.full(n_obj, t0, dtype=np.int64)
        for _ in range(3):  # fixed point: the time depends on where the object is then
            pw = local @ rot.T + o.center(t)
            t = _time_of(pw, t0, t)
        pw = local @ rot.T + o.center(t)
        xyz.append(pw @ T_l0_w[:3, :3].T + T_l0_w[:3, 3])
        ts.append(t)
        t_ann = round(t.mean())
        cw = o.center(np.array(t_ann))
        centers.append(T_l0_w[:3, :3] @ cw + T_l0_w[:3, 3])
        sizes.append(o.size)
        quats.append(matrix_to_quat(T_l0_w[:3, :3] @ rot))
        tb.append(t_ann)
        vels.append(T_l0_w[:3, :3] @ np.asarray(o.v))
        cats.append(o.category)
        links.append(list(o.links))
        npts.append(n_obj)
        ids.append(o.instance_id)
    boxes = BoxArray(np.array(ids, dtype=object), np.array(centers), np.array(sizes, float),
                     np.array(quats), np.array(tb, dtype=np.int64), np.array(vels))
    return Scan(t0, np.concatenate(xyz), np.concatenate(ts), boxes, cats, links, npts)


def true_boxes2d(cam_t_ns: int, T_ego_cam: np.ndarray) -> dict[str, np.ndarray]:
    T_cam_w = np.linalg.inv(ego_pose(np.array([cam_t_ns]))[0] @ T_ego_cam)
    out = {}
    for o in OBJECTS:
        c = o.center(np.array(cam_t_ns))[None]
        b = project_boxes_2d(c, np.array([o.size], float), _yaw_quat(o.yaw)[None], T_cam_w,
                             INTR)[0]
        if np.all(np.isfinite(b)):
            out[o.instance_id] = b
    return out


# ------------------------------------------------------------------ a clean lake + truth dir
CLIP = "synthetic-align"


def write_lake(root: Path, seed: int = 0) -> tuple[Lake, Path, list[Scan]]:
    """Clean-zone tables as the upstream stages would leave them, and a truth/ folder."""
    rng = np.random.default_rng(seed)
    lake = Lake(root / "lake")
    scans = [make_scan(t0, rng) for t0 in T0S]
    aid = "red"
    lake.write_table("clean", "clips", rows_to_table(ClipRow, [ClipRow(
        clip_id=CLIP, location="synthetic", road_type="arterial", weather="clear",
        lighting="day", work_zone=False, n_agents=1, reference_agent=aid, duration_s=0.5,
        source="simulated", status="ok")]), clip_id=CLIP)
    lake.write_table("clean", "agents", rows_to_table(AgentRow, [AgentRow(
        clip_id=CLIP, agent_id=aid, kind="vehicle", role="reference", has_ins=True)]),
        clip_id=CLIP, agent_id=aid)
    tr = pose_track()
    lake.write_table("clean", "ego_poses", columns_to_table(EgoPoseRow, {
        "clip_id": [CLIP] * len(tr), "agent_id": [aid] * len(tr),
        "t_ns": tr.t_ns, "x": tr.xyz[:, 0], "y": tr.xyz[:, 1], "z": tr.xyz[:, 2],
        "qw": tr.quat_wxyz[:, 0], "qx": tr.quat_wxyz[:, 1], "qy": tr.quat_wxyz[:, 2],
        "qz": tr.quat_wxyz[:, 3], "vx": np.zeros(len(tr)), "vy": np.zeros(len(tr)),
        "vz": np.zeros(len(tr)), "rtk_status": np.full(len(tr), 2)}), clip_id=CLIP,
        agent_id=aid)
    T_c = t_ego_cam_left()
    qc = matrix_to_quat(T_c[:3, :3])
    lake.write_table("clean", "calibrated_sensors", rows_to_table(CalibratedSensorRow, [
        CalibratedSensorRow(clip_id=CLIP, agent_id=aid, sensor="LIDAR_TOP", modality="lidar",
                            tx=0.5, ty=0.0, tz=1.9, qw=1.0, qx=0.0, qy=0.0, qz=0.0,
                            source="clip.yaml"),
        CalibratedSensorRow(clip_id=CLIP, agent_id=aid, sensor="CAM_LEFT", modality="camera",
                            tx=T_c[0, 3], ty=T_c[1, 3], tz=T_c[2, 3], qw=qc[0], qx=qc[1],
                            qy=qc[2], qz=qc[3], width=INTR.width, height=INTR.height,
                            fx=INTR.fx, fy=INTR.fy, cx=INTR.cx, cy=INTR.cy,
                            distortion_model="none", distortion=[], source="camera_info"),
    ]), clip_id=CLIP, agent_id=aid)
    lake.write_table("clean", "lidar_frames", rows_to_table(LidarFrameRow, [
        LidarFrameRow(clip_id=CLIP, agent_id=aid, sensor="LIDAR_TOP", frame_idx=k,
                      stamp_ns=s.t0, t_start_ns=s.t0, t_end_ns=s.t0 + PERIOD_NS - 1,
                      n_points=len(s.t_ns), n_nan=0)
        for k, s in enumerate(scans)]), clip_id=CLIP, agent_id=aid)
    lake.write_table("clean", "deskew_frames", rows_to_table(DeskewFrameRow, [
        DeskewFrameRow(clip_id=CLIP, agent_id=aid, sensor="LIDAR_TOP", frame_idx=k,
                       n_uncovered=0, deskew_ref_ns=s.t0)
        for k, s in enumerate(scans)]), clip_id=CLIP, agent_id=aid)
    ok, png = cv2.imencode(".png", np.full((INTR.height, INTR.width, 3), 70, np.uint8))
    assert ok
    cam_rows = []
    for k, st in enumerate(CAM_STAMPS):
        key = lake.write_blob("clean", lake.blob_key(CLIP, aid, "CAM_LEFT", k), png.tobytes())
        cam_rows.append(CameraFrameRow(clip_id=CLIP, agent_id=aid, sensor="CAM_LEFT",
                                       frame_idx=k, stamp_ns=int(st), width=INTR.width,
                                       height=INTR.height, blob=key, sha256="0" * 64))
    lake.write_table("clean", "camera_frames", rows_to_table(CameraFrameRow, cam_rows),
                     clip_id=CLIP, agent_id=aid)
    n = [len(s.t_ns) for s in scans]
    xyz = np.concatenate([s.xyz for s in scans]).astype(np.float32)
    lake.write_table("clean", "lidar_points_deskewed", columns_to_table(LidarPointRow, {
        "clip_id": [CLIP] * sum(n), "agent_id": [aid] * sum(n),
        "sensor": pa.array(["LIDAR_TOP"] * sum(n)).dictionary_encode(),
        "frame_idx": np.repeat(np.arange(len(scans)), n).astype(np.int32),
        "t_ns": np.concatenate([s.t_ns for s in scans]),
        "x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2],
        "intensity": np.zeros(sum(n), np.float32), "ring": np.zeros(sum(n), np.uint16),
        "return_id": np.zeros(sum(n), np.uint8)}), clip_id=CLIP, agent_id=aid,
        row_group_by="frame_idx")
    ann = []
    for k, s in enumerate(scans):
        b = s.boxes
        for j in range(len(b)):
            ann.append(AnnotationRow(
                clip_id=CLIP, agent_id=aid, sensor="LIDAR_TOP", frame_idx=k,
                t_ns=int(b.t_ns[j]), instance_id=str(b.instance_id[j]),
                category=s.categories[j], cx=b.center[j, 0], cy=b.center[j, 1],
                cz=b.center[j, 2], w=b.size[j, 0], l=b.size[j, 1], h=b.size[j, 2],
                qw=b.quat[j, 0], qx=b.quat[j, 1], qy=b.quat[j, 2], qz=b.quat[j, 3],
                vx=b.velocity[j, 0], vy=b.velocity[j, 1], vz=b.velocity[j, 2],
                links=s.links[j], num_lidar_pts=None))
    lake.write_table("clean", "annotations", rows_to_table(AnnotationRow, ann), clip_id=CLIP,
                     agent_id=aid)
    truth = root / "truth"
    truth.mkdir(parents=True, exist_ok=True)
    rows: dict[str, list] = {k: [] for k in
                             ("agent_id", "camera", "frame_idx", "instance_id", "kind",
                              "x0", "y0", "x1", "y1")}
    for k, st in enumerate(CAM_STAMPS):
        for inst, b in true_boxes2d(int(st), T_c).items():
            for col, v in zip(rows, [aid, "CAM_LEFT", k, inst, "object", *b.tolist()],
                              strict=True):
                rows[col].append(v)
    buf = io.BytesIO()
    pq.write_table(pa.table(rows), buf)
    (truth / "boxes2d.parquet").write_bytes(buf.getvalue())
    return lake, truth, scans


def camera() -> Camera:
    return Camera("CAM_LEFT", INTR, t_ego_cam_left())
