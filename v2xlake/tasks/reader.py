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
import pyarrow.compute as pc

from v2xlake.schemas.errors import ClipError
from v2xlake.schemas.geometry import matrix_to_quat, quat_to_matrix
from v2xlake.schemas.stage import StageReport
from v2xlake.storage.lake import Lake
from v2xlake.storage.reader import (
    AgentRecord,
    CalibrationChoice,
    ClipRecord,
    PoseSamples,
    calibrations,
    effective_calibration,
    no_pose_report,
    read,
    read_clip,
)
from v2xlake.storage.reader import read_pose_samples as _read_pose_samples
from v2xlake.tasks.geometry import invert, rotation_angle, so3_exp, so3_log, transform
from v2xlake.tasks.interpolate import PoseCoverageError, PoseTrack


@dataclass(eq=False)
class AgentData(AgentRecord):
    """An agent's records plus its pose track (``poses``).

    ``poses`` is what every consumer places the agent with: for a cooperative agent whose
    frames the register stage accepted, its INS track corrected by the registered relative
    transform (``pose_source == "registered"``, see :func:`registered_track`); otherwise the
    INS track itself. ``ins_poses`` is always the INS track."""

    poses: PoseTrack
    ins_poses: PoseTrack | None = None
    pose_source: str = "ins"  # "registered" | "ins"

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


#: Registered frames further apart than this (by the other agent's scan time) are not
#: bridged: between them the agent's poses stay INS (``load_clip(registered_max_gap_s=)``).
REGISTERED_MAX_GAP_S = 0.35


def with_tracks(rec: ClipRecord, *, registered: bool = True,
                registered_max_gap_s: float = REGISTERED_MAX_GAP_S) -> ClipData:
    """The record with every agent's pose track built; with ``registered`` the cooperative
    agents' tracks carry the register stage's accepted transforms (:func:`registered_track`)."""
    agents = {aid: AgentData(**{k: getattr(a, k) for k in AgentRecord.__dataclass_fields__},
                             poses=track(a.pose_samples, rec.clip_id, aid))
              for aid, a in rec.agents.items()}
    for a in agents.values():
        a.ins_poses = a.poses
    if registered and rec.registrations.num_rows:
        ref = agents[rec.reference_agent]
        for aid, a in agents.items():
            if aid == rec.reference_agent:
                continue
            corrected = registered_track(rec, ref, a, int(registered_max_gap_s * 1e9))
            if corrected is not None:
                a.poses, a.pose_source = corrected, "registered"
    return ClipData(rec.clip_id, rec.info, agents, rec.instances,
                    rec.registrations)


def load_clip(lake: Lake, clip_id: str, *, registered: bool = True,
              registered_max_gap_s: float = REGISTERED_MAX_GAP_S) -> ClipData:
    """Everything but the points of one clip (clean zone), pose tracks built (cooperative
    agents placed by their registered transforms where the register stage accepted them)."""
    return with_tracks(read_clip(lake, clip_id), registered=registered,
                       registered_max_gap_s=registered_max_gap_s)


def load_posed_clip(lake: Lake, clip_id: str, stage: str, why_needed: str
                    ) -> ClipData | StageReport:
    """The clip as ``load_clip`` gives it, for a stage that needs poses: its
    ``not_applicable`` report (naming ``why_needed``) when no agent has a pose track, and a
    failure to load it raised as ``stage``'s ``ClipError`` (so the quarantine report names
    the stage that could not go on). Annotate and align start this way."""
    if (na := no_pose_report(lake, clip_id, stage, why_needed)):
        return na
    try:
        return load_clip(lake, clip_id)
    except ClipError as e:
        raise ClipError(clip_id, e.reason, agent_id=e.agent_id, path=e.path, stage=stage) from e


