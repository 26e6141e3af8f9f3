"""A clip's guidance for the anonymizer: every agent's object boxes in the clip world and
every camera's pose, from what ingest wrote (anonymize runs before deskew and registration).

Poses are the clean ``ego_poses`` the stage has just computed from the raw pose source (local
ENU, relative time); calibration, LiDAR frames and annotations are the raw tables. A box is
in its LiDAR's frame at the scan start (``lidar_frames.t_start_ns``, the convention of the
annotate stage) and describes the object at its own ``t_ns``; it is moved to each image's
time with its velocity. Boxes of other agents fill in objects this agent's LiDAR did not see
(cooperative perception is what the recording is for), the agent's own boxes win.

Without boxes (no annotation file), the boxes are LiDAR clusters (``clusters.py``).
Pure: the stage (``stage.py``) reads the tables and parses poses and calibration; this module
assembles the guide from them.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import pyarrow as pa

from v2xlake.schemas.calibration import CameraIntrinsics, DistortionModel
from v2xlake.tasks.anonymize.guide import (
    PEOPLE,
    GuideConfig,
    Region,
    WorldBoxes,
    band_region,
    ground_height,
    project_regions,
    world_boxes_from_sensor,
)
from v2xlake.tasks.anonymize.timespace import T0_OFFSET_NS
from v2xlake.tasks.geometry import invert
from v2xlake.tasks.interpolate import PoseTrack

if TYPE_CHECKING:
    from v2xlake.storage.reader import CameraCalib


@dataclass
class ClipGuide:
    """Pose tracks, cameras and world boxes of one clip; ``regions`` per image."""

    config: GuideConfig
    tracks: dict[str, PoseTrack] = field(default_factory=dict)
    cameras: dict[tuple[str, str], tuple[np.ndarray, CameraIntrinsics]] = field(
        default_factory=dict)  # (agent, sensor) -> T_ego_cam, intrinsics
    boxes: dict[str, WorldBoxes] = field(default_factory=dict)  # per agent that saw them
    source: str = "none"  # "annotations" | "lidar clusters" | "none"
    t0_abs: int = 0

    def rel(self, stamp_abs: int) -> int:
        return int(stamp_abs) - self.t0_abs + T0_OFFSET_NS

    def regions(self, agent: str, sensor: str, stamp_abs: int) -> list[Region] | None:
        """Regions of one image; None when this image cannot be guided (no pose at its time,
        no calibrated camera, no boxes in the clip): it gets the full-frame plan."""
        track = self.tracks.get(agent)
        cam = self.cameras.get((agent, sensor))
        if track is None or cam is None or not self.boxes:
            return None
        t = self.rel(stamp_abs)
        if not bool(track.covers(t)):
            return None
        T_ego_cam, intr = cam
        T_cam_world = invert(track.matrices(t)[0] @ T_ego_cam)
        own = self._at(self.boxes[agent], t, agent) if agent in self.boxes else None
        seen = set(own.instance.tolist()) if own is not None else set()
        parts = [own] if own is not None else []
        for other, b in self.boxes.items():
            if other == agent:
                continue
            ob = self._at(b, t, other)
            keep = ~np.isin(ob.instance, list(seen)) if seen else np.ones(len(ob), bool)
            parts.append(ob.take(keep))
            seen |= set(ob.instance[keep].tolist())
        regions = project_regions(WorldBoxes.concat(parts), T_cam_world, intr, self.config,
                                  self.source == "lidar clusters")
        if self.source == "lidar clusters" and self.config.band_from_m > 0:
            T_world_ego = track.matrices(t)[0]
            if own is not None and len(own):  # the nearest scan's, without held persons
                own = own.take(own.t_ns == own.t_ns[np.argmin(np.abs(own.t_ns - t))])
            ground = ground_height(own, T_world_ego, self.config.band_from_m)
            band = band_region(T_cam_world, T_world_ego, intr, ground, self.config)
            if band is not None:
                regions.append(band)
        return regions


    def _at(self, b: WorldBoxes, t: int, agent: str = "") -> WorldBoxes:
        """Boxes at time ``t``: annotated instances moved by their velocity; LiDAR clusters
        (no velocity; their track numbers, ``clusters.track_ids``, let carrying pair them) from
        the one scan nearest in time, plus the
        person boxes of the scans within ``person_hold_ns``. Why persons: far away a sparse
        LiDAR puts its few returns on a walker in some sweeps only (4, 0, 4 returns in three
        sweeps of a simulated pedestrian 32 m away), and the frames nearest an empty sweep
        got no head region; a walker moves 0.2 m in 150 ms, inside the region's margins
        (a car 2 m: its boxes are not held). Only persons farther than ``person_hold_from_m``
        from ``agent`` (whose LiDAR saw them) are held: nearer ones have returns in every
        sweep), and only where the nearest scan has no person within ``person_hold_gap_m``
        (the same walker seen again)."""
        if self.source == "lidar clusters" and len(b):
            dt = np.abs(b.t_ns - t)
            near = b.t_ns[np.argmin(dt)]
            if abs(int(near) - t) > self.config.max_age_ns:
                return b.take(np.zeros(len(b), bool))
            keep = b.t_ns == near
            if self.config.person_hold_ns > 0:
                held = ~keep & (dt <= self.config.person_hold_ns) & np.isin(b.category,
                                                                            list(PEOPLE))
                track = self.tracks.get(agent)
                if held.any() and track is not None and self.config.person_hold_from_m > 0:
                    idx = np.flatnonzero(held)
                    ok = np.asarray(track.covers(b.t_ns[idx]), bool)
                    seen_from = track.matrices(b.t_ns[idx[ok]])[:, :2, 3]
                    far = np.zeros(len(idx), bool)
                    far[ok] = np.hypot(*(b.center[idx[ok], :2] - seen_from).T) \
                        > self.config.person_hold_from_m
                    held[idx[~far]] = False
                now = keep & np.isin(b.category, list(PEOPLE))
                if held.any() and now.any():  # the nearest scan saw it again: no need
                    idx = np.flatnonzero(held)
                    gap = np.hypot(b.center[idx, None, 0] - b.center[now][None, :, 0],
                                   b.center[idx, None, 1] - b.center[now][None, :, 1])
                    held[idx[gap.min(1) < self.config.person_hold_gap_m]] = False
                keep |= held
            return b.take(keep)
        return b.at(t, self.config.max_age_ns)


def camera_intrinsics(c: CameraCalib) -> CameraIntrinsics | None:
    """A calibrated camera's intrinsics, None when its distortion model is unknown."""
    try:
        model = DistortionModel(c.distortion_model or "none")
        dist = list(c.distortion) if model is not DistortionModel.NONE else []
        return CameraIntrinsics(width=c.width, height=c.height, fx=float(c.K[0, 0]),
                                fy=float(c.K[1, 1]), cx=float(c.K[0, 2]), cy=float(c.K[1, 2]),
                                distortion_model=model, distortion=dist)
    except ValueError:
        return None


