"""Ground truth of a simulated clip (``OUT/truth/``), and how to read it back.

NOT part of the input contract: stages never read it, tests and evaluations do.

World frame: ``LocalFrame(origin_lat, origin_lon)`` (local ENU, z = ellipsoidal height); the
red agent's TRUE INS position at the first PPS is (0, 0, z0) in it. The anonymizer builds its
world from the first REPORTED INS fix, which carries the red INS bias ``b_red(0)``: its origin is
shifted by that bias (xy; z keeps the ellipsoidal height), i.e.
``p_clean = p_truth + b_red_xy(0)`` up to ~1e-8 relative tangent-plane rotation; ``poses.parquet``
records the bias of every agent at every sample so tests can relate both.

Files:
* ``sim_config.json``: the SimConfig; ``load_truth`` rebuilds the analytic world from it, so
  :meth:`SimTruth.T_world_ego` is exact at ANY time (not interpolated).
* ``poses.parquet``: agent, t_ns (1 kHz, over the INS span: clip start to the last scan's end
  + ``run.NAV_TAIL_NS``), true ``T_world_ego`` (x y z qw qx qy qz), world velocity vx vy vz,
  INS position bias bx by bz (reported = true + bias).
* ``extrinsics.json``: per agent true and published ``T_ego_lidar`` / ``T_ego_cam`` (Transform
  dicts), camera intrinsics, INS attitude bias (roll, pitch, yaw rad; ``R_ins = R_bias R_true``)
  and position-bias parameters.
* ``relative.parquet``: per LiDAR frame (scan start t_ns) and agent pair (red <- other): the
  TRUE ``T_L1_L2`` and the eq. 1a estimate from the reported INS poses and published extrinsics
  (``init_*``), with their translation / rotation disagreement.
* ``boxes2d.parquet``: per image (agent, camera, frame_idx, stamp_ns) every object, face and
  plate with at least one pixel in the final image: kind, instance_id, visible box x0 y0 x1 y1
  (pixels, end exclusive) and n_pixels taken from the label images rendered with the colour
  (an occluder erases what it covers, see ``camera``), amodal box ax0..ay1,
  ``visible_fraction`` (visible / unoccluded pixels) and ``occluded`` (bool: fewer than
  ``camera.MIN_VISIBLE_PX`` pixels or a fraction under 0.5 for faces / plates, 0.1 for
  objects; consumers wanting "what an anonymizer must blur" should keep every row, those
  wanting "what a detector should find" should drop ``occluded`` ones), and for objects the
  agent's LiDAR frame whose sweep contains the image stamp with the mean point time of the
  object in it (lidar_frame_idx, lidar_n_pts, lidar_mean_t_ns; -1 when the LiDAR saw none).
* ``lidar_truth.parquet`` (when ``write_lidar_truth``): per LiDAR point in message order
  (agent, frame_idx, idx): t_ns, the true world hit point wx wy wz (before range noise),
  the object name hit and ``is_static``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

from v2xlake.schemas.geometry import Transform
from v2xlake.storage import files
from v2xlake.tasks.geometry import matrix_to_quat, rigid
from v2xlake.tasks.simulate.config import SimConfig
from v2xlake.tasks.simulate.ins import InsError, ins_error
from v2xlake.tasks.simulate.rig import AgentRig, build_rigs
from v2xlake.tasks.simulate.scene import World, build_world


def transform_dict(m: np.ndarray) -> dict[str, Any]:
    return Transform.from_matrix(m).model_dump()


def pose_columns(m: np.ndarray) -> dict[str, np.ndarray]:
    q = matrix_to_quat(m[:, :3, :3])
    return {"x": m[:, 0, 3], "y": m[:, 1, 3], "z": m[:, 2, 3],
            "qw": q[:, 0], "qx": q[:, 1], "qy": q[:, 2], "qz": q[:, 3]}


def write_parquet(path: Path, cols: dict[str, Any]) -> int:
    return files.write_parquet(path, pa.table(cols))


def ins_matrix(err: InsError, T_true: np.ndarray, tau: np.ndarray) -> np.ndarray:
    """What the INS reports as T_world_ego (world = truth world)."""
    return rigid(err.R_bias @ T_true[..., :3, :3], T_true[..., :3, 3] + err.bias(tau))


@dataclass
class SimTruth:
    clip_dir: Path
    cfg: SimConfig
    world: World
    rigs: dict[str, AgentRig]

    @property
    def start_ns(self) -> int:
        return self.cfg.start_s * 1_000_000_000

    def tau(self, t_ns: np.ndarray) -> np.ndarray:
        return (np.asarray(t_ns, np.int64) - self.start_ns) / 1e9

    def T_world_ego(self, agent: str, t_ns: np.ndarray) -> np.ndarray:
        """Exact true pose(s) (N, 4, 4) from the analytic trajectory."""
        return self.world.agents[agent].matrix(np.atleast_1d(self.tau(t_ns)))

    def T_ego_lidar(self, agent: str, published: bool = False) -> np.ndarray:
        r = self.rigs[agent]
        return r.T_ego_lidar_pub if published else r.T_ego_lidar_true

    def T_world_lidar(self, agent: str, t_ns: np.ndarray) -> np.ndarray:
        return self.T_world_ego(agent, t_ns) @ self.T_ego_lidar(agent)

    def T_world_ins(self, agent: str, t_ns: np.ndarray) -> np.ndarray:
        """The pose the INS reports (with its bias), in the truth world frame."""
        tau = np.atleast_1d(self.tau(t_ns))
        return ins_matrix(ins_error(self.cfg, agent), self.world.agents[agent].matrix(tau), tau)

    def ins_bias(self, agent: str, t_ns: np.ndarray) -> np.ndarray:
        return ins_error(self.cfg, agent).bias(self.tau(t_ns))

    def table(self, name: str) -> pa.Table:
        return files.read_parquet(self.clip_dir / "truth" / f"{name}.parquet")

    def extrinsics(self) -> dict[str, Any]:
        return json.loads((self.clip_dir / "truth" / "extrinsics.json").read_text())


def load_truth(clip_dir: str | Path) -> SimTruth:
    d = Path(clip_dir)
    cfg = SimConfig.model_validate_json((d / "truth" / "sim_config.json").read_text())
    return SimTruth(d, cfg, build_world(cfg), build_rigs(cfg))
