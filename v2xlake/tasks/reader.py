"""A clip ready for computation: the clean-zone records of ``v2xlake.storage.reader`` with
their pose tracks built (eq. 2a-2c interpolation), and the small pose / box helpers every
stage and export shares.

All reading happens in ``storage/reader.py``; this module only turns its arrays into
:class:`PoseTrack` objects and matrices, so a stage or export imports the I/O (points per
frame, frames available) from there and the math from here.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import pyarrow as pa

from v2xlake.schemas.errors import ClipError
from v2xlake.storage.lake import Lake
from v2xlake.storage.reader import AgentRecord, ClipRecord, PoseSamples, read_clip
from v2xlake.storage.reader import read_pose_samples as _read_pose_samples
from v2xlake.tasks.geometry import transform
from v2xlake.tasks.interpolate import PoseCoverageError, PoseTrack


@dataclass(eq=False)
class AgentData(AgentRecord):
    """An agent's records plus its pose track (``poses``)."""

    poses: PoseTrack

    @property
    def velocity(self) -> np.ndarray:
        """(N, 3) world velocity at the pose samples."""
        return self.pose_samples.velocity

    def T_world_ego(self, t_ns: np.ndarray | int, *, clip_id: str = "") -> np.ndarray:
        """(N, 4, 4) interpolated ego poses (eq. 2a-2c), never extrapolated."""
        try:
            return self.poses.matrices(t_ns)
        except PoseCoverageError as e:
            raise ClipError(clip_id, f"ego pose interpolation: {e}", agent_id=self.agent_id,
                            stage="export") from e


@dataclass(eq=False)
class ClipData(ClipRecord):
    agents: dict[str, AgentData]  # type: ignore[assignment]  # reference agent first


def track(samples: PoseSamples, clip_id: str, agent_id: str) -> PoseTrack:
    try:
        return PoseTrack.create(samples.t_ns, samples.xyz, samples.quat_wxyz)
    except ValueError as e:
        raise ClipError(clip_id, f"ego_poses unusable: {e}", agent_id=agent_id) from e


def with_tracks(rec: ClipRecord) -> ClipData:
    """The record with every agent's pose track built."""
    agents = {aid: AgentData(**{k: getattr(a, k) for k in AgentRecord.__dataclass_fields__},
                             poses=track(a.pose_samples, rec.clip_id, aid))
              for aid, a in rec.agents.items()}
    return ClipData(rec.clip_id, rec.info, agents, rec.instances,
                    rec.registrations)


def load_clip(lake: Lake, clip_id: str) -> ClipData:
    """Everything but the points of one clip (clean zone), pose tracks built."""
    return with_tracks(read_clip(lake, clip_id))


def load_pose_track(lake: Lake, clip_id: str, agent_id: str) -> PoseTrack:
    """The agent's clean ``T_world_ego`` track; ClipError if the agent has no INS."""
    return track(_read_pose_samples(lake, clip_id, agent_id), clip_id, agent_id)


def boxes_matrices(ann: pa.Table) -> np.ndarray:
    """(N, 4, 4) ``T_frame_box`` of annotation rows."""
    c = {k: ann[k].to_numpy() for k in ("cx", "cy", "cz", "qw", "qx", "qy", "qz")}
    q = np.stack([c["qw"], c["qx"], c["qy"], c["qz"]], 1)
    return transform(np.stack([c["cx"], c["cy"], c["cz"]], 1), q)


def nearest_index(sorted_t: np.ndarray, t: np.ndarray | int) -> np.ndarray:
    """Index of the nearest value in a sorted array, for each query."""
    t = np.atleast_1d(np.asarray(t, dtype=np.int64))
    i = np.clip(np.searchsorted(sorted_t, t), 1, max(len(sorted_t) - 1, 1))
    left = sorted_t[i - 1]
    right = sorted_t[np.minimum(i, len(sorted_t) - 1)]
    return np.where(np.abs(t - left) <= np.abs(right - t), i - 1, i).astype(np.int64)


def lidar_world_poses(agent: AgentData, sensor: str, t_ns: np.ndarray, clip_id: str) -> np.ndarray:
    """``T_world_lidar(t) = T_world_ego(t) @ T_ego_lidar`` for each time."""
    return agent.T_world_ego(t_ns, clip_id=clip_id) @ agent.sensors[sensor].T_ego_sensor


#: Where a cooperative agent's relative transform ``T_Lref_Lother`` comes from: the register
#: stage's accepted refinement (eq. 1b), the two agents' INS poses (eq. 1a), or -- for the
#: reference agent itself -- nothing relative at all (identity).
TransformSource = Literal["registered", "ins", "reference"]
REGISTERED: TransformSource = "registered"
INS: TransformSource = "ins"
REFERENCE: TransformSource = "reference"

