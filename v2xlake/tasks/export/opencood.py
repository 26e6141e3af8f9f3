"""OpenCOOD / V2V4Real layout: ``<split>/<scenario>/<agent int>/%06d.yaml`` + ``%06d.pcd``.

What the V2V4Real loader expects, and why each choice here:

* agent folders are integers, "cav ids": vehicles ``0, 1, ...`` (the clip's reference agent
  first when it is a vehicle) and roadside units ``-1, -2, ...``, as V2XSet marks
  infrastructure. OpenCOOD's ``BaseDataset`` lists the folders -- sorted when
  ``train=False``, shuffled when ``train=True`` (V2V4Real / v2x-vit) -- then moves the first
  one to the end if its id is negative ("roadside unit data's id is always negative ... they
  shouldn't be ego vehicle"), and makes the first of the list the ego. So with
  ``train=False`` the ego is the reference vehicle ``0`` when the clip has at most one
  roadside unit (with two, sorted names are "-1", "-2", "0": only "-1" moves and "-2"
  becomes the ego); with ``train=True`` the ego is a random agent per scenario, as the
  loader intends. ``<clip>.json`` next to the scenario folders maps the numbers back to
  agent ids and names ``loader_ego``, the agent a sorted (``train=False``) loader takes;
  a clip where that is not the reference agent gets a report note;
* every agent has the same file names (the loader indexes timestamps on the ego only), so
  frame ``%06d`` is the reference agent's LiDAR frame index and the other agents contribute
  their scan nearest in time;
* ``lidar_pose``: ``T_world_lidar`` at scan start in the clip world frame, written as
  ``[x, y, z, roll, yaw, pitch]`` (degrees, OpenCOOD's ``x_to_world`` convention): the form
  that the published pose path takes as it is — ``load_yaml`` (plain ``yaml.Loader``) gives
  a list, ``x1_to_x2`` turns a list into a matrix through ``x_to_world`` (a nested 4x4 list
  would crash it: only an ndarray is taken as a matrix), ``dist_two_pose`` subtracts the
  first two entries. The exact 4x4 is kept beside it as ``lidar_pose_matrix``. For a
  cooperative agent with an accepted registration (eq. 1b) the pose is
  ``T_world_lidar_ref @ T_L1_L2`` so that fusing uses the refined relative transform;
  ``pose_source`` ("registered" / "ins" / "reference") and ``pose_source_reason`` say which
  one a frame got (``v2xlake.tasks.reader.relative_transform``); the loader ignores them;
* ``vehicles`` are in the agent's own LiDAR frame at t0 (as V2V4Real annotates): ``location``
  = box centre, ``center`` = 0, ``angle`` = [roll, yaw, pitch] in degrees in OpenCOOD's
  ``x_to_world`` convention, ``extent`` = half (l, w, h), ``ass_id`` = one integer per global
  instance id, shared across agents;
* several LiDARs on one agent (issue #27): OpenCOOD has one LiDAR per agent, so with
  ``merge_lidars`` each frame's PCD is the agent's merged cloud in its primary LiDAR's frame
  at t0: every other LiDAR's deskewed scan nearest in time (within ``merge_tolerance_ms``)
  moved by ``T_world_primary(t0)^-1 @ T_world_other(t_other)`` -- the effective extrinsics
  (register's refined ones where usable) and the ego motion between the two scans' instants
  -- and appended; ``lidars`` in the YAML says which scan of which LiDAR, with which
  calibration, gave how many of the points (the loader ignores it);
* PCD: the deskewed points in the LiDAR frame at t0, intensity in the colour channel (the
  loader reads ``np.asarray(pcd.colors)[:, 0]``; a plain ``x y z intensity`` PCD crashes it).
  Open3D stores colours as 8-bit RGB, so intensity is quantised to 1/255.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import open3d as o3d
import yaml
from pydantic import BaseModel, ConfigDict

from v2xlake.schemas.errors import ClipError
from v2xlake.schemas.stage import StageReport
from v2xlake.storage.lake import Lake
from v2xlake.storage.reader import PointFrame, available_frames, iter_point_frames
from v2xlake.tasks.export.common import file_output, report_step
from v2xlake.tasks.geometry import apply, invert
from v2xlake.tasks.reader import (
    AgentData,
    ClipData,
    boxes_matrices,
    lidar_world_poses,
    load_clip,
    match_agents,
    nearest_index,
    relative_transform,
)

ROADSIDE = "roadside"  # the agents table's kind of an infrastructure unit (schemas.clip)


class OpenCoodConfig(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")

    lidar_sensor: str = "LIDAR_TOP"
    default_split: str = "train"
    intensity_scale: float | None = None  # None: divide by 255 if intensities exceed 1
    match_tolerance_ms: float = 50.0
    use_registrations: bool = True
    # issue #27: append the agent's other LiDARs' scans to the primary one's, in its frame
    merge_lidars: bool = True
    merge_tolerance_ms: float = 50.0


def matrix_to_opencood_angles(R: np.ndarray) -> list[float]:
    """[roll, yaw, pitch] degrees that OpenCOOD's ``x_to_world`` turns back into ``R``."""
    pitch = math.asin(float(np.clip(R[2, 0], -1.0, 1.0)))
    roll = math.atan2(-float(R[2, 1]), float(R[2, 2]))
    yaw = math.atan2(float(R[1, 0]), float(R[0, 0]))
    return [math.degrees(roll), math.degrees(yaw), math.degrees(pitch)]


