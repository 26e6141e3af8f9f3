"""Point files (``.pcd``, ``.ply``, ``.npy``, ``.bin``) read without a point library and
scanned for absolute time in any field."""

from __future__ import annotations

import io

import numpy as np

from v2xlake.audit.report import Finding
from v2xlake.audit.rules import COLOUR_FIELDS, EPOCH_HI_S, EPOCH_LO_S, UNIT_SCALE, epoch_unit


def scan_points(cols: dict[str, np.ndarray], where: str) -> list[Finding]:
    """Absolute time in point data: any value of any field in the epoch window (first unit
    that matches). Unlike a table column, one value is enough: no coordinate, intensity,
    ring or relative time of a real point is 6e8 or more."""
    out: list[Finding] = []
    for name, v in cols.items():
        if name.lower() in COLOUR_FIELDS or not np.issubdtype(np.asarray(v).dtype, np.number):
            continue
        a = np.asarray(v, dtype=np.float64).ravel()
        a = a[np.isfinite(a)]
        for unit, k in UNIT_SCALE.items():
            hit = (a >= EPOCH_LO_S * k) & (a <= EPOCH_HI_S * k)
            if hit.any():
                out.append(Finding(
                    "absolute_time", f"{where}:{name}",
                    f"{int(hit.sum())} of {a.size} values in the 1990-2100 epoch window in "
                    f"{unit} (e.g. {float(a[hit][0])!r}): never a real point's value"))
                break
    return out


_PCD_TYPES = {("F", 4): "f4", ("F", 8): "f8", ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4",
              ("U", 8): "u8", ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4", ("I", 8): "i8"}


def read_pcd(data: bytes) -> tuple[bytes, dict[str, np.ndarray]]:
    """(header bytes, field -> values) of a PCD file, ascii or binary, laid out as its
    header's FIELDS / SIZE / TYPE / COUNT say. Raises ValueError on what it cannot read."""
    end = data.find(b"\nDATA ")
    if end < 0:
        raise ValueError("no DATA line in the PCD header")
    eol = data.find(b"\n", end + 1)
    eol = len(data) if eol < 0 else eol
    header, body = data[: eol + 1], data[eol + 1 :]
    h: dict[str, list[str]] = {}
    for line in header.decode("ascii", "replace").splitlines():
        parts = line.split()
        if parts and not parts[0].startswith("#"):
            h[parts[0].upper()] = parts[1:]
    names, sizes, types = h.get("FIELDS", []), h.get("SIZE", []), h.get("TYPE", [])
    counts = [int(c) for c in h.get("COUNT", ["1"] * len(names))]
    if not names or not len(names) == len(sizes) == len(types) == len(counts):
        raise ValueError("PCD header FIELDS/SIZE/TYPE/COUNT disagree")
    n = int(h["POINTS"][0]) if "POINTS" in h else int(h["WIDTH"][0]) * int(h["HEIGHT"][0])
    fmts = [_PCD_TYPES[(t.upper(), int(z))] for t, z in zip(types, sizes, strict=True)]
    kind = h["DATA"][0].lower()
    cols: dict[str, np.ndarray] = {}
    if kind == "ascii":
        arr = np.loadtxt(io.BytesIO(body), dtype=np.float64, ndmin=2) if body.strip() else (
            np.zeros((0, sum(counts))))
        j = 0
        for name, c in zip(names, counts, strict=True):
            cols[name] = arr[:, j : j + c]
            j += c
    elif kind == "binary":
        dt = np.dtype([(f"f{i}", "<" + f, (c,)) for i, (f, c) in enumerate(
            zip(fmts, counts, strict=True))])
        rec = np.frombuffer(body, dtype=dt, count=n)
        cols = {name: rec[f"f{i}"] for i, name in enumerate(names)}
    else:
        raise ValueError(f"PCD DATA {kind} is not decoded by the audit")
    return header, cols


_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2",
              "int16": "i2", "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4",
              "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4", "double": "f8",
              "float64": "f8"}


def read_ply(data: bytes) -> tuple[bytes, dict[str, np.ndarray]]:
    """(header bytes, "element.property" -> values) of a PLY file's elements up to the first
    one with a list property (a point cloud's vertices come first)."""
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise ValueError("not a PLY file")
    eol = data.index(b"\n", end)
    header, body = data[: eol + 1], data[eol + 1 :]
    fmt = ""
    elements: list[tuple[str, int, list[tuple[str, str]]]] = []
    for line in header.decode("ascii", "replace").splitlines():
        p = line.split()
        if p[:1] == ["format"]:
            fmt = p[1]
        elif p[:1] == ["element"]:
            elements.append((p[1], int(p[2]), []))
        elif p[:1] == ["property"] and elements:
            elements[-1][2].append((p[-1], "list" if p[1] == "list" else _PLY_TYPES[p[1]]))
    order = {"binary_little_endian": "<", "binary_big_endian": ">"}.get(fmt)
    cols: dict[str, np.ndarray] = {}
    pos = 0
    lines = body.splitlines() if fmt == "ascii" else []
    for name, n, props in elements:
        if any(t == "list" for _, t in props):
            break
        if fmt == "ascii":
            arr = np.loadtxt(lines[pos : pos + n], dtype=np.float64, ndmin=2)
            pos += n
            cols.update({f"{name}.{p}": arr[:, i] for i, (p, _) in enumerate(props)})
        elif order is not None:
            dt = np.dtype([(p, order + t) for p, t in props])
            rec = np.frombuffer(body, dtype=dt, count=n, offset=pos)
            pos += n * dt.itemsize
            cols.update({f"{name}.{p}": rec[p] for p, _ in props})
        else:
            raise ValueError(f"PLY format {fmt!r}")
    return header, cols


def scan_bin(data: bytes, where: str) -> list[Finding]:
    """A headerless ``.bin`` / ``.pcd.bin`` (nuScenes N x 5, KITTI N x 4 float32): every
    float32 value; and, read as float64 N x 3..6, any column lying wholly in the window (a
    float64 file would otherwise hide its times from the float32 reading)."""
    if len(data) % 4:
        return [Finding("unscannable", where, f"{len(data)} bytes: not float32 points")]
    out = scan_points({"float32": np.frombuffer(data, "<f4")}, where)
    if out or len(data) % 8:
        return out
    d = np.frombuffer(data, "<f8")
    for k in (5, 4, 6, 3):
        if d.size % k == 0 and d.size // k >= 2:
            m = d.reshape(-1, k)
            for j in range(k):
                if epoch_unit(float(np.min(m[:, j])), float(np.max(m[:, j]))) is not None:
                    return [Finding("absolute_time", f"{where}:float64 column {j}",
                                    f"read as float64 N x {k}, every value of column {j} lies "
                                    f"in the 1990-2100 epoch window (e.g. {float(m[0, j])!r})")]
    return out


def scan_npy(data: bytes, where: str) -> list[Finding]:
    arr = np.load(io.BytesIO(data), allow_pickle=False)
    if arr.dtype.names:
        return scan_points({n: arr[n] for n in arr.dtype.names}, where)
    if not np.issubdtype(arr.dtype, np.number):
        return [Finding("unscannable", where, f"array of dtype {arr.dtype}")]
    return scan_points({"values": arr}, where)
