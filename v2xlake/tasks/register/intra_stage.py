"""The intra-agent refinement as the register stage runs it (issue #27): every secondary
LiDAR of an agent (modality lidar, other than the primary: ``LIDAR_TOP``, else the agent's
first LiDAR) refined against the primary on deskewed frames, several frame pairs pooled, as
``calibration_refined`` rows (the register stage's table; ``storage.reader.effective_calibration``
hands a usable row to every consumer: ``calibrated_sensors`` readers, exports,
``v2xlake calibration``). Pure: it takes the LiDARs' scans (``scans.AgentScans``, read by
``stage.refine_agent_lidars``) and returns rows; the registration itself is ``intra.py``.

A frame pair is the primary's scan and the secondary's scan that started closest to it
(within ``pair_tolerance_ns``). Each scan is deskewed to its own reference time, so the pair
measures ``T_P(t1)_S(t2) = T_ego_P^-1 M T_ego_S`` with ``M = T_world_ego(t1)^-1
T_world_ego(t2)`` the ego motion between the two reference times (from the INS); the static
extrinsic follows as ``T_P_S = (T_ego_P^-1 M^-1 T_ego_P) T_P(t1)_S(t2)`` without needing the
unknown ``T_ego_S`` for the compensation. The secondary's refined ``T_ego_S`` is the primary's
effective extrinsic (the clip-level refinement of it when the stage has one) times ``T_P_S``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from v2xlake.schemas.tables import CalibrationRefinedRow
from v2xlake.tasks.geometry import invert, matrix_to_quat, rotation_angle, se3_adjoint
from v2xlake.tasks.register.config import IntraSection
from v2xlake.tasks.register.intra import IntraConfig, IntraResult, Pooled, combine, refine_extrinsic
from v2xlake.tasks.register.scans import AgentScans, redeskew

_SECTION = IntraSection()  # the user parameters' one default (register.intra)


@dataclass(frozen=True)
class IntraStageSettings:
    """How the register stage refines the secondary LiDARs of each agent: the user
    parameters of ``register.intra`` (their defaults read from :class:`IntraSection`) and
    internal settings."""

    enabled: bool = _SECTION.enabled
    primary: str | None = None  # None: LIDAR_TOP, else the agent's first LiDAR (sorted)
    frames: int = _SECTION.frames  # frame pairs per secondary LiDAR, spread, then pooled
    pair_tolerance_ns: int = 50_000_000  # scan starts of a pair at most this far apart
    redeskew: bool = True  # deskew the secondary again with a first pass's rotation
    config: IntraConfig = field(default_factory=IntraConfig)


def _lenient(c: IntraConfig) -> IntraConfig:
    """The first pass: the search's best minimum, whatever its support (only used to deskew
    the secondary scan again, never reported)."""
    return dataclasses.replace(c, ambiguity_ratio=np.inf, min_overlap=0.0,
                               max_std_deg=np.inf, max_std_m=np.inf, split_halves=0,
                               finish_max_deg=np.inf, finish_max_m=np.inf,
                               max_correction_deg=np.inf, max_correction_m=np.inf)


def split_lidars(lidars: list[str], primary: str | None = None) -> tuple[str, list[str]]:
    """(primary, secondaries) among an agent's LiDAR sensor names."""
    names = sorted(lidars)
    p = primary if primary in names else ("LIDAR_TOP" if "LIDAR_TOP" in names else names[0])
    return p, [s for s in names if s != p]


def frame_pairs(primary: dict[int, tuple[int, int]], secondary: dict[int, tuple[int, int]],
                tolerance_ns: int, n: int) -> list[tuple[int, int]]:
    """Up to ``n`` (primary frame, secondary frame) pairs whose scan starts are within
    ``tolerance_ns``, spread evenly over the clip."""
    if not secondary:
        return []
    sf = np.array(sorted(secondary))
    s0 = np.array([secondary[g][0] for g in sf], dtype=np.int64)
    pairs = []
    for f in sorted(primary):
        k = int(np.argmin(np.abs(s0 - primary[f][0])))
        if abs(int(s0[k]) - primary[f][0]) <= tolerance_ns:
            pairs.append((f, int(sf[k])))
    if len(pairs) <= n:
        return pairs
    idx = np.unique(np.round(np.linspace(0, len(pairs) - 1, n)).astype(int))
    return [pairs[i] for i in idx]


def to_static(r: IntraResult, A: np.ndarray) -> IntraResult:
    """A frame pair's result (``T_P(t1)_S(t2)``) as the static ``T_P_S = A T``, with its
    covariance carried through (left perturbation in the primary frame)."""
    ad = se3_adjoint(A)
    return dataclasses.replace(r, T_init=A @ r.T_init, T=A @ r.T, cov=ad @ r.cov @ ad.T)