def matrix_to_opencood_pose(T: np.ndarray) -> list[float]:
    """``[x, y, z, roll, yaw, pitch]`` (degrees) of a 4x4 pose, as OpenCOOD's YAML carries it."""
    return [float(v) for v in T[:3, 3]] + matrix_to_opencood_angles(T[:3, :3])


def opencood_x_to_world(pose: Sequence[float]) -> np.ndarray:
    """OpenCOOD's ``transformation_utils.x_to_world`` ([x, y, z, roll, yaw, pitch] degrees)."""
    x, y, z, roll, yaw, pitch = pose
    c_y, s_y = math.cos(math.radians(yaw)), math.sin(math.radians(yaw))
    c_r, s_r = math.cos(math.radians(roll)), math.sin(math.radians(roll))
    c_p, s_p = math.cos(math.radians(pitch)), math.sin(math.radians(pitch))
    m = np.eye(4)
    m[0, 3], m[1, 3], m[2, 3] = x, y, z
    m[0, 0] = c_p * c_y
    m[0, 1] = c_y * s_p * s_r - s_y * c_r
    m[0, 2] = -c_y * s_p * c_r - s_y * s_r
    m[1, 0] = s_y * c_p
    m[1, 1] = s_y * s_p * s_r + c_y * c_r
    m[1, 2] = -s_y * s_p * c_r + c_y * s_r
    m[2, 0] = s_p
    m[2, 1] = -c_p * s_r
    m[2, 2] = c_p * c_r
    return m


def write_pcd(path: Path, xyz: np.ndarray, intensity01: np.ndarray) -> None:
    pcd = o3d.geometry.PointCloud()
    pcd.points = o3d.utility.Vector3dVector(np.asarray(xyz, dtype=np.float64))
    c = np.clip(np.asarray(intensity01, dtype=np.float64), 0.0, 1.0)
    pcd.colors = o3d.utility.Vector3dVector(np.repeat(c[:, None], 3, axis=1))
    written = o3d.io.write_point_cloud(str(path), pcd, write_ascii=False,  # type: ignore[arg-type]
                                       compressed=False)
    if not written:
        raise OSError(f"open3d could not write {path}")


@dataclass
class _Secondary:
    """Another LiDAR of an agent, streamed in frame order for merging (the primary's frames
    arrive in order and the nearest-in-time scan of this one never goes backwards)."""

    sensor: str
    t_ns: np.ndarray  # points_t_ns of the usable frames, sorted
    frame_idx: np.ndarray
    frames: Iterator[PointFrame]
    current: PointFrame | None = None

    def take(self, frame_idx: int) -> PointFrame | None:
        while self.current is None or self.current.frame_idx < frame_idx:
            nxt = next(self.frames, None)
            if nxt is None:
                return None
            self.current = nxt
        return self.current if self.current.frame_idx == frame_idx else None


def _secondaries(lake: Lake, clip_id: str, agent: AgentData, primary: str) -> list[_Secondary]:
    """The agent's other LiDARs that have a calibration, deskewed frames and pose coverage."""
    out = []
    for s in sorted(x for x in agent.lidar if x != primary):
        if s not in agent.sensors:
            continue
        lf = agent.lidar[s]
        have = available_frames(lake, clip_id, agent.agent_id, sensor=s)
        keep = agent.poses.covers(lf.points_t_ns) & np.isin(lf.frame_idx, list(have))
        if not keep.any():
            continue
        t, f = lf.points_t_ns[keep], lf.frame_idx[keep]
        o = np.argsort(t, kind="stable")
        fi = [int(x) for x in f[o]]
        out.append(_Secondary(s, t[o], f[o], iter_point_frames(
            lake, clip_id, agent.agent_id, sensor=s, frames=fi)))
    return out


