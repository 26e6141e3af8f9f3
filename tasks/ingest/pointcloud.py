"""``sensor_msgs/PointCloud2`` -> point columns, with NumPy views on the message buffer.

The message's ``data`` is one byte buffer of ``height * row_step`` bytes; a structured dtype
built from its ``PointField`` list (names, offsets, datatypes, ``point_step``, endianness)
turns it into a record array without copying, and each column we keep is one strided copy.
No per-point Python, so decoding runs at memory speed. The time field is converted to int64
absolute GNSS ns according to ``clip.yaml`` (unit and reference), because drivers disagree:
Ouster ``t`` is uint32 ns from the header stamp, Velodyne ``time`` float32 s from the header,
the simulator ``timestamp`` float64 absolute seconds.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from schemas.clip import LidarFields, PointTimeField, TimeReference, TimeUnit

# sensor_msgs/PointField datatype constants
POINTFIELD_DTYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
UNIT_NS = {TimeUnit.S: 1_000_000_000, TimeUnit.MS: 1_000_000, TimeUnit.US: 1_000, TimeUnit.NS: 1}


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


def point_times_ns(values: np.ndarray, tf: PointTimeField, stamp_ns: int) -> np.ndarray:
    """Per-point time as int64 absolute ns."""
    scale = UNIT_NS[tf.unit]
    if np.issubdtype(values.dtype, np.integer):
        t = values.astype(np.int64) * scale
        return t + stamp_ns if tf.reference is TimeReference.HEADER else t
    v = values.astype(np.float64)
    if tf.reference is TimeReference.HEADER:
        return np.rint(v * scale).astype(np.int64) + stamp_ns
    # absolute float: subtract a whole second first so the product keeps ns resolution
    base = stamp_ns // 1_000_000_000 * 1_000_000_000
    base_units = base / scale
    return np.rint((v - base_units) * scale).astype(np.int64) + base


@dataclass
class DecodedCloud:
    """One scan as columns; non-finite points are already dropped and counted."""

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

    @property
    def n_points(self) -> int:
        return int(self.x.size)


def _column(arr: np.ndarray, name: str | None, dtype: type, n: int, what: str,
            keep: np.ndarray | None) -> np.ndarray:
    """One field as a contiguous array of ``dtype``, filtered by ``keep`` in the same pass."""
    if name is None:
        return np.zeros(n if keep is None else int(np.count_nonzero(keep)), dtype=dtype)
    if arr.dtype.names is None or name not in arr.dtype.names:
        raise KeyError(f"{what} field {name!r} not in PointCloud2 fields {arr.dtype.names}")
    col = arr[name]
    if col.ndim > 1:
        col = col[:, 0]
    if keep is not None:
        col = col[keep]
    return np.ascontiguousarray(col, dtype=dtype)


def decode_cloud(msg: Any, fields: LidarFields, stamp_ns: int) -> DecodedCloud:
    """Decode one PointCloud2 according to the clip.yaml field mapping."""
    arr = cloud_array(msg)
    n = arr.size
    for what, name in (("x", fields.x), ("y", fields.y), ("z", fields.z),
                       ("time", fields.time.field)):
        if arr.dtype.names is None or name not in arr.dtype.names:
            raise KeyError(f"{what} field {name!r} not in PointCloud2 fields {arr.dtype.names}")
    finite = np.isfinite(arr[fields.x])
    finite &= np.isfinite(arr[fields.y])
    finite &= np.isfinite(arr[fields.z])
    n_ok = int(np.count_nonzero(finite))
    keep = None if n_ok == n else finite
    t = point_times_ns(arr[fields.time.field] if keep is None else
                       arr[fields.time.field][keep], fields.time, stamp_ns)
    if t.size:
        t0, t1 = int(t.min()), int(t.max())
    elif n:  # only non-finite points: the scan still took place, keep its time span
        t_all = point_times_ns(arr[fields.time.field], fields.time, stamp_ns)
        t0, t1 = int(t_all.min()), int(t_all.max())
    else:
        t0 = t1 = stamp_ns
    return DecodedCloud(
        stamp_ns=stamp_ns, t_ns=t,
        x=_column(arr, fields.x, np.float32, n, "x", keep),
        y=_column(arr, fields.y, np.float32, n, "y", keep),
        z=_column(arr, fields.z, np.float32, n, "z", keep),
        intensity=_column(arr, fields.intensity, np.float32, n, "intensity", keep),
        ring=_column(arr, fields.ring, np.uint16, n, "ring", keep),
        return_id=_column(arr, fields.return_id, np.uint8, n, "return_id", keep),
        n_nan=n - n_ok, t_start_ns=t0, t_end_ns=t1,
    )
