"""Raw -> clean for time and position (docs/architecture.md "Time", "Space"; CATS-V2V A.3).

Time: every clean table uses the clip's relative axis
``t_rel = t_abs - clip_t0_abs + 100_000_000`` ns, where ``clip_t0_abs`` is the earliest sensor
stamp of the clip over all agents. Position: local ENU metres in ``LocalFrame(lat0, lon0)``
at the reference agent's first INS fix (x = y = 0 there, z = ellipsoidal height). Attitude
becomes ``R_world_ego = R_local_enu(lat, lon) @ attitude_to_matrix(roll, pitch, azimuth)``:
the INS attitude is relative to the local level at the vehicle's own position, which is
rotated by up to a few millidegrees per kilometre against the clip frame.

Everything here works on Arrow tables in memory (no I/O), so the rules are unit-testable.
"""

from __future__ import annotations

import re

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from v2xlake.schemas.arrow import columns_to_table
from v2xlake.schemas.tables import EgoPoseRow, GnssRow
from v2xlake.tasks.geodesy import LocalFrame, attitude_to_matrix
from v2xlake.tasks.geometry import matrix_to_quat

T0_OFFSET_NS = 100_000_000
EPOCH_LO_S, EPOCH_HI_S = 631_152_000, 4_102_444_800  # 1990 .. 2100
UNITS_PER_S = {"s": 1, "ms": 10**3, "us": 10**6, "ns": 10**9}
# a digit run (optionally with decimals) not glued to letters, digits or a preceding decimal
NUMBER = re.compile(r"(?<![0-9A-Za-z])(?<![0-9]\.)([0-9]{9,19})(\.[0-9]+)?(?![0-9A-Za-z])")

# Absolute-time columns per raw table: shifted to the relative axis in the clean zone.
TIME_COLUMNS: dict[str, tuple[str, ...]] = {
    "ins": ("t_ns",),
    "ego_poses": ("t_ns",),
    "imu": ("t_ns",),
    "gnss": ("t_ns",),
    "lidar_frames": ("stamp_ns", "t_start_ns", "t_end_ns", "deskew_ref_ns"),
    "lidar_points": ("t_ns",),
    "radar_frames": ("stamp_ns", "t_start_ns", "t_end_ns"),
    "radar_points": ("t_ns",),
    "camera_frames": ("stamp_ns",),
    "annotations": ("t_ns",),
    "instances": ("first_t_ns", "last_t_ns"),
    "registrations": ("t_ns",),
    "alignments": ("camera_t_ns", "points_t_ns"),
}

# Which columns define the clip's zero (sensor stamps, not derived values).
T0_SOURCES: dict[str, tuple[str, ...]] = {
    "lidar_frames": ("t_start_ns", "stamp_ns"),
    "camera_frames": ("stamp_ns",),
    "radar_frames": ("t_start_ns", "stamp_ns"),
    "ins": ("t_ns",),
    "imu": ("t_ns",),
    "gnss": ("t_ns",),
    "ego_poses": ("t_ns",),
}


def clip_t0_abs(tables: dict[str, pa.Table]) -> int:
    """Earliest sensor stamp over every agent and sensor table given (raises if none)."""
    best: int | None = None
    for name, cols in T0_SOURCES.items():
        t = tables.get(name)
        if t is None or t.num_rows == 0:
            continue
        for c in cols:
            if c in t.column_names:
                m = pc.min(t.column(c)).as_py()
                if m is not None and (best is None or m < best):
                    best = int(m)
    if best is None:
        raise ValueError(
            "no sensor time stamps in the clip (lidar_frames, camera_frames, ins, imu, gnss)"
        )
    return best


def shift_times(table: pa.Table, name: str, t0_abs: int) -> pa.Table:
    """Replace every absolute-time column of ``name`` by its relative value (nulls stay null)."""
    delta = T0_OFFSET_NS - int(t0_abs)
    for c in TIME_COLUMNS.get(name, ()):
        if c not in table.column_names:
            continue
        i = table.column_names.index(c)
        col = table.column(c)
        table = table.set_column(i, table.schema.field(c), pc.add(col, pa.scalar(delta, col.type)))
    return table


