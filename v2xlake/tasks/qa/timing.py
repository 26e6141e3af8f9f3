"""QA's numeric core on stamp arrays: distances to a sensor's PPS grid, interval jitter,
measured rates, dropped frames, pose coverage of scans (no lake, no files)."""

from __future__ import annotations

import numpy as np

NS = 1_000_000_000
MS = 1_000_000


def grid_offsets_ns(t_ns: np.ndarray, period_ns: int) -> np.ndarray:
    """Signed distance of each stamp to the nearest multiple of ``period_ns`` (PPS-aligned)."""
    r = np.mod(t_ns, period_ns)
    return np.where(r > period_ns // 2, r - period_ns, r)


def pps_offsets_ns(t_ns: np.ndarray, rate_hz: float, phase_ns: int = 0) -> np.ndarray:
    """Signed distance of each stamp to ``sec + phase + round(k * 1e9 / rate)`` for the
    nearest k: the grid of a sensor triggered from every PPS edge (at 30 Hz the grid restarts
    each second, so k * 33.333 ms is rounded per frame, never accumulated)."""
    t = np.asarray(t_ns, np.int64) - int(phase_ns)
    if rate_hz < 1.0:  # slower than the PPS: every period_ns from the epoch
        return grid_offsets_ns(t, round(NS / rate_hz))
    sec = np.floor_divide(t, NS)
    frac = t - sec * NS
    k = np.rint(frac * rate_hz / NS).astype(np.int64)
    grid = np.rint(k * (NS / rate_hz)).astype(np.int64)  # k == rate lands on the next second
    return frac - grid


def camera_offsets_ns(t_ns: np.ndarray, fps: float) -> np.ndarray:
    """``pps_offsets_ns`` at ``fps`` with no phase (the CATS-V2V camera trigger)."""
    return pps_offsets_ns(t_ns, fps)


def interval_jitter_ns(t_ns: np.ndarray, period_ns: float) -> np.ndarray:
    """Deviation of each interval from the nearest whole number (>= 1) of periods: the
    jitter of a free-running sensor, with dropped frames not counted as jitter."""
    if t_ns.size < 2:
        return np.zeros(0)
    dt = np.diff(t_ns).astype(np.float64)
    n = np.maximum(np.rint(dt / period_ns), 1.0)
    return dt - n * period_ns


def measured_rate_hz(t_ns: np.ndarray) -> float | None:
    """The rate the stamps show: 1 / median positive interval (None: fewer than 2 stamps)."""
    if t_ns.size < 2:
        return None
    dt = np.diff(np.sort(t_ns))
    dt = dt[dt > 0]
    return float(NS / np.median(dt)) if dt.size else None


def dropped_frames(t_ns: np.ndarray, period_ns: float) -> tuple[int, list[tuple[int, int]]]:
    """Number of missing frames and the (before, after) stamps of every gap."""
    if t_ns.size < 2:
        return 0, []
    dt = np.diff(t_ns)
    missing = np.maximum(np.rint(dt / period_ns).astype(np.int64) - 1, 0)
    idx = np.flatnonzero(missing)
    return int(missing.sum()), [(int(t_ns[i]), int(t_ns[i + 1])) for i in idx]


def ins_uncovered(ins_t: np.ndarray, t_start: np.ndarray, t_end: np.ndarray,
                  max_gap_ns: int) -> np.ndarray:
    """Boolean per scan: True when pose samples do not bracket [t_start, t_end] densely
    (a sample at or before the start, one at or after the end, no gap above ``max_gap_ns``
    in between), i.e. deskew could not interpolate a pose for every point."""
    bad = np.ones(t_start.size, dtype=bool)
    if ins_t.size < 2:
        return bad
    lo = np.searchsorted(ins_t, t_start, side="right") - 1
    hi = np.searchsorted(ins_t, t_end, side="left")
    ok = (lo >= 0) & (hi < ins_t.size)
    gaps = np.diff(ins_t)
    for i in np.flatnonzero(ok):
        a, b = int(lo[i]), int(hi[i])
        bad[i] = b > a and bool(gaps[a:b].max() > max_gap_ns)
    return bad


def spans(mask: np.ndarray, t_start: np.ndarray, t_end: np.ndarray) -> list[tuple[int, int]]:
    """Merge consecutive flagged scans into (start, end) time spans."""
    out: list[tuple[int, int]] = []
    for i in np.flatnonzero(mask):
        s, e = int(t_start[i]), int(t_end[i])
        if out and s <= out[-1][1] + 200 * MS:
            out[-1] = (out[-1][0], max(out[-1][1], e))
        else:
            out.append((s, e))
    return out