def merge_lidars(agent: AgentData, clip_id: str, primary: str, t_primary_ns: int,
                 xyz: np.ndarray, intensity: np.ndarray, others: list[_Secondary],
                 tolerance_ns: float) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """The primary scan plus each other LiDAR's scan nearest ``t_primary_ns`` (within
    ``tolerance_ns``), moved into the primary LiDAR frame at ``t_primary_ns``:
    ``T_world_primary(t_p)^-1 @ T_world_other(t_o)`` (effective extrinsics, ego motion
    between the instants). Returns (xyz, intensity, what went in per LiDAR)."""
    parts, ints = [np.asarray(xyz, np.float64)], [np.asarray(intensity, np.float64)]
    info: dict[str, Any] = {primary: {
        "points": len(xyz), "calibration": agent.calibration_source.get(primary, "published"),
        "timestamp_ns": int(t_primary_ns)}}
    T_wp = lidar_world_poses(agent, primary, np.array([t_primary_ns]), clip_id)[0]
    for o in others:
        k = int(nearest_index(o.t_ns, t_primary_ns)[0])
        if abs(int(o.t_ns[k]) - int(t_primary_ns)) > tolerance_ns:
            continue
        fr = o.take(int(o.frame_idx[k]))
        if fr is None:
            continue
        T_ws = lidar_world_poses(agent, o.sensor, o.t_ns[k:k + 1], clip_id)[0]
        parts.append(apply(invert(T_wp) @ T_ws, fr.xyz.astype(np.float64)))
        ints.append(fr.intensity.astype(np.float64))
        info[o.sensor] = {"points": len(fr.xyz), "frame_idx": fr.frame_idx,
                          "calibration": agent.calibration_source.get(o.sensor, "published"),
                          "timestamp_ns": int(o.t_ns[k])}
    return np.concatenate(parts), np.concatenate(ints), info


def opencood_cav_ids(clip: ClipData) -> dict[str, int]:
    """Folder number per agent: vehicles 0, 1, ... in the clip's agent order (reference
    first), roadside units -1, -2, ... (V2XSet's convention, which the loader relies on to
    keep infrastructure from being the ego)."""
    vehicles = [aid for aid, a in clip.agents.items() if a.kind != ROADSIDE]
    rsus = [aid for aid, a in clip.agents.items() if a.kind == ROADSIDE]
    return {**{a: i for i, a in enumerate(vehicles)}, **{a: -1 - i for i, a in enumerate(rsus)}}


def opencood_loader_ego(cav_ids: Sequence[int]) -> int:
    """The cav id OpenCOOD's ``BaseDataset`` makes the ego with ``train=False``: the first
    sorted folder name, unless negative, in which case that one goes to the end."""
    names = sorted(str(c) for c in cav_ids)
    if int(names[0]) < 0:
        names = names[1:] + names[:1]
    return int(names[0])