NOT_REGISTERED_CLIP = "register has not run on this clip (no registrations rows)"
NOT_REGISTERED_FRAME = "no registration row for this agent at this reference frame"
REGISTRATION_OFF = "use_registration=False"


@dataclass(frozen=True, eq=False)
class RelativeTransform:
    """Which ``T_Lref_Lother`` a reader should use for one agent at one reference frame.

    ``T`` is the accepted refined transform (eq. 1b) when ``source == "registered"``, else
    None and the caller composes the INS poses (eq. 1a). ``reason`` says why the frame is not
    registered (the register stage's own reason for a rejected pair, e.g. "uncertain: clip
    estimate 1-sigma 2.5 cm > 2.0 cm"); empty when it is. Readers expose it because an INS
    fallback is ~0.5 m off where a registered transform is ~2 cm, and a training set mixing
    the two without knowing which is which is silently worse.
    """

    source: TransformSource
    reason: str = ""
    T: np.ndarray | None = None


_REG_INDEX: weakref.WeakKeyDictionary[ClipRecord, dict[tuple[str, int], dict[str, Any]]] = \
    weakref.WeakKeyDictionary()


def _registration_index(clip: ClipRecord) -> dict[tuple[str, int], dict[str, Any]]:
    """Rows of ``registrations`` against the reference agent by (other agent, reference
    frame), an accepted row winning over a rejected one; built once per clip record so that
    a sample costs a dict lookup, not a scan of the table."""
    idx = _REG_INDEX.get(clip)
    if idx is None:
        idx = {}
        r = clip.registrations
        for x in (r.to_pylist() if r.num_rows else []):
            if x["agent_ref"] != clip.reference_agent:
                continue
            key = (str(x["agent_other"]), int(x["frame_idx"]))
            if key not in idx or (x["accepted"] and not idx[key]["accepted"]):
                idx[key] = x
        _REG_INDEX[clip] = idx
    return idx


def relative_transform(clip: ClipRecord, other: str, ref_frame_idx: int, *,
                       use_registration: bool = True) -> RelativeTransform:
    """The source of ``T_Lref_Lother`` at one reference frame, with the refined matrix when
    the register stage accepted that frame (see :class:`RelativeTransform`)."""
    if other == clip.reference_agent:
        return RelativeTransform(REFERENCE)
    if not use_registration:
        return RelativeTransform(INS, REGISTRATION_OFF)
    if clip.registrations.num_rows == 0:
        return RelativeTransform(INS, NOT_REGISTERED_CLIP)
    x = _registration_index(clip).get((other, int(ref_frame_idx)))
    if x is None:
        return RelativeTransform(INS, NOT_REGISTERED_FRAME)
    if not x["accepted"]:
        return RelativeTransform(INS, f"rejected: {x['reason'] or 'no reason recorded'}")
    return RelativeTransform(REGISTERED, "", transform(
        np.array([x["tx"], x["ty"], x["tz"]]), np.array([x["qw"], x["qx"], x["qy"], x["qz"]])))


def registered_T(clip: ClipRecord, other: str, ref_frame_idx: int) -> np.ndarray | None:
    """The accepted refined ``T_Lref_Lother`` (eq. 1b) of one reference frame, if any
    (:func:`relative_transform` also says why there is none)."""
    return relative_transform(clip, other, ref_frame_idx).T


def match_agents(clip: ClipData, ref_t: np.ndarray, tolerance_ns: float, *,
                 sensor: str = "LIDAR_TOP", have: dict[str, set[int]] | None = None,
                 ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Which reference times every agent can fill, and with which of its LiDAR frames.

    For each agent its scan nearest each time in ``ref_t`` (by the time its deskewed points
    are expressed at); a time is kept when every agent has one within ``tolerance_ns``,
    inside its pose coverage and with deskewed points (``have``: frame indices per agent
    that have points; default: what ``deskew_frames`` says). Returns (keep mask, {agent:
    index into that agent's ``LidarFrames`` per reference time}).
    """
    ref = clip.agents[clip.reference_agent]
    common = ref.poses.covers(ref_t)
    nears: dict[str, np.ndarray] = {}
    for aid, agent in clip.agents.items():
        lf = agent.lidar[agent.lidar_sensor(sensor)]
        t = lf.points_t_ns
        near = nearest_index(t, ref_t)
        common &= np.abs(t[near] - ref_t) <= tolerance_ns
        common &= agent.poses.covers(t[near])
        common &= np.isin(lf.frame_idx[near], list(have[aid])) if have is not None \
            else lf.deskewed[near]
        nears[aid] = near
    return common, nears
