"""Sensor rigs: true and published (mis-calibrated) extrinsics, camera intrinsics.

Frames: ``base_link`` = the agent's INS/IMU frame (body x forward, y left, z up, origin at the
body's geometric centre, 0.40 m above the ground for vehicles, on the ground at the mast for the
roadside unit). LiDAR frame ``<agent>/lidar``: x forward, y left, z up; azimuth 0 = +x, sweeping
clockwise seen from above (front -> right -> back -> left), as in CATS-V2V Fig. 6. Camera frames
``<agent>/cam_front`` ...: optical convention (z forward, x right, y down).

``T_ego_sensor`` maps points from the sensor frame into base_link. The TRUE extrinsic is the
nominal mount plus a small seeded mounting deviation; ``/tf_static`` publishes the true one
composed with a calibration error ``T_pub = T_true @ T_err`` whose translation has norm
``lidar_ext_trans_err_m`` and rotation angle ``lidar_ext_rot_err_deg`` (random directions), on
every agent or only on those named in ``lidar_ext_err_agents``. An explicit error
(``lidar_ext_err_xyz_m`` and/or ``lidar_ext_err_rpy_deg``, issue #21) replaces the random one and
is exact in base_link terms: ``t_pub = t_true + xyz`` and ``R_pub = Rz(yaw) Ry(pitch) Rx(roll)
@ R_true`` (a pure yaw error adds exactly that angle to the extrinsic's yaw), so a test can
state "published minus true" without the mounting deviation leaking in. The random stream is
drawn either way, so the other numbers of a seed do not move.

``lidar_height_m`` sets the vehicles' nominal LiDAR height above the ground (the mount sits
``lidar_height_m - EGO_HEIGHT`` above base_link); default 1.55 m above base_link (1.95 m).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from v2xlake.schemas.calibration import CameraIntrinsics, DistortionModel
from v2xlake.tasks.geometry import rigid
from v2xlake.tasks.simulate.config import SimConfig
from v2xlake.tasks.simulate.scene import EGO_HEIGHT

# name: (yaw deg, hfov deg, base width, base height red, base height black, x, y, z) with x y z
# the mount position in base_link
_CAMS: dict[str, tuple[float, float, int, int, int, float, float, float]] = {
    "CAM_FRONT": (0.0, 120.0, 3840, 2160, 2160, 1.00, 0.0, 1.25),
    "CAM_FRONT_NARROW": (0.0, 30.0, 3840, 2160, 2160, 1.00, 0.15, 1.25),
    "CAM_BACK": (180.0, 70.0, 3840, 2160, 2160, -1.00, 0.0, 1.25),
    "CAM_FRONT_LEFT": (60.0, 100.0, 1920, 1080, 1536, 0.60, 0.70, 1.25),
    "CAM_BACK_LEFT": (125.0, 100.0, 1920, 1080, 1536, -0.50, 0.70, 1.25),
    "CAM_FRONT_RIGHT": (-60.0, 100.0, 1920, 1080, 1536, 0.60, -0.70, 1.25),
    "CAM_BACK_RIGHT": (-125.0, 100.0, 1920, 1080, 1536, -0.50, -0.70, 1.25),
}
_FRONT_DISTORTION = [-0.03, 0.004, 0.0002, -0.0001, 0.0]


def frame_name(agent: str, sensor: str) -> str:
    """tf frame of a sensor: LIDAR_TOP -> red/lidar, CAM_FRONT -> red/cam_front."""
    if sensor == "LIDAR_TOP":
        return f"{agent}/lidar"
    return f"{agent}/{sensor.lower()}"


def _cam_rotation(yaw_deg: float, pitch_down_deg: float) -> np.ndarray:
    y = np.radians(yaw_deg)
    z = np.array([np.cos(y), np.sin(y), 0.0])
    x = np.array([np.sin(y), -np.cos(y), 0.0])
    r0 = np.column_stack([x, np.cross(z, x), z])
    return r0 @ Rotation.from_euler("x", -np.radians(pitch_down_deg)).as_matrix()


def _error(rng: np.random.Generator, trans: float, rot_deg: float) -> np.ndarray:
    def unit() -> np.ndarray:
        v = rng.normal(size=3)
        return v / np.linalg.norm(v)
    return rigid(Rotation.from_rotvec(unit() * np.radians(rot_deg)).as_matrix(), unit() * trans)


def explicit_error(T_true: np.ndarray, xyz: tuple[float, float, float] | None,
                   rpy_deg: tuple[float, float, float] | None) -> np.ndarray:
    """``T_pub`` for an explicit error: translation ``t_true + xyz`` (base_link axes) and
    rotation ``Rz(yaw) Ry(pitch) Rx(roll) @ R_true``."""
    r, p, y = np.radians(rpy_deg or (0.0, 0.0, 0.0))
    R_err = Rotation.from_euler("ZYX", [y, p, r]).as_matrix()
    return rigid(R_err @ T_true[:3, :3], T_true[:3, 3] + np.asarray(xyz or (0.0, 0.0, 0.0)))


@dataclass(frozen=True)
class CameraRig:
    name: str
    intrinsics: CameraIntrinsics
    T_ego_cam_true: np.ndarray
    T_ego_cam_pub: np.ndarray


@dataclass(frozen=True)
class AgentRig:
    agent: str
    T_ego_lidar_true: np.ndarray
    T_ego_lidar_pub: np.ndarray
    cameras: dict[str, CameraRig]
    # the optional second LiDAR (SimConfig.side_lidar): true and published T_ego_lidar_left
    T_ego_side_true: np.ndarray | None = None
    T_ego_side_pub: np.ndarray | None = None


def build_rigs(cfg: SimConfig) -> dict[str, AgentRig]:
    rigs: dict[str, AgentRig] = {}
    for k, agent in enumerate(cfg.agents):
        rng = np.random.default_rng([cfg.seed, 777, k])
        if agent == "rsu":
            lid_nom = rigid(np.eye(3), np.array([0.0, 0.0, 5.5]))
            cams_for = [c for c in ("CAM_FRONT",) if c in cfg.cameras]
        else:
            z = 1.55 if cfg.lidar_height_m is None else cfg.lidar_height_m - EGO_HEIGHT
            lid_nom = rigid(np.eye(3), np.array([0.20, 0.0, z]))
            cams_for = list(cfg.cameras)
        mount = rigid(Rotation.from_rotvec(rng.normal(size=3) * np.radians(0.3)).as_matrix(),
                     rng.normal(size=3) * 0.02)
        lid_true = lid_nom @ mount
        wrong = cfg.lidar_ext_err_agents is None or agent in cfg.lidar_ext_err_agents
        # the error is drawn for every agent (same random stream), applied to the chosen ones
        err = _error(rng, cfg.lidar_ext_trans_err_m, cfg.lidar_ext_rot_err_deg)
        if not wrong:
            lid_pub = lid_true.copy()
        elif cfg.lidar_ext_err_xyz_m is not None or cfg.lidar_ext_err_rpy_deg is not None:
            lid_pub = explicit_error(lid_true, cfg.lidar_ext_err_xyz_m, cfg.lidar_ext_err_rpy_deg)
        else:
            lid_pub = lid_true @ err
        cams: dict[str, CameraRig] = {}
        for name in cams_for:
            yaw, hfov, bw, bh_red, bh_black, x, y, z = _CAMS[name]
            bh = bh_black if agent == "black" else bh_red
            w = cfg.image_width or bw
            h = round(bh * w / bw)
            fx = (w / 2) / np.tan(np.radians(hfov) / 2)
            dist = _FRONT_DISTORTION if name == "CAM_FRONT" else [0.0] * 5
            intr = CameraIntrinsics(
                width=w, height=h, fx=float(fx), fy=float(fx),
                cx=w / 2 + 0.0013 * w, cy=h / 2 - 0.0011 * h,
                distortion_model=DistortionModel.PLUMB_BOB, distortion=list(dist),
            )
            if agent == "rsu":
                r, t = _cam_rotation(0.0, 12.0), np.array([0.3, 0.0, 5.3])
            else:
                r, t = _cam_rotation(yaw, 2.0), np.array([x, y, z])
            cmount = rigid(Rotation.from_rotvec(rng.normal(size=3) * np.radians(0.2)).as_matrix(),
                          rng.normal(size=3) * 0.01)
            c_true = rigid(r, t) @ cmount
            c_pub = c_true @ _error(rng, cfg.cam_ext_trans_err_m, cfg.cam_ext_rot_err_deg)
            cams[name] = CameraRig(name, intr, c_true, c_pub)
        side_true = side_pub = None
        if cfg.side_lidar and agent != "rsu":  # no random draws: the rest stays identical
            side_true = rigid(Rotation.from_euler(
                "ZYX", cfg.side_lidar_mount_rpy_deg[::-1], degrees=True).as_matrix(),
                np.array(cfg.side_lidar_mount_xyz_m))
            side_pub = explicit_error(side_true, cfg.side_lidar_err_xyz_m,
                                      cfg.side_lidar_err_rpy_deg)
        rigs[agent] = AgentRig(agent, lid_true, lid_pub, cams, side_true, side_pub)
    return rigs
