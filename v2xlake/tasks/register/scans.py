"""One agent's deskewed scans as registration uses them: frame by frame, voxel-downsampled
with each voxel's capture time, and reduced to the static scene (``static.py``) with counts of
what was removed.

Pure: ``AgentScans`` holds what ``stage.py`` read from the lake (pose track, extrinsic, frame
times, annotated boxes) and a ``FrameReader`` that hands over one frame's points when asked,
so a clip never has to fit in memory and this module never sees the lake. The numeric work
is in ``voxel.py`` and ``static.py``.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from v2xlake.tasks.geometry import apply, invert
from v2xlake.tasks.interpolate import PoseTrack
from v2xlake.tasks.register.config import StaticSection
from v2xlake.tasks.register.static import (
    MovingBoxes,
    RemovalCounts,
    above_ground,
    annotation_boxes,
    body_box,
    box_of_point,
    dynamic_mask,
    ground_distance,
    grow_to_objects,
    without_still,
)
from v2xlake.tasks.register.voxel import VoxelGrid, voxel_downsample_t

#: the other agent's body moves with its INS velocity over this step (ns) after the frame
_BODY_DT_NS = 20_000_000

#: one deskewed frame of one LiDAR: frame index -> ((N, 3) float32 points, (N,) int64 capture
#: times), empty arrays for a frame without points
FrameReader = Callable[[int], tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class Body:
    """An agent's declared footprint: box size and its centre in the ego frame."""

    length: float
    width: float
    height: float
    center_ego: tuple[float, float, float]


@dataclass
class FilteredScan:
    points: np.ndarray  # (M, 3) float64 voxel centroids of the static scene
    counts: RemovalCounts
    ground_m: float = float("nan")  # LiDAR origin to the ground plane around it


@dataclass(frozen=True)
class AnnotationColumns:
    """One LiDAR's annotated boxes as columns (one entry per box): frame, centre time,
    centre, size (w, l, h), rotation (w, x, y, z) and velocity (NaN where not given)."""

    frame_idx: np.ndarray  # (K,) int64
    t_ns: np.ndarray  # (K,) int64
    center: np.ndarray  # (K, 3) float64
    size_wlh: np.ndarray  # (K, 3) float64
    quat_wxyz: np.ndarray  # (K, 4) float64
    velocity: np.ndarray  # (K, 3) float64


def boxes_per_frame(ann: AnnotationColumns, frames: dict[int, tuple[int, int]]
                    ) -> dict[int, MovingBoxes]:
    """Annotated boxes per frame of ``frames`` (frame -> (scan start, deskew reference
    time)), centre times relative to the frame's deskew reference time (seconds); boxes of
    frames deskew skipped are left out."""
    out: dict[int, MovingBoxes] = {}
    fr = ann.frame_idx
    for f in np.unique(fr):
        if int(f) not in frames:
            continue
        m = fr == f
        ref = frames[int(f)][1]
        out[int(f)] = annotation_boxes(ann.center[m], ann.size_wlh[m], ann.quat_wxyz[m],
                                       ann.velocity[m], (ann.t_ns[m] - ref) * 1e-9, 0.0)
    return out


