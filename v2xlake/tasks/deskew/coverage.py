"""Which points and scans a pose track can compensate, on arrays: the longest pose gap
deskew interpolates across, the gaps of a track, and why a deskewed scan cannot be kept
(no lake, no files)."""

from __future__ import annotations

import numpy as np

from v2xlake.tasks.deskew.config import PoseGaps, UncoveredPolicy
from v2xlake.tasks.interpolate import PoseTrack
from v2xlake.tasks.motion import DeskewResult


def max_pose_gap(track: PoseTrack, cfg: PoseGaps) -> int:
    """The longest pose interval deskew interpolates across: the configured one, else
    ``periods`` of the track's median period and at least 50 ms. A fixed 50 ms
    made every 10 Hz pose source (localisation stacks, Odometry) a gap at every sample."""
    if cfg.max_ns is not None:
        return cfg.max_ns
    d = np.diff(track.t_ns)
    period = float(np.median(d)) if d.size else 0.0
    return int(max(50_000_000, cfg.periods * period))


def pose_gaps(track: PoseTrack, max_gap: int) -> np.ndarray:
    """(K, 2) [t_a, t_b] of consecutive INS samples further apart than ``max_gap``."""
    d = np.diff(track.t_ns)
    k = np.flatnonzero(d > max_gap)
    return np.stack([track.t_ns[k], track.t_ns[k + 1]], axis=1)


def uncompensable(res: DeskewResult, track: PoseTrack, gaps: np.ndarray,
                  uncovered: UncoveredPolicy, pose_gaps: PoseGaps) -> str | None:
    """Why this frame cannot be compensated, or None."""
    finite = res.n_points - res.n_nan
    if finite == 0:
        return None
    span = f"points span [{res.t_min_ns}, {res.t_max_ns}] ns"
    if res.t_ref_ns is not None and not bool(track.covers(res.t_ref_ns)):
        return (f"reference time {res.t_ref_ns} ns is outside the INS coverage "
                f"[{track.t_min}, {track.t_max}] ns")
    if res.n_uncovered > uncovered.max_fraction * finite:
        if res.uncovered_max_ns is not None and res.uncovered_max_ns > track.t_max:
            cover = f"INS covers only up to {track.t_max} ns"
        else:
            cover = f"INS covers only from {track.t_min} ns"
        return (f"{span} but {cover} ({res.n_uncovered} of {finite} points uncovered, "
                f"times [{res.uncovered_min_ns}, {res.uncovered_max_ns}] ns)")
    assert res.t_min_ns is not None and res.t_max_ns is not None
    for a, b in gaps:
        if a < res.t_max_ns and b > res.t_min_ns:
            limit = max_pose_gap(track, pose_gaps) / 1e6
            return (f"{span} but the INS has a gap of {(b - a) / 1e6:.1f} ms between {a} and "
                    f"{b} ns (max {limit:.1f} ms: deskew.pose_gaps.max_ns or "
                    "deskew.pose_gaps.periods sets it)")
    return None