def export_opencood(lake: Lake, clip_ids: Sequence[str], out_dir: Path | str,
                    splits: dict[str, str] | None = None,
                    config: OpenCoodConfig = OpenCoodConfig()) -> StageReport:  # noqa: B008
    root = Path(out_dir)
    report = StageReport(stage="export_opencood", clip_id=",".join(clip_ids))
    n_frames = n_boxes = 0
    for n_clip, cid in enumerate(clip_ids, start=1):
        clip = load_clip(lake, cid)
        split = (splits or {}).get(cid, config.default_split)
        scen = root / split / cid
        ref = clip.agents[clip.reference_agent]
        rs = ref.lidar_sensor(config.lidar_sensor)
        ref_frames = ref.lidar[rs]
        ref_t = ref_frames.points_t_ns
        gids = sorted(set(clip.instances["instance_id"].to_pylist())) \
            if clip.instances.num_rows else []
        for a in clip.agents.values():
            if a.annotations.num_rows:
                gids = sorted(set(gids) | set(a.annotations["instance_id"].to_pylist()))
        ass = {g: i for i, g in enumerate(gids)}
        agent_num = opencood_cav_ids(clip)
        ego_num = opencood_loader_ego(list(agent_num.values()))
        loader_ego = next(a for a, n in agent_num.items() if n == ego_num)
        if loader_ego != clip.reference_agent:
            report.notes.append(
                f"{cid}: OpenCOOD's sorted loader (train=False) takes {loader_ego} (folder "
                f"{ego_num}) as ego, not the reference agent {clip.reference_agent}")
        (scen).mkdir(parents=True, exist_ok=True)
        meta = {"agents": agent_num, "instances": ass,
                "reference_agent": clip.reference_agent, "loader_ego": loader_ego,
                "frames": {f"{int(f):06d}": int(t) for f, t in
                           zip(ref_frames.frame_idx, ref_t, strict=True)}}
        meta["note"] = "frames: reference LiDAR frame -> scan start (ns, relative time)"
        (root / split / f"{cid}.json").write_text(json.dumps(meta, indent=1))
        # the loader reads the same file names for every agent: keep only reference frames
        # that every agent can fill (a matching scan, pose coverage, deskewed points)
        have = {aid: available_frames(lake, cid, aid, sensor=a.lidar_sensor(config.lidar_sensor))
                for aid, a in clip.agents.items()}
        common, nears = match_agents(clip, ref_t, config.match_tolerance_ms * 1e6,
                                     sensor=config.lidar_sensor, have=have)
        if not common.any():
            raise ClipError(cid, "no LiDAR frame that every agent can provide",
                            stage="export_opencood")
        T_wl_ref = np.full((len(ref_t), 4, 4), np.nan)
        T_wl_ref[common] = lidar_world_poses(ref, rs, ref_t[common], cid)
        for aid, agent in clip.agents.items():
            sensor = agent.lidar_sensor(config.lidar_sensor)
            lf = agent.lidar[sensor]
            d = scen / str(agent_num[aid])
            d.mkdir(parents=True, exist_ok=True)
            near, ok = nears[aid], common
            want = {int(lf.frame_idx[near[k]]): k for k in np.flatnonzero(ok)}
            T_wl = lidar_world_poses(agent, sensor, lf.points_t_ns[near[ok]], cid)
            T_by_frame = dict(zip([int(f) for f in lf.frame_idx[near[ok]]], T_wl, strict=True))
            ann = agent.annotations
            others = _secondaries(lake, cid, agent, sensor) if config.merge_lidars else []
            for j, fr in enumerate(iter_point_frames(lake, cid, aid, sensor=sensor,
                                                     frames=list(want)), start=1):
                report_step(f"opencood {cid}/{aid}: frames", j, len(want))
                k = want[fr.frame_idx]
                ref_fi = int(ref_frames.frame_idx[k])
                name = f"{ref_fi:06d}"
                T = T_by_frame[fr.frame_idx]
                rel = relative_transform(clip, aid, ref_fi,
                                         use_registration=config.use_registrations)
                if rel.T is not None:
                    T = T_wl_ref[k] @ rel.T
                t_p = int(lf.points_t_ns[lf.frame_idx == fr.frame_idx][0])
                xyz, inten, lidars = merge_lidars(
                    agent, cid, sensor, t_p, fr.xyz, fr.intensity, others,
                    config.merge_tolerance_ms * 1e6)
                scale = config.intensity_scale if config.intensity_scale is not None else (
                    255.0 if inten.size and float(inten.max()) > 1.0 else 1.0)
                write_pcd(d / f"{name}.pcd", xyz, inten / scale)
                vehicles: dict[int, dict[str, object]] = {}
                if ann.num_rows:
                    a = ann.filter(ann["frame_idx"].to_numpy() == fr.frame_idx)
                    if a.num_rows:
                        B = boxes_matrices(a)
                        for r, row in enumerate(a.to_pylist()):
                            vehicles[ass[row["instance_id"]]] = {
                                "angle": matrix_to_opencood_angles(B[r, :3, :3]),
                                "center": [0.0, 0.0, 0.0],
                                "extent": [row["l"] / 2, row["w"] / 2, row["h"] / 2],
                                "location": [float(v) for v in B[r, :3, 3]],
                                "obj_type": row["category"],
                                "ass_id": ass[row["instance_id"]],
                            }
                        n_boxes += a.num_rows
                doc = {"lidar_pose": matrix_to_opencood_pose(T),
                       "lidar_pose_matrix": [[float(v) for v in row] for row in T],
                       "vehicles": vehicles, "agent_id": aid,
                       "pose_source": rel.source, "pose_source_reason": rel.reason,
                       "timestamp_ns": t_p}
                if len(lidars) > 1:
                    doc["lidars"] = lidars
                yp = d / f"{name}.yaml"
                yp.write_text(yaml.safe_dump(doc, sort_keys=False))
                n_frames += 1
        report.outputs.append(file_output(root / split / f"{cid}.json"))
        report_step("opencood: clips", n_clip, len(clip_ids))
    report.metrics = {"frames": float(n_frames), "boxes": float(n_boxes)}
    return report