class AgentScans:
    """One agent's deskewed scans of one LiDAR, its pose track and extrinsic; reads one frame
    at a time through ``read_frame`` (``stage.read_agent_scans`` builds it from the lake)."""

    def __init__(self, agent: str, sensor: str, track: PoseTrack, T_ego_lidar: np.ndarray,
                 frames: dict[int, tuple[int, int]], read_frame: FrameReader,
                 boxes: dict[int, MovingBoxes] | None = None) -> None:
        self.agent, self.sensor = agent, sensor
        self.track, self.T_ego_lidar = track, T_ego_lidar
        # frame_idx -> (scan start, deskew reference time); frames deskew skipped are left out
        self.frames = frames
        self._read_frame = read_frame
        self._boxes = boxes or {}
        # frame -> T_world_lidar: the static filter asks for each frame's pose once per
        # neighbouring frame (interpolating the track each time)
        self._T_world_lidar: dict[int, np.ndarray] = {}
        # time -> T_world_ego: the register stage asks for the same few times per frame from
        # several places (its pose, eq. 1a, the other agents' bodies), and each track
        # interpolation validates the whole track again (about 9 per frame pair, 1 ms each)
        self._world_ego: dict[int, np.ndarray] = {}

    def has_annotations(self, frame_idx: int) -> bool:
        return frame_idx in self._boxes

    def annotated(self) -> bool:
        return bool(self._boxes)

    def points(self, frame_idx: int) -> np.ndarray:
        return self.points_t(frame_idx)[0]

    def points_t(self, frame_idx: int) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3) float32 points and (N,) int64 capture times of one deskewed frame."""
        return self._read_frame(frame_idx)

    def max_travel_per_scan(self) -> float:
        """How far the agent moves during one scan at its usual top speed (95th percentile of
        the INS speed, so a position step does not count as speed) times the scan period
        (median spacing of scan starts): the lever of a wrong extrinsic rotation on deskew."""
        starts = np.sort(np.array([t0 for t0, _ in self.frames.values()], dtype=np.int64))
        t, p = self.track.t_ns, self.track.xyz
        if len(starts) < 2 or len(t) < 2:
            return 0.0
        dt = np.diff(t).astype(np.float64) * 1e-9
        ok = dt > 0
        speed = np.linalg.norm(np.diff(p, axis=0)[ok], axis=1) / dt[ok]
        period = float(np.median(np.diff(starts))) * 1e-9
        return float(np.percentile(speed, 95)) * period if len(speed) else 0.0

    def prefetch(self, t_ns: list[int]) -> None:
        """Interpolate ``T_world_ego`` at every time of ``t_ns`` the track covers in one call
        (:meth:`world_ego` then finds them; a time it does not cover still raises there).
        WHY: the register stage asks for each frame's pose (and each other agent's body at
        every frame, two times a frame) one or two times at a time, and every interpolation
        validated the whole track again: 120 calls on a 3 s clip with three agents, 1 % of
        its CPU. The pose at a time is the same computed alone or in a batch."""
        t = np.unique(np.asarray(t_ns, dtype=np.int64))
        t = t[self.track.covers(t)]
        self.world_ego(*(int(x) for x in t))

    def world_ego(self, *t_ns: int) -> list[np.ndarray]:
        """``T_world_ego`` at each of ``t_ns``, the track interpolated once per time and the
        missing times in one call (raises where the track does not cover one; do not modify
        the returned arrays)."""
        todo = [t for t in t_ns if t not in self._world_ego]
        if todo:
            for t, T in zip(todo, self.track.matrices(np.array(todo, dtype=np.int64)),
                            strict=True):
                self._world_ego[t] = T
        return [self._world_ego[t] for t in t_ns]

    def T_world_lidar(self, frame_idx: int) -> np.ndarray:
        """Where the frame's deskewed points live: ``T_world_ego(t_ref) T_ego_lidar`` (computed
        once per frame; do not modify the returned array)."""
        T = self._T_world_lidar.get(frame_idx)
        if T is None:
            T = self.world_ego(self.frames[frame_idx][1])[0] @ self.T_ego_lidar
            self._T_world_lidar[frame_idx] = T
        return T


def is_stationary(xyz: np.ndarray, quat_wxyz: np.ndarray, max_motion_m: float,
                  max_rotation_deg: float) -> bool:
    """Whether a pose track stays put: every position within ``max_motion_m`` of the first
    one and every attitude within ``max_rotation_deg`` of the first (unit quaternions, w
    first). What the track says, never what the agent is called: a "roadside unit" on a
    trailer or a swaying mast is not stationary."""
    p = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    q = np.asarray(quat_wxyz, dtype=np.float64).reshape(-1, 4)
    if len(p) == 0 or len(q) == 0:
        return False
    if float(np.max(np.linalg.norm(p - p[0], axis=1))) > max_motion_m:
        return False
    # angle between two unit quaternions: 2 acos(|<q, q0>|)
    dot = np.clip(np.abs(q @ q[0]), 0.0, 1.0)
    return float(np.degrees(2.0 * np.arccos(dot.min()))) <= max_rotation_deg


def redeskew(xyz: np.ndarray, t_ns: np.ndarray, t_ref_ns: int, track: PoseTrack,
             T_used: np.ndarray, T_new: np.ndarray) -> np.ndarray:
    """A scan deskewed with extrinsic ``T_used`` as if deskewed with ``T_new``: deskew's own
    kernel (eq. 3) run backwards (each point from the reference time to its own time, with
    the extrinsic that put it there), then forwards with the new one. Points the INS does not
    cover come back NaN (and are dropped by voxelisation)."""
    from v2xlake.tasks.motion import deskew_points

    t = np.asarray(t_ns, np.int64)
    raw = deskew_points(xyz, np.full(len(t), t_ref_ns, np.int64), track, T_used,
                        t_ref_ns=t).xyz
    return deskew_points(raw, t, track, T_new, t_ref_ns=t_ref_ns).xyz


class StaticScans:
    """An agent's scans reduced to the static scene, one voxel size per use (target/source).

    Keeps a small window of fine clouds (``dynamic_voxel_m``) of neighbouring frames for the
    consistency test; frames are expected roughly in order (each is read once then).
    ``filtered`` may be called from several threads at once (``in_flight`` frames at a time:
    the windows grow by that much); the caches only save work, a frame's result never
    depends on what they hold."""

    def __init__(self, scans: AgentScans, settings: StaticSection,
                 bodies: list[tuple[AgentScans, Body]],
                 redeskew_with: np.ndarray | None = None, max_range_m: float = 80.0,
                 in_flight: int = 1) -> None:
        self.scans, self.s = scans, settings
        self.max_range_m = max_range_m
        self.bodies = bodies
        self.redeskew_with = redeskew_with
        self._fine: OrderedDict[int, tuple[np.ndarray, VoxelGrid]] = OrderedDict()
        self._raw: OrderedDict[int, tuple[np.ndarray, np.ndarray]] = OrderedDict()
        self._raw_window = 2 + 2 * (max(in_flight, 1) - 1)
        self._fine_window = 2 * settings.dynamic_neighbours + 2 + 2 * (max(in_flight, 1) - 1)
        self._lock = threading.Lock()
        frames = sorted(scans.frames)
        self._order = {f: i for i, f in enumerate(frames)}
        self._frames = frames
        # the poses asked for frame by frame (this agent's and the bodies'), at once
        ref = [scans.frames[f][1] for f in frames]
        scans.prefetch(ref)
        for other, _ in bodies:
            other.prefetch(ref + [t + _BODY_DT_NS for t in ref])
        self.seconds = {"read": 0.0, "voxel": 0.0, "filter": 0.0}  # where the time goes

    def _spent(self, key: str, seconds: float) -> None:
        with self._lock:
            self.seconds[key] += seconds

    def _points(self, f: int) -> tuple[np.ndarray, np.ndarray]:
        with self._lock:
            hit = self._raw.get(f)
        if hit is not None:
            return hit
        t = time.perf_counter()
        xyz, t_ns = self.scans.points_t(f)
        if self.redeskew_with is not None and len(xyz):
            xyz = redeskew(xyz, t_ns, self.scans.frames[f][1], self.scans.track,
                           self.scans.T_ego_lidar, self.redeskew_with)
        with self._lock:
            self._raw[f] = (xyz, t_ns)
            self.seconds["read"] += time.perf_counter() - t
            while len(self._raw) > self._raw_window:
                self._raw.popitem(last=False)
        return xyz, t_ns

    def _fine_tree(self, f: int) -> tuple[np.ndarray, VoxelGrid]:
        with self._lock:
            hit = self._fine.get(f)
        if hit is not None:
            return hit
        xyz, _ = self._points(f)
        pts = voxel_downsample_t(xyz, None, self.s.dynamic_voxel_m, self.max_range_m + 10.0)[0]
        # the hash grid of the GICP searches (exact, GIL-free), with cells as large as the
        # search bound's half: a SciPy k-d tree held the GIL while it was built
        out = (pts, VoxelGrid(pts, 2.0 * self.s.dynamic_residual_m))
        with self._lock:
            self._fine[f] = out
            while len(self._fine) > self._fine_window:
                self._fine.popitem(last=False)
        return out

    def _use_dynamic(self, f: int) -> bool:
        if not self.s.enabled or self.s.dynamic == "off":
            return False
        if self.s.dynamic == "on":
            return True
        return not (self.s.use_annotations and self.scans.has_annotations(f))

    def _nearest(self, f: int, pts_f: np.ndarray, g: int) -> np.ndarray:
        fine, tree = self._fine_tree(g)
        if len(fine) == 0:
            return np.full(len(pts_f), np.inf)
        T_g_f = invert(self.scans.T_world_lidar(g)) @ self.scans.T_world_lidar(f)
        _, d2 = tree.batch_nearest_neighbor_search(apply(T_g_f, pts_f),
                                                   max_dist_m=4.0 * self.s.dynamic_residual_m)
        return np.asarray(d2, dtype=np.float64)

    def filtered(self, f: int, voxel_m: float) -> FilteredScan:
        xyz, t_ns = self._points(f)
        ref_ns = self.scans.frames[f][1]
        t0 = time.perf_counter()
        pts, t_s = voxel_downsample_t(xyz, (t_ns - ref_ns) * 1e-9 if len(t_ns) else None,
                                      voxel_m, self.max_range_m)
        t1 = time.perf_counter()
        self._spent("voxel", t1 - t0)
        try:
            return self._filtered(f, pts, t_s, voxel_m)
        finally:
            self._spent("filter", time.perf_counter() - t1)

    def _filtered(self, f: int, pts: np.ndarray, t_s: np.ndarray, voxel_m: float
                  ) -> FilteredScan:
        counts = RemovalCounts(n_in=len(pts))
        if not self.s.enabled or len(pts) == 0:
            return FilteredScan(pts, counts)
        keep = np.ones(len(pts), bool)
        if self.s.use_annotations and self.scans.has_annotations(f):
            b = self.scans._boxes[f]
            grown = without_still(b, self.s.keep_still_boxes_mps).grown(self.s.box_margin_m)
            hit = box_of_point(pts, t_s, grown) >= 0
            counts.boxes = int(hit.sum())
            keep &= ~hit
        if self.bodies:
            boxes = MovingBoxes.concat([self._body(f, o, body) for o, body in self.bodies])
            hit = keep & (box_of_point(pts, t_s, boxes) >= 0)
            counts.bodies = int(hit.sum())
            keep &= ~hit
        if self._use_dynamic(f):
            i = self._order[f]
            n = self.s.dynamic_neighbours
            before = [g for g in self._frames[max(0, i - n):i]]
            after = [g for g in self._frames[i + 1:i + 1 + n]]
            # (np.compress: the rows a mask keeps, as boolean indexing gives them, 4x faster
            # on an (n, 3) cloud; the above-ground rows taken once, not once per neighbour)
            q = np.compress(keep, pts, axis=0)
            up = above_ground(q)
            q_up = np.compress(up, q, axis=0)
            sides = [np.min([self._nearest(f, q_up, g) for g in side], axis=0) if side
                     else None for side in (before, after)]
            if up.any() and (sides[0] is not None or sides[1] is not None):
                moving = np.zeros(len(q), bool)
                moving[up] = dynamic_mask(sides[0], sides[1], self.s.dynamic_residual_m)
                if self.s.dynamic_object_fraction < 1.0:
                    moving = grow_to_objects(q, moving, up, max(voxel_m, 0.5),
                                             self.s.dynamic_object_fraction)
                idx = np.flatnonzero(keep)[moving]
                counts.dynamic = len(idx)
                keep[idx] = False
        kept = np.compress(keep, pts, axis=0)
        return FilteredScan(kept, counts, ground_distance(kept))

    def _body(self, f: int, other: AgentScans, body: Body) -> MovingBoxes:
        """The other agent's body in this frame, placed by both INS tracks at this frame's
        reference time and moving with the other agent's INS velocity."""
        ref_ns = self.scans.frames[f][1]
        W_L = self.scans.T_world_lidar(f)
        try:
            W_e, W_e2 = other.world_ego(ref_ns, ref_ns + _BODY_DT_NS)
        except Exception:  # the other agent's INS does not cover this time
            return MovingBoxes.empty()
        T = invert(W_L) @ W_e
        v_world = (W_e2[:3, 3] - W_e[:3, 3]) / (_BODY_DT_NS * 1e-9)
        v = W_L[:3, :3].T @ v_world
        return body_box(T, v, 0.0, body.length, body.width, body.height,
                        np.array(body.center_ego), self.s.body_margin_m)