def registered_track(clip: ClipRecord, ref: AgentData, agent: AgentData, max_gap_ns: int,
                     pair_tolerance_ns: int = 1_000_000) -> PoseTrack | None:
    """The agent's ego track placed by the accepted registrations against the reference agent.

    At an accepted frame k the register stage measured ``T_L1_Lj`` between the two deskewed
    scans (at their reference times t1, tj), so the agent's LiDAR is at
    ``T_W_Lj = T_W_E1(t1) E1 T_L1_Lj`` and its ego at ``T_W_Lj Ej^-1``, with the extrinsics
    every consumer uses (the effective calibration). The difference to the INS pose at tj --
    a rotation about the agent and a shift, in world axes -- is interpolated linearly
    between accepted frames at most ``max_gap_ns`` apart and applied to the INS samples
    there, whose times stay the same (so per-sample data such as velocities still lines up;
    between samples the correction is interpolated with the pose, sub-millimetre at INS
    rates); elsewhere the INS track stands. None when nothing is accepted.

    Why the whole track and not only the LiDAR frames: cameras, radar, boxes and the ROS
    ``/tf`` tree of this agent are placed by the same ego track, so all of them move with
    the registration consistently; a per-frame patch of the LiDAR alone would leave the
    camera 15 cm away from the LiDAR it is calibrated to."""
    r = clip.registrations
    if r.num_rows == 0:
        return None
    rows = [x for x in r.to_pylist() if x["accepted"] and x["agent_other"] == agent.agent_id
            and x["agent_ref"] == ref.agent_id]
    if not rows:
        return None
    s1, sj = ref.lidar_sensor(), agent.lidar_sensor()
    lf1, lfj = ref.lidar[s1], agent.lidar[sj]
    E1, Ej = ref.sensors[s1].T_ego_sensor, agent.sensors[sj].T_ego_sensor
    ref_of = dict(zip(lf1.frame_idx.tolist(), lf1.ref_ns.tolist(), strict=True))
    order = np.argsort(lfj.t_start_ns)
    starts = lfj.t_start_ns[order]
    base = ref.poses  # the reference agent is never corrected
    ins = agent.ins_poses or agent.poses
    t_k, dR, dp = [], [], []
    for x in rows:
        t1 = ref_of.get(int(x["frame_idx"]))
        j = int(nearest_index(starts, int(x["t_ns"]))[0])
        if t1 is None or t1 < 0 or abs(int(starts[j]) - int(x["t_ns"])) > pair_tolerance_ns:
            continue
        tj = int(lfj.ref_ns[order[j]])
        if tj < 0 or not (base.covers(t1) and ins.covers(tj)):
            continue
        T_reg = transform(np.array([x["tx"], x["ty"], x["tz"]]),
                          np.array([x["qw"], x["qx"], x["qy"], x["qz"]]))
        M_reg = base.matrices(t1)[0] @ E1 @ T_reg @ invert(Ej)
        M_ins = ins.matrices(tj)[0]
        t_k.append(tj)
        dR.append(so3_log(M_reg[:3, :3] @ M_ins[:3, :3].T))
        dp.append(M_reg[:3, 3] - M_ins[:3, 3])
    if not t_k:
        return None
    o = np.argsort(t_k)
    tk = np.asarray(t_k, np.int64)[o]
    keep = np.concatenate([[True], np.diff(tk) > 0])
    tk, wk, pk = tk[keep], np.asarray(dR)[o][keep], np.asarray(dp)[o][keep]
    t_all = ins.t_ns
    xyz, q = ins.xyz, ins.quat_wxyz
    # accepted frames bracketing each sample, bridged only when close enough
    k = np.searchsorted(tk, t_all, side="right") - 1
    i0 = np.clip(k, 0, len(tk) - 1)
    i1 = np.clip(k + 1, 0, len(tk) - 1)
    inside = (k >= 0) & (k < len(tk) - 1)
    gap = tk[i1] - tk[i0]
    bridged = inside & (gap <= max_gap_ns)
    a = np.where(bridged, (t_all - tk[i0]) / np.maximum(gap, 1), 0.0)[:, None]
    w = wk[i0] * (1 - a) + wk[i1] * a
    p = pk[i0] * (1 - a) + pk[i1] * a
    R_new = so3_exp(np.where(bridged[:, None], w, 0.0)) @ quat_to_matrix(q)
    q_new = matrix_to_quat(R_new)
    xyz_new = xyz + np.where(bridged[:, None], p, 0.0)
    return PoseTrack.create(t_all, xyz_new, q_new)


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


@dataclass(frozen=True)
class CalibrationComparison:
    agent_id: str
    sensor: str
    published: np.ndarray  # T_ego_sensor 4x4
    refined: np.ndarray | None  # None: the clip has no refinement for this sensor
    correction_m: float
    correction_deg: float
    std_m: float
    std_deg: float
    refined_components: str
    usable: bool
    effective: str  # "refined" | "published": what annotate, align and the exports use
    reason: str = ""  # why (part of) the published extrinsic is kept
    method: str = ""  # what refined it: the clip solve, or intra-agent against a primary

    @property
    def delta_lidar(self) -> np.ndarray:
        """(6,) refined relative to published in the LiDAR frame: [rot deg, trans m]."""
        if self.refined is None:
            return np.zeros(6)
        d = invert(self.published) @ self.refined
        return np.concatenate([np.degrees(so3_log(d[:3, :3])), d[:3, 3]])


def compare_calibration(lake: Lake, clip_id: str,
                        choice: CalibrationChoice | None = None
                        ) -> list[CalibrationComparison]:
    """Every LiDAR of every agent of the clip: published, refined (if any), effective."""
    choice = choice or CalibrationChoice()
    out = []
    cal = read(lake, "calibrated_sensors", clip_id)
    ref = read(lake, "calibration_refined", clip_id)
    agents = sorted(set(cal["agent_id"].to_pylist())) if cal.num_rows else []
    for a in agents:
        pub_all = calibrations(cal.filter(pc.equal(cal["agent_id"], a)), clip_id, a)
        pub = {s: c for s, c in pub_all.items() if c.modality == "lidar"}
        ref_a = ref.filter(pc.equal(ref["agent_id"], a)) if ref.num_rows else ref
        _, source = effective_calibration(pub, ref_a, choice)
        rows = {r["sensor"]: r for r in ref_a.to_pylist()} if ref_a.num_rows else {}
        for s, c in sorted(pub.items()):
            r = rows.get(s)
            refined = None
            if r is not None:
                q = np.array([r["qw"], r["qx"], r["qy"], r["qz"]], dtype=np.float64)
                refined = transform(np.array([r["tx"], r["ty"], r["tz"]], dtype=np.float64),
                                    q / np.linalg.norm(q))
            d = invert(c.T_ego_sensor) @ refined if refined is not None else np.eye(4)
            out.append(CalibrationComparison(
                a, s, c.T_ego_sensor, refined, float(np.linalg.norm(d[:3, 3])),
                float(np.degrees(rotation_angle(d))), float(r["std_m"]) if r else float("nan"),
                float(r["std_deg"]) if r else float("nan"),
                str(r["refined_components"]) if r else "", bool(r["usable"]) if r else False,
                source[s], str((r or {}).get("reason") or ""),
                str((r or {}).get("method") or "")))
    return out
