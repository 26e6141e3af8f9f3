"""A front 4D imaging radar (``SimConfig.radar``): detections with radial velocity and RCS.

Geometry comes from the same ray caster as the LiDAR (``lidar.LidarCaster``) with a coarse
radar-like beam pattern (6 elevation rows from -4 to +8 deg, 1 deg azimuth, 150 m range,
20 Hz) mounted in the front bumper; only hits inside the radar's +-60 deg field of view and
off the ground are detections. Each detection is reported in the radar frame at the scan
stamp (one time per scan, as automotive radars do), with

- radial velocity ``v_r = (v_target - v_sensor) . u`` along the line of sight ``u`` at the
  moment of the hit (``v_target`` from the actor's box motion, zero for static objects,
  ``v_sensor`` of the radar's own origin), positive away from the sensor; exact, no noise;
- RCS in dBsm by what was hit (vehicles 10-20, pedestrians -8, cyclists -3, buildings and
  fences 15, poles 5) plus seeded Gaussian noise of 1 dB.

Written as ``sensor_msgs/PointCloud2`` with float32 fields x y z v_r rcs (a Continental
ARS548-like layout), the layout ``docs/recordings.md`` describes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from v2xlake.schemas.annotation import ObjectClass
from v2xlake.tasks.geometry import rigid
from v2xlake.tasks.simulate.config import LidarSpec
from v2xlake.tasks.simulate.lidar import LidarCaster
from v2xlake.tasks.simulate.scene import GROUND_ID, World

RADAR_SPEC = LidarSpec(beams=6, columns=360, rate_hz=20.0, elev_min_deg=-4.0,
                       elev_max_deg=8.0, max_range_m=150.0, min_range_m=0.5,
                       dual_return=False)
T_EGO_RADAR = rigid(np.eye(3), np.array([2.35, 0.0, 0.10]))  # front bumper, base_link 0.4 m up
FOV_DEG = 60.0
RADAR_DTYPE = np.dtype({"names": ["x", "y", "z", "v_r", "rcs"], "formats": ["<f4"] * 5,
                        "offsets": [0, 4, 8, 12, 16], "itemsize": 20})
RADAR_FIELDS = [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("v_r", 12, 7), ("rcs", 16, 7)]
_RCS = {ObjectClass.CAR: 10.0, ObjectClass.VAN: 12.0, ObjectClass.TRUCK: 20.0,
        ObjectClass.TRAILER: 18.0, ObjectClass.BUS: 20.0, ObjectClass.PEDESTRIAN: -8.0,
        ObjectClass.BICYCLE: -3.0, ObjectClass.SCOOTER: -3.0, ObjectClass.MOTORCYCLE: 2.0}
_RCS_STATIC, _RCS_POLE, _RCS_OTHER = 15.0, 5.0, 0.0


@dataclass
class RadarScan:
    stamp_ns: int
    points: np.ndarray  # RADAR_DTYPE, radar frame at ``stamp_ns``


class RadarSim:
    """Front radar of one agent."""

    def __init__(self, world: World, agent: str, start_ns: int, seed: int) -> None:
        self.caster = LidarCaster(world, agent, T_EGO_RADAR, RADAR_SPEC, start_ns, seed + 4242)
        self.rng = np.random.default_rng([seed, 4243])
        sc = world.scene
        self.rcs = np.full(len(sc.names), _RCS_STATIC)
        self.rcs[sc.cy_id0:sc.actor_id0] = _RCS_POLE
        self.actor_of = np.full(len(sc.names), -1)
        for k, (i, act) in enumerate(self.caster.actors):
            self.rcs[sc.actor_id(i)] = _RCS.get(act.category, _RCS_OTHER)
            self.actor_of[sc.actor_id(i)] = k

    def scan(self, k: int) -> RadarScan:
        c = self.caster
        s = c.cast(k)
        st = c.last
        col = np.searchsorted(st.t_ns, s.t_ns)
        az = 2 * np.pi * col / RADAR_SPEC.columns  # clockwise from the radar's +x
        fov = np.radians(FOV_DEG)
        keep = (s.obj_id != GROUND_ID) & ((az <= fov) | (az >= 2 * np.pi - fov))
        col, world, oid = col[keep], s.world[keep], s.obj_id[keep]
        o = st.origin[col]
        u = world - o
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        # the sensor's own velocity at each column, by central differences of its origin
        h = 1e-4
        tau = (st.t_ns - c.start_ns) / 1e9
        v_sensor = (c.lidar_poses(tau + h)[0] - c.lidar_poses(tau - h)[0]) / (2 * h)
        # a target's velocity from its box centre over the scan's columns
        dt = np.gradient((st.t_ns - st.t_ns[0]) / 1e9)
        v_actor = np.gradient(st.actor_center, axis=0) / dt[:, None, None] \
            if st.actor_center.shape[1] else np.zeros((len(st.t_ns), 0, 3))
        ka = self.actor_of[oid]
        v_target = np.zeros_like(world)
        moving = ka >= 0
        v_target[moving] = v_actor[col[moving], ka[moving]]
        v_r = np.einsum("ni,ni->n", v_target - v_sensor[col], u)
        # positions in the radar frame at the scan stamp (the first column's pose)
        xyz = (world - st.origin[0]) @ st.rot[0]
        pts = np.zeros(len(world), RADAR_DTYPE)
        pts["x"], pts["y"], pts["z"] = xyz.T
        pts["v_r"] = v_r
        pts["rcs"] = self.rcs[oid] + self.rng.normal(0.0, 1.0, len(world))
        return RadarScan(s.stamp_ns, pts)