def assemble_guide(t0_abs: int, tracks: dict[str, PoseTrack],
                   cameras: dict[tuple[str, str], tuple[np.ndarray, CameraIntrinsics]],
                   extrinsics: dict[str, dict[str, np.ndarray]], annotations: pa.Table,
                   lidar_frames: pa.Table, config: GuideConfig,
                   clusters: dict[str, WorldBoxes] | None = None) -> ClipGuide:
    """The guide from each agent's pose track, its cameras (``T_ego_cam``, intrinsics), every
    sensor's ``T_ego_sensor`` (``extrinsics``: where annotation boxes are given), and the raw
    annotations and LiDAR frames; LiDAR clusters when the clip has no annotations."""
    g = ClipGuide(config, t0_abs=int(t0_abs), tracks=dict(tracks), cameras=dict(cameras))
    if annotations.num_rows:
        g.boxes = _annotation_boxes(annotations, lidar_frames, g, extrinsics, t0_abs)
        g.source = "annotations"
    elif clusters:
        g.boxes = clusters
        g.source = "lidar clusters"
        g.config = dataclasses.replace(
            config, plate_z_m=(min(config.cluster_plate_z0_m, config.plate_z_m[0]),
                               config.plate_z_m[1]))
    return g


def _annotation_boxes(ann: pa.Table, frames: pa.Table, g: ClipGuide,
                      sensors: dict[str, dict[str, np.ndarray]], t0_abs: int
                      ) -> dict[str, WorldBoxes]:
    """Each agent's annotation rows as world boxes (rows outside its pose coverage dropped)."""
    start: dict[tuple[str, str, int], int] = {}
    if frames.num_rows:
        fd = frames.select(["agent_id", "sensor", "frame_idx", "t_start_ns"]).to_pydict()
        start = {(a, s, int(f)): int(t) for a, s, f, t in zip(
            fd["agent_id"], fd["sensor"], fd["frame_idx"], fd["t_start_ns"], strict=True)}
    d = ann.to_pydict()
    shift = T0_OFFSET_NS - int(t0_abs)

    def col(name: str, rows: np.ndarray) -> np.ndarray:
        if name not in d:
            return np.full(len(rows), np.nan)
        return np.asarray([np.nan if d[name][i] is None else d[name][i] for i in rows], float)

    out: dict[str, WorldBoxes] = {}
    agent = np.asarray(d["agent_id"]).astype(str)
    for a in map(str, np.unique(agent)):
        track, cal = g.tracks.get(a), sensors.get(a, {})
        if track is None:
            continue
        rows = np.flatnonzero(agent == a)
        rows = rows[[d["sensor"][i] in cal for i in rows]]
        t_frame = np.array([start.get((a, d["sensor"][i], int(d["frame_idx"][i])),
                                      int(d["t_ns"][i])) for i in rows], np.int64) + shift
        ok = np.asarray(track.covers(t_frame), bool)
        rows, t_frame = rows[ok], t_frame[ok]
        if not len(rows):
            continue
        T_sensor = np.stack([cal[d["sensor"][i]] for i in rows])
        out[a] = world_boxes_from_sensor(
            np.array([int(d["t_ns"][i]) for i in rows], np.int64) + shift,
            track.matrices(t_frame) @ T_sensor,
            np.stack([col("cx", rows), col("cy", rows), col("cz", rows)], 1),
            np.stack([col("w", rows), col("l", rows), col("h", rows)], 1),
            np.stack([col(c, rows) for c in ("qw", "qx", "qy", "qz")], 1),
            np.stack([col("vx", rows), col("vy", rows), col("vz", rows)], 1),
            np.asarray([d["category"][i] for i in rows]).astype(str),
            np.asarray([d["instance_id"][i] for i in rows]).astype(str))
    return out