def reference_origin(ins: pa.Table, reference_agent: str) -> tuple[float, float, str]:
    """lat0, lon0 of the reference agent's first INS fix (another agent's if it has none)."""
    if ins.num_rows == 0:
        raise ValueError("no INS rows")
    agents = (
        ins.column("agent_id").to_pylist()
        if "agent_id" in ins.column_names
        else [reference_agent] * ins.num_rows
    )
    t = ins.column("t_ns").to_numpy()
    lat = ins.column("lat").to_numpy()
    lon = ins.column("lon").to_numpy()
    mask = np.array([a == reference_agent for a in agents])
    used = reference_agent
    if not mask.any():
        mask = np.ones(len(t), bool)
        used = str(agents[int(np.argmin(t))])
    i = np.flatnonzero(mask)[int(np.argmin(t[mask]))]
    return float(lat[i]), float(lon[i]), used


def ins_to_ego_poses(ins: pa.Table, frame: LocalFrame, t0_abs: int) -> pa.Table:
    """Raw ``ins`` rows of one agent -> clean ``ego_poses`` (T_world_ego, local ENU, t_rel)."""
    n = ins.num_rows
    lat = ins.column("lat").to_numpy().astype(float)
    lon = ins.column("lon").to_numpy().astype(float)
    alt = ins.column("alt").to_numpy().astype(float)
    xyz = frame.to_local(lat, lon, alt).reshape(n, 3)
    r_loc_enu = frame.R_local_enu(lat, lon).reshape(n, 3, 3)
    r_enu_body = attitude_to_matrix(
        ins.column("roll").to_numpy(),
        ins.column("pitch").to_numpy(),
        ins.column("azimuth").to_numpy(),
    ).reshape(n, 3, 3)
    r = r_loc_enu @ r_enu_body
    q = matrix_to_quat(r).reshape(n, 4)
    v_enu = np.stack([ins.column(c).to_numpy().astype(float) for c in ("ve", "vn", "vu")], -1)
    v = np.einsum("nij,nj->ni", r_loc_enu, v_enu)
    cols = {
        "t_ns": ins.column("t_ns").to_numpy().astype(np.int64) - int(t0_abs) + T0_OFFSET_NS,
        "x": xyz[:, 0],
        "y": xyz[:, 1],
        "z": xyz[:, 2],
        "qw": q[:, 0],
        "qx": q[:, 1],
        "qy": q[:, 2],
        "qz": q[:, 3],
        "vx": v[:, 0],
        "vy": v[:, 1],
        "vz": v[:, 2],
        "rtk_status": ins.column("rtk_status").to_numpy().astype(np.int64),
    }
    for key in ("clip_id", "agent_id"):
        if key in ins.column_names:
            cols[key] = ins.column(key)
    return _order(columns_to_table(EgoPoseRow, _complete(EgoPoseRow, cols, n)), ins)


def map_origin(poses: pa.Table, reference_agent: str) -> tuple[float, float, str]:
    """x0, y0 of the reference agent's first pose in a local map (another agent's if it has
    none): the clean world of a clip whose poses have no geodetic reference is the map
    shifted in the xy-plane to that point (CATS-V2V A.3), z kept."""
    if poses.num_rows == 0:
        raise ValueError("no pose rows")
    agents = (poses.column("agent_id").to_pylist() if "agent_id" in poses.column_names
              else [reference_agent] * poses.num_rows)
    t = poses.column("t_ns").to_numpy()
    mask = np.array([a == reference_agent for a in agents])
    used = reference_agent
    if not mask.any():
        mask = np.ones(len(t), bool)
        used = str(agents[int(np.argmin(t))])
    i = np.flatnonzero(mask)[int(np.argmin(t[mask]))]
    return float(poses.column("x")[i].as_py()), float(poses.column("y")[i].as_py()), used


def map_poses_to_world(poses: pa.Table, origin_xy: tuple[float, float], t0_abs: int
                       ) -> pa.Table:
    """Raw ``ego_poses`` in a local map (absolute time) -> clean ``ego_poses``: relative time,
    xy shifted to the clip origin; orientation, z and velocities are unchanged."""
    out = shift_times(poses, "ego_poses", t0_abs)
    for c, o in zip(("x", "y"), origin_xy, strict=True):
        i = out.column_names.index(c)
        out = out.set_column(i, out.schema.field(c), pc.subtract(out.column(c),
                                                                 pa.scalar(float(o))))
    return out