def refine_secondaries(clip_id: str, P: AgentScans, secondaries: Iterable[AgentScans],
                       settings: IntraStageSettings | None = None,
                       T_ego_primary: np.ndarray | None = None
                       ) -> tuple[list[CalibrationRefinedRow], list[str]]:
    """Rows for every secondary LiDAR's scans (``secondaries``, the agent's other LiDARs than
    the primary's ``P``) and notes.

    ``T_ego_primary``: the primary's effective extrinsic (the stage's refined one when usable;
    default the published one)."""
    s = settings or IntraStageSettings()
    agent, primary = P.agent, P.sensor
    T_ep = P.T_ego_lidar if T_ego_primary is None else np.asarray(T_ego_primary)
    rows, notes = [], []
    for S in secondaries:
        sec = S.sensor
        results: list[IntraResult] = []
        for f, g in frame_pairs(P.frames, S.frames, s.pair_tolerance_ns, s.frames):
            E1 = P.track.matrices(P.frames[f][1])[0]
            E2 = S.track.matrices(S.frames[g][1])[0]
            M = invert(E1) @ E2
            X0 = invert(P.T_ego_lidar) @ M @ S.T_ego_lidar
            pts_p = P.points(f).astype(np.float64)
            xyz, t_ns = S.points_t(g)
            pts_s = xyz.astype(np.float64)
            if s.redeskew:
                # deskew turned the ego motion into the secondary's frame with its published
                # rotation, wrong by up to tens of degrees: the scan is smeared by about
                # (travel per scan) x (rotation error). A first, lenient pass (its best
                # minimum, no refusal) gives the rotation to deskew the scan again with;
                # only the second pass, on the re-deskewed scan, is judged.
                r1 = refine_extrinsic(pts_p, pts_s, X0, _lenient(s.config))
                T_es1 = P.T_ego_lidar @ invert(M) @ r1.T  # T_ego_S of the first pass
                pts_s = redeskew(xyz, t_ns, S.frames[g][1], S.track, S.T_ego_lidar, T_es1)
                pts_s = pts_s[np.isfinite(pts_s).all(axis=1)].astype(np.float64)
            r = refine_extrinsic(pts_p, pts_s, X0, s.config)
            results.append(to_static(r, invert(P.T_ego_lidar) @ invert(M) @ P.T_ego_lidar))
        pooled = combine(results, s.config)
        refusals = sorted({r.reason.split(":")[0] for r in results if not r.accepted})
        reason = pooled.reason + (f"; refused frames: {', '.join(refusals)}" if refusals else "")
        rows.append(_row(clip_id, agent, sec, primary, S.T_ego_lidar, T_ep, pooled,
                         len(results), reason))
        notes.append(f"intra {agent} {sec} vs {primary}: "
                     + ("refined" if pooled.accepted else "published kept") + f" ({reason})")
    return rows, notes


def _row(clip_id: str, agent: str, sensor: str, primary: str, T_pub: np.ndarray,
         T_ep: np.ndarray, pooled: Pooled, n_frames: int, reason: str) -> CalibrationRefinedRow:
    """The refined-calibration row of one secondary LiDAR: refined (usable) when the pooled
    estimate is accepted, else the published extrinsic with the reason."""
    if pooled.accepted and pooled.T is not None:
        T = T_ep @ pooled.T
        # left perturbation of T_P_S (primary frame) -> right perturbation of T_ego_S
        ad = se3_adjoint(invert(pooled.T))
        cov = ad @ pooled.cov @ ad.T
        comps, std_m, std_deg = "rx ry rz tx ty tz", pooled.std_m, pooled.std_deg
    else:
        T, cov, comps, std_m, std_deg = T_pub, np.full((6, 6), np.nan), "", float("nan"), \
            float("nan")
    q, qp = matrix_to_quat(T[:3, :3]), matrix_to_quat(T_pub[:3, :3])
    d = invert(T_pub) @ T
    return CalibrationRefinedRow(
        clip_id=clip_id, agent_id=agent, sensor=sensor, tx=T[0, 3], ty=T[1, 3], tz=T[2, 3],
        qw=q[0], qx=q[1], qy=q[2], qz=q[3], pub_tx=T_pub[0, 3], pub_ty=T_pub[1, 3],
        pub_tz=T_pub[2, 3], pub_qw=qp[0], pub_qx=qp[1], pub_qy=qp[2], pub_qz=qp[3],
        correction_m=float(np.linalg.norm(d[:3, 3])),
        correction_deg=float(np.degrees(rotation_angle(d))),
        cov=[float(x) for x in cov.ravel()], std_m=std_m, std_deg=std_deg,
        refined_components=comps, usable=bool(pooled.accepted), n_frames=n_frames,
        source="refined", method=f"intra:small_gicp:GICP+search vs {primary}",
        reason=reason)


