"""A small, physically consistent clean zone for the export tests (helper E).

Two vehicles drive a straight street with lane markings and building facades; a parked car,
a moving car, a car pulling a trailer (linked instances) and a walking pedestrian share it.
Everything is generated from one world model, so it is self-consistent by construction:

* deskewed points are sampled on the street, facades and inside the annotated boxes in the
  LiDAR frame at scan start t0; raw points are the same points moved to their own beam
  time with the interpolated poses (the inverse of eq. 3), so deskewing them gives back the
  deskewed table;
* camera images are ray-cast through the distorted camera model (plumb_bob) at their
  stamps, so undistorting them with the calibration gives a pinhole view of the same world;
* annotations are the world boxes at t0 expressed in the LiDAR frame at t0.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pyarrow as pa

from v2xlake.schemas.arrow import columns_to_table, rows_to_table
from v2xlake.schemas.geometry import matrix_to_quat, quat_to_matrix
from v2xlake.schemas.tables import LAKE_TABLES
from v2xlake.storage.lake import Lake
from v2xlake.tasks.geometry import invert as invert_rigid
from v2xlake.tasks.geometry import transform as pose_matrices
from v2xlake.tasks.interpolate import PoseTrack

T0_NS = 100_000_000
LIDAR_PERIOD_NS = 100_000_000
POSE_PERIOD_NS = 8_000_000
CAM_W, CAM_H = 320, 180
CAM_K = np.array([[160.0, 0.0, 160.0], [0.0, 160.0, 90.0], [0.0, 0.0, 1.0]])
CAM_D = np.array([-0.05, 0.01, 0.0, 0.0, 0.0])
# camera optical frame (x right, y down, z forward) in the ego frame (x fwd, y left, z up)
R_EGO_CAM = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
SPEED = 5.0


@dataclass(frozen=True)
class WorldObject:
    instance_id: str
    category: str
    start_xy: tuple[float, float]
    velocity_xy: tuple[float, float]
    yaw: float
    wlh: tuple[float, float, float]
    color: tuple[int, int, int]
    links: tuple[str, ...] = ()

    def center(self, t_s: float) -> np.ndarray:
        return np.array([self.start_xy[0] + self.velocity_xy[0] * t_s,
                         self.start_xy[1] + self.velocity_xy[1] * t_s, self.wlh[2] / 2])

    def matrix(self, t_s: float) -> np.ndarray:
        m = np.eye(4)
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        m[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
        m[:3, 3] = self.center(t_s)
        return m


OBJECTS = (
    WorldObject("car-parked", "Car", (22.0, -5.0), (0.0, 0.0), 0.05, (1.9, 4.5, 1.6),
                (40, 60, 200)),
    WorldObject("car-moving", "Car", (6.0, 1.75), (4.0, 0.0), 0.0, (1.8, 4.2, 1.5),
                (200, 40, 40)),
    WorldObject("truck-car", "Car", (34.0, 5.25), (2.0, 0.0), 0.0, (2.0, 4.8, 1.8),
                (40, 160, 40), ("trailer",)),
    WorldObject("trailer", "Trailer", (28.0, 5.25), (2.0, 0.0), 0.0, (2.2, 6.0, 2.4),
                (160, 160, 40), ("truck-car",)),
    WorldObject("ped", "Pedestrian", (14.0, 7.5), (0.0, -1.2), -1.57, (0.7, 0.7, 1.75),
                (200, 120, 200)),
)


def ego_state(x: np.ndarray, lateral: float) -> tuple[np.ndarray, np.ndarray]:
    """Positions and quaternions on the gently curving path y = lateral + 0.3 sin(0.1 x)."""
    y = lateral + 0.3 * np.sin(0.1 * x)
    dy = 0.03 * np.cos(0.1 * x)
    yaw = np.arctan(dy)
    pitch = 0.01 * np.sin(0.7 * x)
    roll = 0.008 * np.cos(0.5 * x)
    from scipy.spatial.transform import Rotation

    q = Rotation.from_euler("ZYX", np.stack([yaw, pitch, roll], 1)).as_quat()  # xyzw
    quat = np.concatenate([q[:, 3:], q[:, :3]], 1)
    quat *= np.where(quat[:, :1] < 0, -1, 1)
    return np.stack([x, y, np.zeros_like(x)], 1), quat


def _ctab(name: str, clip_id: str, agent_id: str, **cols: object) -> pa.Table:
    n = len(next(iter(cols.values())))  # type: ignore[arg-type]
    return columns_to_table(LAKE_TABLES[name], dict(clip_id=[clip_id] * n,
                                                     agent_id=[agent_id] * n, **cols))


def _rt(m: np.ndarray) -> dict[str, float]:
    q = matrix_to_quat(m[:3, :3])
    return dict(tx=float(m[0, 3]), ty=float(m[1, 3]), tz=float(m[2, 3]), qw=float(q[0]),
                qx=float(q[1]), qy=float(q[2]), qz=float(q[3]))


def T_ego_lidar() -> np.ndarray:
    m = np.eye(4)
    a = 0.02  # a small mounting yaw, so frames are not trivially aligned
    m[:3, :3] = [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]
    m[:3, 3] = (0.6, 0.0, 1.8)
    return m


def T_ego_cam() -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = R_EGO_CAM
    m[:3, 3] = (1.6, 0.0, 1.5)
    return m


def _sample_box(rng: np.random.Generator, obj: WorldObject, t_s: float, n: int) -> np.ndarray:
    w, l, h = obj.wlh
    local = rng.uniform(-0.45, 0.45, (n, 3)) * np.array([l, w, h])
    m = obj.matrix(t_s)
    return local @ m[:3, :3].T + m[:3, 3]


def _world_points(rng: np.random.Generator, center: np.ndarray, t_s: float,
                  n_ground: int) -> tuple[np.ndarray, np.ndarray, list[tuple[int, int]]]:
    r = np.sqrt(rng.uniform(3.0**2, 35.0**2, n_ground))
    a = rng.uniform(-np.pi, np.pi, n_ground)
    ground = np.stack([center[0] + r * np.cos(a), center[1] + r * np.sin(a),
                       np.zeros(n_ground)], 1)
    ground = ground[np.abs(ground[:, 1]) < 12.0]
    nw = n_ground // 4
    wx = center[0] + rng.uniform(-30, 30, nw)
    wall = np.stack([wx, np.where(rng.random(nw) < 0.5, -12.0, 12.0), rng.uniform(0, 6, nw)], 1)
    inten = [rng.uniform(0.05, 0.3, len(ground)), rng.uniform(0.3, 0.5, nw)]
    pts = [ground, wall]
    spans: list[tuple[int, int]] = []
    start = len(ground) + nw
    for obj in OBJECTS:
        d = np.linalg.norm(obj.center(t_s)[:2] - center[:2])
        if d > 40.0:
            continue
        n = 200
        pts.append(_sample_box(rng, obj, t_s, n))
        inten.append(rng.uniform(0.5, 0.9, n))
        spans.append((start, start + n))
        start += n
    return np.concatenate(pts), np.concatenate(inten), spans


def _render(track: PoseTrack, t_ns: int, weather: str, rng: np.random.Generator,
            rays_cam: np.ndarray) -> bytes:
    """Ray-cast the street through the distorted camera at time t."""
    T_wc = track.matrices(t_ns)[0] @ T_ego_cam()
    d = rays_cam @ T_wc[:3, :3].T
    o = T_wc[:3, 3]
    t_s = (t_ns - T0_NS) / 1e9
    n = len(d)
    depth = np.full(n, np.inf)
    color = np.empty((n, 3))
    sky = 190.0 if weather == "overcast" else 120.0
    color[:] = sky - 40.0 * np.clip(-d[:, 2], -1, 1)[:, None]
    # ground z = 0
    with np.errstate(divide="ignore", invalid="ignore"):
        tg = -o[2] / d[:, 2]
    hit = (d[:, 2] < -1e-6) & (tg > 0)
    gp = o + tg[:, None] * d
    depth[hit] = tg[hit]
    g = np.full(n, 85.0)
    y = gp[:, 1]
    lane = (np.abs(np.abs(y) - 1.75) < 0.08) & (np.mod(gp[:, 0], 6.0) < 3.0)
    edge = np.abs(np.abs(y) - 3.5) < 0.1
    curb = np.abs(np.abs(y) - 8.0) < 0.15
    g[lane | edge] = 230.0
    g[curb] = 160.0
    g[np.abs(y) > 8.0] = 120.0
    color[hit] = g[hit, None]
    # facades y = +-12
    for wy in (-12.0, 12.0):
        with np.errstate(divide="ignore", invalid="ignore"):
            tw = (wy - o[1]) / d[:, 1]
        wp = o + tw[:, None] * d
        ok = (tw > 0) & (tw < depth) & (wp[:, 2] >= 0) & (wp[:, 2] <= 9.0)
        win = (np.mod(wp[:, 0], 4.0) < 1.8) & (np.mod(wp[:, 2], 3.0) > 1.2)
        c = np.where(win, 60.0, 150.0 + 20.0 * np.sign(wy))
        depth[ok] = tw[ok]
        color[ok] = c[ok, None]
    # boxes (slab test in each box frame), skipping boxes behind the camera
    for obj in OBJECTS:
        m = obj.matrix(t_s)
        w, l, h = obj.wlh
        fwd = T_wc[:3, 2]
        if float(fwd @ (m[:3, 3] - o)) < -0.5 * float(np.linalg.norm(obj.wlh)):
            continue
        inv = invert_rigid(m[None])[0]
        ol = inv[:3, :3] @ o + inv[:3, 3]
        dl = d @ inv[:3, :3].T
        half = np.array([l / 2, w / 2, h / 2])
        with np.errstate(divide="ignore", invalid="ignore"):
            inv_d = 1.0 / dl
            t1 = (-half - ol) * inv_d
            t2 = (half - ol) * inv_d
        lo, hi = np.fmin(t1, t2), np.fmax(t1, t2)
        tn = np.fmax(np.fmax(lo[:, 0], lo[:, 1]), lo[:, 2])
        tf = np.fmin(np.fmin(hi[:, 0], hi[:, 1]), hi[:, 2])
        ok = (tn <= tf) & (tn > 0) & (tn < depth)
        if not ok.any():
            continue
        hitp = ol + tn[ok, None] * dl[ok]
        face = np.argmax(np.abs(hitp) / half, 1)
        shade = np.array([1.0, 0.75, 0.55])[face]
        depth[ok] = tn[ok]
        color[ok] = np.array(obj.color)[None, :] * shade[:, None]
    img = color.reshape(CAM_H, CAM_W, 3)
    if weather != "overcast":
        img = 0.7 * img + 25.0 + rng.normal(0, 6.0, img.shape)
    ok_, png = cv2.imencode(".png", np.clip(img, 0, 255).astype(np.uint8))
    assert ok_
    return png.tobytes()


def _camera_rays() -> np.ndarray:
    u, v = np.meshgrid(np.arange(CAM_W) + 0.0, np.arange(CAM_H) + 0.0)
    pix = np.stack([u.ravel(), v.ravel()], 1).reshape(-1, 1, 2)
    und = cv2.undistortPoints(pix, CAM_K, CAM_D).reshape(-1, 2)
    rays = np.concatenate([und, np.ones((len(und), 1))], 1)
    return rays / np.linalg.norm(rays, axis=1, keepdims=True)


def build_clean_clip(lake: Lake, clip_id: str = "clip-a", *, weather: str = "overcast",
                     location: str = "testville", x_offset: float = 0.0, seconds: float = 2.0,
                     n_ground: int = 3000, seed: int = 0, with_deskewed: bool = True,
                     with_cameras: bool = True,
                     skip_deskewed_frames: tuple[int, ...] = (),
                     skip_deskewed_agent: str | None = None) -> None:
    """Write one clip's clean tables (two agents) into ``lake``."""
    rng = np.random.default_rng(seed)
    agents = {"red": 0.0, "black": -3.5}
    start_x = {"red": x_offset, "black": x_offset - 12.0}
    n_frames = round(seconds * 10)
    pose_t = np.arange(T0_NS - 2 * POSE_PERIOD_NS,
                       T0_NS + n_frames * LIDAR_PERIOD_NS + 12 * POSE_PERIOD_NS, POSE_PERIOD_NS,
                       dtype=np.int64)
    pose_t = pose_t[pose_t >= 0]
    lake.write_table("clean", "clips", rows_to_table(LAKE_TABLES["clips"], [dict(
        clip_id=clip_id, location=location, road_type="arterial", weather=weather,
        lighting="day", work_zone=False, n_agents=2, reference_agent="red",
        duration_s=seconds, source="simulated", status="ok")]), clip_id=clip_id)
    lake.write_table("clean", "agents", rows_to_table(LAKE_TABLES["agents"], [
        dict(clip_id=clip_id, agent_id=a, kind="vehicle",
             role="reference" if a == "red" else "cooperative", has_ins=True)
        for a in agents]), clip_id=clip_id)
    rays = _camera_rays()
    ann_rows: list[dict[str, object]] = []
    inst: dict[str, dict[str, object]] = {}
    for agent, lateral in agents.items():
        ts = (pose_t - T0_NS) / 1e9
        xyz, quat = ego_state(start_x[agent] + SPEED * ts, lateral)
        track = PoseTrack.create(pose_t, xyz, quat)
        vel = np.gradient(xyz, ts, axis=0)
        lake.write_table("clean", "ego_poses", _ctab("ego_poses", clip_id, agent, **dict(
            t_ns=pose_t, x=xyz[:, 0], y=xyz[:, 1], z=xyz[:, 2], qw=quat[:, 0], qx=quat[:, 1],
            qy=quat[:, 2], qz=quat[:, 3], vx=vel[:, 0], vy=vel[:, 1], vz=vel[:, 2],
            rtk_status=np.full(len(pose_t), 2))), clip_id=clip_id, agent_id=agent)
        # IMU at the pose times: body rates and specific force from the trajectory
        lake.write_table("clean", "imu", _ctab("imu", clip_id, agent, **dict(
            sensor=["IMU"] * len(pose_t), t_ns=pose_t, wx=np.zeros(len(pose_t)),
            wy=np.zeros(len(pose_t)), wz=np.gradient(np.unwrap(2 * np.arctan2(
                quat[:, 3], quat[:, 0])), ts), ax=np.zeros(len(pose_t)),
            ay=np.zeros(len(pose_t)), az=np.full(len(pose_t), 9.81))),
            clip_id=clip_id, agent_id=agent)
        calib = [dict(clip_id=clip_id, agent_id=agent, sensor="LIDAR_TOP", modality="lidar",
                      source="clip.yaml", **_rt(T_ego_lidar()))]
        if with_cameras:
            calib.append(dict(clip_id=clip_id, agent_id=agent, sensor="CAM_FRONT",
                              modality="camera", source="camera_info", width=CAM_W,
                              height=CAM_H, fx=CAM_K[0, 0], fy=CAM_K[1, 1], cx=CAM_K[0, 2],
                              cy=CAM_K[1, 2], distortion_model="plumb_bob",
                              distortion=CAM_D.tolist(), **_rt(T_ego_cam())))
        lake.write_table("clean", "calibrated_sensors",
                         rows_to_table(LAKE_TABLES["calibrated_sensors"], calib),
                         clip_id=clip_id, agent_id=agent)
        T_el = T_ego_lidar()
        raw_cols: dict[str, list[np.ndarray]] = {k: [] for k in
                                                 ("frame_idx", "t_ns", "x", "y", "z",
                                                  "intensity", "ring")}
        desk_cols: dict[str, list[np.ndarray]] = {k: [] for k in raw_cols}
        frames = []
        for k in range(n_frames):
            t0 = T0_NS + k * LIDAR_PERIOD_NS
            T_wl0 = track.matrices(t0)[0] @ T_el
            world, inten, _spans = _world_points(rng, T_wl0[:3, 3], (t0 - T0_NS) / 1e9,
                                                n_ground)
            inv0 = invert_rigid(T_wl0[None])[0]
            p0 = world @ inv0[:3, :3].T + inv0[:3, 3]
            az = np.mod(np.arctan2(p0[:, 1], p0[:, 0]), 2 * np.pi)
            # 1,800 firing columns per revolution: points of one column share a time
            col = np.floor(az / (2 * np.pi) * 1800).astype(np.int64)
            ti = t0 + col * (LIDAR_PERIOD_NS // 1800)
            T_wli = track.matrices(ti) @ T_el
            rel = invert_rigid(T_wli) @ T_wl0
            praw = np.einsum("nij,nj->ni", rel[:, :3, :3], p0) + rel[:, :3, 3]
            elev = np.degrees(np.arctan2(p0[:, 2], np.linalg.norm(p0[:, :2], axis=1)))
            ring = np.clip((elev + 25.0) / 40.0 * 31, 0, 31).astype(np.uint16)
            order = np.argsort(ti, kind="stable")
            for cols, pts in ((raw_cols, praw), (desk_cols, p0)):
                if cols is desk_cols and k in skip_deskewed_frames and \
                        skip_deskewed_agent in (None, agent):
                    continue  # what the deskew stage does with a scan the INS does not cover
                cols["frame_idx"].append(np.full(len(order), k, np.int32))
                cols["t_ns"].append(ti[order])
                cols["x"].append(pts[order, 0])
                cols["y"].append(pts[order, 1])
                cols["z"].append(pts[order, 2])
                cols["intensity"].append(inten[order])
                cols["ring"].append(ring[order])
            frames.append(dict(clip_id=clip_id, agent_id=agent, sensor="LIDAR_TOP",
                               frame_idx=k, stamp_ns=t0, t_start_ns=t0,
                               t_end_ns=int(ti.max()), n_points=len(p0), n_nan=0))
            # annotations: world boxes at t0 in the LiDAR frame at t0
            for obj in OBJECTS:
                tso = (t0 - T0_NS) / 1e9
                if np.linalg.norm(obj.center(tso)[:2] - T_wl0[:2, 3]) > 40.0:
                    continue
                B = inv0 @ obj.matrix(tso)
                q = matrix_to_quat(B[:3, :3])
                v = inv0[:3, :3] @ np.array([*obj.velocity_xy, 0.0])
                w, l, h = obj.wlh
                ann_rows.append(dict(
                    clip_id=clip_id, agent_id=agent, sensor="LIDAR_TOP", frame_idx=k,
                    t_ns=t0, instance_id=obj.instance_id, category=obj.category,
                    cx=B[0, 3], cy=B[1, 3], cz=B[2, 3], w=w, l=l, h=h, qw=q[0], qx=q[1],
                    qy=q[2], qz=q[3], vx=v[0], vy=v[1], vz=v[2], links=list(obj.links)))
                rec = inst.setdefault(obj.instance_id, dict(
                    clip_id=clip_id, instance_id=obj.instance_id, category=obj.category,
                    n_annotations=0, agents=[], first_t_ns=t0, last_t_ns=t0,
                    links=list(obj.links)))
                rec["n_annotations"] = int(rec["n_annotations"]) + 1  # type: ignore[call-overload]
                agents_seen = rec["agents"]
                assert isinstance(agents_seen, list)
                if agent not in agents_seen:
                    agents_seen.append(agent)
                rec["last_t_ns"] = max(int(rec["last_t_ns"]), t0)  # type: ignore[call-overload]
        lake.write_table("clean", "lidar_frames", rows_to_table(LAKE_TABLES["lidar_frames"],
                                                                frames),
                         clip_id=clip_id, agent_id=agent)
        if with_deskewed:  # what the deskew stage records per frame, in its own table
            deskewed = {int(f) for f in np.concatenate(desk_cols["frame_idx"])} \
                if desk_cols["frame_idx"] else set()
            lake.write_table("clean", "deskew_frames", rows_to_table(
                LAKE_TABLES["deskew_frames"],
                [dict(clip_id=clip_id, agent_id=agent, sensor="LIDAR_TOP",
                      frame_idx=f["frame_idx"], n_uncovered=0,
                      deskew_ref_ns=f["t_start_ns"] if f["frame_idx"] in deskewed else None)
                 for f in frames]), clip_id=clip_id, agent_id=agent)
        tables = [("lidar_points", raw_cols)] + ([("lidar_points_deskewed", desk_cols)]
                                                  if with_deskewed else [])
        for name, cols in tables:
            c = {k: np.concatenate(v) for k, v in cols.items()}
            n = len(c["x"])
            t = _ctab("lidar_points", clip_id, agent, **dict(
                sensor=pa.array(["LIDAR_TOP"] * n).dictionary_encode(), **c,
                return_id=np.zeros(n, np.uint8)))
            lake.write_table("clean", name, t,
                             clip_id=clip_id, agent_id=agent, row_group_by="frame_idx")
        if with_cameras:
            cam_rows = []
            n_cam = round(seconds * 30)
            for k in range(n_cam):
                stamp = T0_NS + round(k * 1e9 / 30)
                png = _render(track, stamp, weather, rng, rays)
                key = lake.blob_key(clip_id, agent, "CAM_FRONT", k)
                lake.write_blob("clean", key, png)
                import hashlib

                cam_rows.append(dict(clip_id=clip_id, agent_id=agent, sensor="CAM_FRONT",
                                     frame_idx=k, stamp_ns=stamp, width=CAM_W, height=CAM_H,
                                     blob=key, sha256=hashlib.sha256(png).hexdigest(),
                                     anonymizer="none", n_blurred=0))
            lake.write_table("clean", "camera_frames",
                             rows_to_table(LAKE_TABLES["camera_frames"], cam_rows),
                             clip_id=clip_id, agent_id=agent)
    lake.write_table("clean", "annotations", rows_to_table(LAKE_TABLES["annotations"],
                                                           ann_rows), clip_id=clip_id)
    lake.write_table("clean", "instances", rows_to_table(LAKE_TABLES["instances"],
                                                         list(inst.values())), clip_id=clip_id)
    if with_deskewed:  # what the pipeline does next: annotate counts the points per box
        from v2xlake.tasks.annotate.stage import run_annotate

        run_annotate(lake, clip_id)


def world_box_at(instance_id: str, t_ns: int) -> np.ndarray:
    obj = next(o for o in OBJECTS if o.instance_id == instance_id)
    return obj.matrix((t_ns - T0_NS) / 1e9)


def quat_matrix(q: list[float]) -> np.ndarray:
    return quat_to_matrix(np.asarray(q))


def pose_matrix(xyz: np.ndarray, q: np.ndarray) -> np.ndarray:
    return pose_matrices(xyz, q)[0]


def agent_track(agent: str, x_offset: float = 0.0, seconds: float = 2.0) -> PoseTrack:
    pose_t = np.arange(T0_NS - 2 * POSE_PERIOD_NS,
                       T0_NS + round(seconds * 10) * LIDAR_PERIOD_NS + 12 * POSE_PERIOD_NS,
                       POSE_PERIOD_NS, dtype=np.int64)
    lateral = {"red": 0.0, "black": -3.5}[agent]
    start = x_offset - (12.0 if agent == "black" else 0.0)
    xyz, quat = ego_state(start + SPEED * (pose_t - T0_NS) / 1e9, lateral)
    return PoseTrack.create(pose_t, xyz, quat)


def render_pinhole(agent: str, t_ns: int, K: np.ndarray) -> np.ndarray:
    """The overcast street through an ideal pinhole camera K (OpenCV pixel centres)."""
    u, v = np.meshgrid(np.arange(CAM_W) + 0.0, np.arange(CAM_H) + 0.0)
    rays = np.linalg.solve(K, np.stack([u.ravel(), v.ravel(), np.ones(u.size)])).T
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    png = _render(agent_track(agent), t_ns, "overcast", np.random.default_rng(0), rays)
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    assert img is not None
    return img


def run_stages(lake: Lake, clip_dir: Path, needed: tuple[str, ...]) -> str:
    """Run the flow's stages named in ``needed`` (in pipeline order, default parameters) on
    a clip folder, directly (no Prefect); each must be done. Returns the clip id."""
    from v2xlake.flows.pipeline import STAGES

    cid: str | None = None
    for stage in STAGES:
        if stage.name not in needed:
            continue
        rep = stage.run(lake, str(clip_dir) if stage.name == "ingest" else str(cid),
                        stage.config_model())
        assert rep.status == "done", (stage.name, rep.reason)
        cid = rep.clip_id
    assert cid is not None
    return cid
