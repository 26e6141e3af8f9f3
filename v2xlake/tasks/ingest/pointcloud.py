"""``sensor_msgs/PointCloud2`` -> point columns, with NumPy views on the message buffer.

The message's ``data`` is one byte buffer of ``height * row_step`` bytes; a structured dtype
built from its ``PointField`` list (names, offsets, datatypes, ``point_step``, endianness)
turns it into a record array without copying; one compiled pass (``_compact``) reads each
record once and writes the columns. No per-point Python. The time field is converted to int64
absolute GNSS ns according to ``clip.yaml`` (unit and reference), because drivers disagree:
Ouster ``t`` is uint32 ns from the header stamp, Velodyne ``time`` float32 s from the header,
the simulator ``timestamp`` float64 absolute seconds.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numba import njit

from v2xlake.schemas.clip import LidarFields, PointTimeField, TimeReference, TimeUnit

# sensor_msgs/PointField datatype constants
POINTFIELD_DTYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
UNIT_NS = {TimeUnit.S: 1_000_000_000, TimeUnit.MS: 1_000_000, TimeUnit.US: 1_000, TimeUnit.NS: 1}
SCAN_TIME = PointTimeField(field="", unit=TimeUnit.NS, reference=TimeReference.HEADER)


def cloud_dtype(fields: list[Any], point_step: int, is_bigendian: bool) -> np.dtype:
    """Structured dtype of one point, honouring offsets and padding (``itemsize=point_step``)."""
    order = ">" if is_bigendian else "<"
    names, formats, offsets = [], [], []
    for f in fields:
        code = POINTFIELD_DTYPES.get(int(f.datatype))
        if code is None:
            raise ValueError(f"PointField {f.name!r} has unknown datatype {f.datatype}")
        base = np.dtype(order + code)
        names.append(f.name)
        formats.append(base if int(f.count) <= 1 else (base, int(f.count)))
        offsets.append(int(f.offset))
    return np.dtype({"names": names, "formats": formats, "offsets": offsets,
                     "itemsize": int(point_step)})


def cloud_array(msg: Any) -> np.ndarray:
    """The points of a PointCloud2 as a structured (N,) view (a copy only when rows are padded)."""
    dt = cloud_dtype(list(msg.fields), msg.point_step, bool(msg.is_bigendian))
    n_row = int(msg.width) * int(msg.point_step)
    h = int(msg.height)
    data = np.asarray(msg.data, dtype=np.uint8)
    if data.size < h * int(msg.row_step) or int(msg.row_step) < n_row:
        raise ValueError(f"PointCloud2 buffer holds {data.size} bytes, header promises "
                         f"{h} rows x {msg.row_step} bytes (point_step {msg.point_step})")
    if int(msg.row_step) != n_row:  # padded rows: drop the padding
        data = data[: h * int(msg.row_step)].reshape(h, int(msg.row_step))[:, :n_row].copy()
    return np.frombuffer(data, dtype=dt, count=h * int(msg.width))


def time_origin(tf: PointTimeField, stamp_ns: int, is_float: bool) -> tuple[float, int]:
    """``(off, base)`` with ``t_ns = (v - off) * scale + base`` for a raw time value ``v``:
    relative times add the header stamp; absolute float times first subtract a whole second
    (``off``, in the field's unit) so the product keeps ns resolution in float64."""
    if tf.reference is TimeReference.HEADER:
        return 0.0, stamp_ns
    if not is_float:
        return 0.0, 0
    base = stamp_ns // 1_000_000_000 * 1_000_000_000
    return base / UNIT_NS[tf.unit], base


def point_times_ns(values: np.ndarray, tf: PointTimeField, stamp_ns: int) -> np.ndarray:
    """Per-point time as int64 absolute ns (float arithmetic in place: one temporary)."""
    scale = UNIT_NS[tf.unit]
    is_float = not np.issubdtype(values.dtype, np.integer)
    off, base = time_origin(tf, stamp_ns, is_float)
    if not is_float:
        t = values.astype(np.int64)
        if scale != 1:
            t *= scale
        t += base
        return t
    v = values.astype(np.float64)
    v -= off
    v *= scale
    np.rint(v, out=v)
    t = v.astype(np.int64)
    t += base
    return t


@dataclass
class DecodedCloud:
    """One scan as columns; non-finite and no-return points are already dropped and counted
    (``n_nan``, ``n_zero``); the time span covers every finite point, returns or not."""

    stamp_ns: int
    t_ns: np.ndarray
    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    intensity: np.ndarray
    ring: np.ndarray
    return_id: np.ndarray
    n_nan: int
    t_start_ns: int
    t_end_ns: int
    n_zero: int = 0

    @property
    def n_points(self) -> int:
        return int(self.x.size)


def _source(arr: np.ndarray, name: str | None, what: str) -> np.ndarray | None:
    """The field's values as a strided 1-D view (first element of a ``count > 1`` field)."""
    if name is None:
        return None
    if arr.dtype.names is None or name not in arr.dtype.names:
        raise KeyError(f"{what} field {name!r} not in PointCloud2 fields {arr.dtype.names}")
    col = arr[name]
    return col[:, 0] if col.ndim > 1 else col


@njit(cache=True, nogil=True)
def _compact(x: np.ndarray, y: np.ndarray, z: np.ndarray, t: np.ndarray, inten: np.ndarray,
             ring: np.ndarray, ret: np.ndarray, has: np.ndarray, t_float: bool, scale: int,
             off: float, base: int, min_r2: float, ox: np.ndarray, oy: np.ndarray,
             oz: np.ndarray, ot: np.ndarray, oi: np.ndarray, oring: np.ndarray, oret: np.ndarray
             ) -> tuple[int, int, int, int]:
    """One pass over the records: keep points with finite x, y, z beyond the minimum range
    (no-return points sit at the origin), convert each field to its column type and the time
    to int64 ns as ``point_times_ns`` does (``time_origin``); returns the number kept, the
    number dropped as no-return, and the time span of every finite point. ``has`` flags
    intensity, ring, return (absent: zeros). One pass matters: the record buffer is read from
    memory once, where column-by-column NumPy reads it once per column (strided reads touch
    every cache line)."""
    k = 0
    n_zero = 0
    t_min: Any = np.iinfo(np.int64).max
    t_max: Any = np.iinfo(np.int64).min
    for j in range(x.size):
        xv, yv, zv = np.float64(x[j]), np.float64(y[j]), np.float64(z[j])
        if not (np.isfinite(xv) and np.isfinite(yv) and np.isfinite(zv)):
            continue
        if t_float:
            tv = np.int64(np.rint((np.float64(t[j]) - off) * scale)) + base
        else:
            tv = np.int64(t[j]) * scale + base
        if tv < t_min:
            t_min = tv
        if tv > t_max:
            t_max = tv
        if xv * xv + yv * yv + zv * zv <= min_r2:
            n_zero += 1
            continue
        ox[k], oy[k], oz[k] = xv, yv, zv
        ot[k] = tv
        oi[k] = inten[j] if has[0] else 0
        oring[k] = ring[j] if has[1] else 0
        oret[k] = ret[j] if has[2] else 0
        k += 1
    return k, n_zero, t_min, t_max


def check_integer_field(col: np.ndarray, name: str, what: str, hi: int) -> None:
    """A ring / return field must hold whole numbers in [0, hi]: a float field mapped there
    (intensity, a time) would be cast to garbage rings without a word."""
    if np.issubdtype(col.dtype, np.integer):
        return
    v = np.asarray(col, np.float64)
    v = v[np.isfinite(v)]
    if v.size and (np.any(v != np.rint(v)) or v.min() < 0 or v.max() > hi):
        raise ValueError(
            f"{what} field {name!r} is {col.dtype} with non-integer values (e.g. "
            f"{v[np.flatnonzero(v != np.rint(v))[:3]].tolist() or [v.min(), v.max()]}); "
            f"{what} must be an integer field in 0..{hi}: map the right field or set "
            f"{what}: null")


def check_time_reference(tf: PointTimeField, stamp_ns: int, t0: int, t1: int,
                         max_offset_ns: int) -> None:
    """Per-point times must lie near the header stamp whatever their declared reference: a
    header-relative field declared absolute lands ~50 years off, an absolute field declared
    header-relative ~50 years ahead; both are refused, saying which it looks like."""
    worst = max(abs(t0 - stamp_ns), abs(t1 - stamp_ns))
    if worst <= max_offset_ns:
        return
    rel = (t0 - stamp_ns) / 1e9, (t1 - stamp_ns) / 1e9
    day = 86_400 * 1_000_000_000
    if tf.reference is TimeReference.ABSOLUTE and abs(t1) < day:  # values near zero
        hint = "its values look relative to the header stamp: set reference: header"
    elif tf.reference is TimeReference.HEADER and abs(t1 - 2 * stamp_ns) < day:
        hint = "its values look like absolute epoch times: set reference: absolute"
    else:
        hint = "check the unit"
    raise ValueError(
        f"per-point time field {tf.field!r} (declared {tf.reference.value}, unit "
        f"{tf.unit.value}) puts the points {rel[0]:.6g}..{rel[1]:.6g} s from the header stamp "
        f"{stamp_ns} ns, beyond the {max_offset_ns / 1e9:g} s allowed "
        f"(ingest.max_point_time_offset_s); {hint}")


def decode_cloud(msg: Any, fields: LidarFields, stamp_ns: int, *, min_range_m: float = 0.0,
                 max_time_offset_ns: int | None = None) -> DecodedCloud:
    """Decode one PointCloud2 according to the clip.yaml field mapping in one compiled pass
    (``_compact``): non-finite and no-return points dropped and counted, columns contiguous,
    time in int64 ns (checked against the header stamp when ``max_time_offset_ns`` is set)."""
    arr = cloud_array(msg)
    if not arr.dtype.isnative:
        arr = arr.astype(arr.dtype.newbyteorder("="))  # big-endian cloud: one native copy
    n = arr.size
    tf = fields.time or SCAN_TIME  # radar without per-point time: the header stamp
    x, y, z = (_source(arr, name, what) for what, name in (
        ("x", fields.x), ("y", fields.y), ("z", fields.z)))
    t = _source(arr, fields.time.field, "time") if fields.time else np.zeros(n, np.uint8)
    assert x is not None and y is not None and z is not None and t is not None
    dummy = np.zeros(1, np.uint8)
    opt = [_source(arr, fields.intensity, "intensity"), _source(arr, fields.ring, "ring"),
           _source(arr, fields.return_id, "return_id")]
    has = np.array([o is not None for o in opt])
    if opt[1] is not None:
        check_integer_field(opt[1], str(fields.ring), "ring", 65535)
    if opt[2] is not None:
        check_integer_field(opt[2], str(fields.return_id), "return_id", 255)
    inten, ring, ret = (o if o is not None else dummy for o in opt)
    ox, oy, oz, oi = (np.empty(n, np.float32) for _ in range(4))
    ot, oring, oret = np.empty(n, np.int64), np.empty(n, np.uint16), np.empty(n, np.uint8)
    t_float = not np.issubdtype(t.dtype, np.integer)
    off, base = time_origin(tf, stamp_ns, t_float)
    k, n_zero, t0, t1 = _compact(x, y, z, t, inten, ring, ret, has, t_float, UNIT_NS[tf.unit],
                                 off, base, float(min_range_m) ** 2, ox, oy, oz, ot, oi, oring,
                                 oret)
    if k + n_zero == 0 and n:  # only non-finite points: the scan took place, keep its span
        t_all = point_times_ns(t, tf, stamp_ns)
        t0, t1 = int(t_all.min()), int(t_all.max())
    elif k + n_zero == 0:
        t0 = t1 = stamp_ns
    if max_time_offset_ns is not None and fields.time is not None:
        check_time_reference(tf, stamp_ns, int(t0), int(t1), max_time_offset_ns)
    return DecodedCloud(
        stamp_ns=stamp_ns, t_ns=ot[:k], x=ox[:k], y=oy[:k], z=oz[:k], intensity=oi[:k],
        ring=oring[:k], return_id=oret[:k], n_nan=n - k - n_zero, t_start_ns=int(t0),
        t_end_ns=int(t1), n_zero=n_zero,
    )


@dataclass
class DecodedRadar:
    """One radar scan as columns; non-finite detections dropped and counted."""

    t_ns: np.ndarray
    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    velocity: np.ndarray
    rcs: np.ndarray
    n_nan: int
    t_start_ns: int
    t_end_ns: int

    @property
    def n_points(self) -> int:
        return int(self.x.size)


def decode_radar(msg: Any, fields: LidarFields, stamp_ns: int, *,
                 max_time_offset_ns: int | None = None) -> DecodedRadar:
    """A 4D radar's ``PointCloud2`` (x, y, z, radial velocity, RCS, per-point time or one
    time per scan) -> columns. Radar scans are small (hundreds to a few thousand
    detections): plain NumPy on the structured view."""
    arr = cloud_array(msg)
    if not arr.dtype.isnative:
        arr = arr.astype(arr.dtype.newbyteorder("="))
    n = arr.size
    cols = {}
    for what, name in (("x", fields.x), ("y", fields.y), ("z", fields.z),
                       ("velocity", fields.velocity), ("rcs", fields.rcs)):
        col = _source(arr, name, what)
        cols[what] = (np.asarray(col, np.float64) if col is not None
                      else np.full(n, np.nan if what == "rcs" else 0.0))
    if fields.time is not None:
        t_src = _source(arr, fields.time.field, "time")
        assert t_src is not None
        t = point_times_ns(np.asarray(t_src), fields.time, stamp_ns)
    else:
        t = np.full(n, stamp_ns, np.int64)
    ok = np.isfinite(cols["x"]) & np.isfinite(cols["y"]) & np.isfinite(cols["z"]) & \
        np.isfinite(cols["velocity"])
    t0, t1 = (int(t.min()), int(t.max())) if n else (stamp_ns, stamp_ns)
    if max_time_offset_ns is not None and fields.time is not None and n:
        check_time_reference(fields.time, stamp_ns, t0, t1, max_time_offset_ns)
    f32 = {k: v[ok].astype(np.float32) for k, v in cols.items()}
    return DecodedRadar(t_ns=t[ok], x=f32["x"], y=f32["y"], z=f32["z"],
                        velocity=f32["velocity"], rcs=f32["rcs"], n_nan=int(n - ok.sum()),
                        t_start_ns=t0, t_end_ns=t1)