def gnss_to_local(gnss: pa.Table, frame: LocalFrame | None, t0_abs: int) -> pa.Table:
    """Raw ``gnss`` -> clean: the fix as local x/y/z, lat/lon/alt null, relative time.

    Without a local frame (a clip with no INS and no GNSS origin) positions are dropped too.
    """
    n = gnss.num_rows
    cols: dict[str, object] = {
        "t_ns": gnss.column("t_ns").to_numpy().astype(np.int64) - int(t0_abs) + T0_OFFSET_NS,
        "status": gnss.column("status").to_numpy().astype(np.int64),
    }
    if "sigma_h" in gnss.column_names:
        cols["sigma_h"] = gnss.column("sigma_h")
    if frame is not None and n:
        lat = gnss.column("lat").to_numpy(zero_copy_only=False).astype(float)
        lon = gnss.column("lon").to_numpy(zero_copy_only=False).astype(float)
        alt = gnss.column("alt").to_numpy(zero_copy_only=False).astype(float)
        xyz = frame.to_local(lat, lon, alt).reshape(n, 3)  # NaN in -> NaN out (no fix)
        cols.update(x=xyz[:, 0], y=xyz[:, 1], z=xyz[:, 2])
    for key in ("clip_id", "agent_id"):
        if key in gnss.column_names:
            cols[key] = gnss.column(key)
    return _order(columns_to_table(GnssRow, _complete(GnssRow, cols, n)), gnss)


def _complete(model: type, cols: dict[str, object], n: int) -> dict[str, object]:
    """Partition keys may be absent from a partition file: fill them as empty strings to drop."""
    for key in ("clip_id", "agent_id"):
        if key not in cols and key in model.model_fields:  # type: ignore[attr-defined]
            cols[key] = pa.array([""] * n, pa.string())
    return cols


def _order(table: pa.Table, source: pa.Table) -> pa.Table:
    """Drop partition columns the source did not carry (they live in the path)."""
    drop = [
        k
        for k in ("clip_id", "agent_id")
        if k in table.column_names and k not in source.column_names
    ]
    return table.drop_columns(drop) if drop else table


def epoch_unit_of(v: float) -> str | None:
    """The unit (s, ms, us, ns) in which ``v`` is a 1990..2100 epoch time, else None."""
    for u, k in UNITS_PER_S.items():
        if EPOCH_LO_S * k <= v <= EPOCH_HI_S * k:
            return u
    return None


def relative_number(v: float, t0_abs: int) -> float:
    """An absolute epoch time in any unit -> the clip's relative axis in the same unit."""
    u = epoch_unit_of(v)
    if u is None:
        return v
    k = UNITS_PER_S[u]
    if u == "ns":
        return float(int(v) - int(t0_abs) + T0_OFFSET_NS)
    return v - t0_abs * k / 1e9 + T0_OFFSET_NS * k / 1e9


def relative_text(text: str, t0_abs: int) -> str:
    """Rewrite epoch times written in free text (QA details: "abs 1700000000000000000 ns") to
    relative ones; bare 9-11 digit integers are left alone unless they carry decimals."""

    def sub(m: re.Match[str]) -> str:
        digits, frac = m.group(1), m.group(2) or ""
        if len(digits) < 12 and not frac:
            return m.group(0)
        v = float(digits + frac)
        u = epoch_unit_of(v)
        if u is None:
            return m.group(0)
        if u == "ns" or not frac:
            return str(
                int(digits)
                - int(t0_abs) * UNITS_PER_S[u] // 10**9
                + T0_OFFSET_NS * UNITS_PER_S[u] // 10**9
            )
        return f"{relative_number(v, t0_abs):.{len(frac) - 1}f}"

    return NUMBER.sub(sub, text)


def scrub_table(table: pa.Table, t0_abs: int, numeric: tuple[str, ...] = ()) -> pa.Table:
    """Copied tables: epoch times in strings (and the named numeric columns) made relative."""
    for i, f in enumerate(table.schema):
        col = table.column(i)
        if pa.types.is_string(f.type) or pa.types.is_large_string(f.type):
            texts = [None if v is None else relative_text(v, t0_abs) for v in col.to_pylist()]
            table = table.set_column(i, f, pa.array(texts, f.type))
        elif f.name in numeric and (pa.types.is_floating(f.type) or pa.types.is_integer(f.type)):
            vals = [None if v is None else relative_number(v, t0_abs) for v in col.to_pylist()]
            table = table.set_column(i, f, pa.array(vals, pa.float64()).cast(f.type, safe=False))
    return table
