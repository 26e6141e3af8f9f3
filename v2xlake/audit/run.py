"""Privacy audit of the clean zone or of a release folder: nothing identifying may leave raw.

What it looks for, and why each rule has the shape it has:

* absolute time: integer columns (or JSON/YAML/text numbers) whose every value lies in the
  1990-2100 epoch window in s, ms, us or ns. A column named ``*_ns`` / ``*_us`` / ``*_ms`` /
  ``*_s`` is only tested in its own unit, because a long clip's relative time in ns (6e11 ns
  = 10 min) overlaps the epoch window in ms.
* latitude/longitude: any column or JSON key named lat/lon/latitude/longitude/lng/gps*, with
  values; and, by value, a pair of float columns of one table that (1) are both tightly
  clustered (spread < ``latlon_max_spread_deg``) away from zero (|v| > 1) with many decimals,
  (2) read as degrees, span about as many metres as the clip's own ego poses do (0.2x-5x),
  and (3) are smooth in row order like a sampled trajectory. Local ENU metres of a moving clip
  spread far wider than 0.05; constant columns (calibration, a parked roadside unit) have no
  spread; the velocity of a cruising car is tightly clustered but, read as degrees, spans
  centimetres (numerically constant) or kilometres (sensor noise) and is rough. The value
  rule is skipped when the zone's ego poses show clips that hardly move (< 5 m): then
  metres and degrees cannot be told apart; the name rule still applies.
* image metadata: PNG text/EXIF/time chunks (parsed here) and JPEG APP1/COM segments.
* unblurred faces / plates: the anonymizer's detector is re-run on a sample of images;
  a detection above the audit's score threshold is a finding.
* rosbags (``.bag`` ROS 1, ``.db3`` / ``.mcap`` ROS 2; a folder with ``metadata.yaml`` is read
  as one bag, a bare storage file on its own): opened with ``rosbags.highlevel.AnyReader``,
  every message is deserialized and walked. Any ``builtin_interfaces/Time`` (header stamps,
  tf stamps) and any log time in the epoch window is absolute time; ``NavSatFix`` and any
  message with a lat/lon-named field is latitude/longitude; strings go through the text rule;
  ``PointCloud2`` fields go through the point rule below; ``Image`` / ``CompressedImage``
  messages join the dataset images the detector re-checks (one sample over files and bags).
  A bag that cannot be opened or read is an ``unreadable`` finding, never a silent skip.
* point files (``.pcd`` by its header's FIELDS/SIZE/TYPE/COUNT, ascii or binary; ``.ply``
  by its header; ``.npy``; ``.bin`` / ``.pcd.bin`` as nuScenes/KITTI write them): any value
  of any field in the epoch window in s/ms/us/ns is absolute time (an x of 1.7e9 is never a
  real point; packed ``rgb``/``rgba`` fields are colours and skipped). A ``.bin`` has no
  header: it is read as float32 (any value), and as float64 N x 3..6 where a whole column
  lies in the window (reading float32 points as float64 makes isolated values land there).
  ``binary_compressed`` PCDs are not decoded: an ``unreadable`` finding.
* everything else: a file whose extension the audit has no scanner for is an
  ``unscannable`` finding, not skipped: what cannot be looked at cannot be released on the
  audit's word. Text-like files (``.md``, ``.txt``, ``.csv``, ``.xml``, no extension such as
  ``SHA256SUMS``) get the text rule.

Which folder: ``"clean"`` / ``"raw"`` are lake zones; any other name given with a lake is a
release name, checked like ``release verify`` checks it (never a path: ``../..`` is refused)
and required to exist; without a lake, ``zone`` is a local folder. ``release=NAME`` always
means ``releases/NAME``, even for a release called ``clean``.
"""

from __future__ import annotations

import io
import json
import math
import os
import re
import struct
import tempfile
from collections.abc import Iterator, Sequence
from contextlib import ExitStack
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.fs as pafs

from v2xlake.storage.files import read_parquet, read_parquet_head
from v2xlake.storage.lake import Lake

EPOCH_LO_S = 631_152_000  # 1990-01-01
EPOCH_HI_S = 4_102_444_800  # 2100-01-01
UNIT_SCALE = {"s": 1, "ms": 10**3, "us": 10**6, "ns": 10**9}
LATLON_NAME = re.compile(r"(^|_)(lat|lon|lng|latitude|longitude|gps|wgs84|geo)(_|$|itude)", re.I)
COUNT_NAME = re.compile(r"(size|bytes|count|^n_|_n$|num_|rows|points)", re.I)
TIME_KEY = re.compile(r"(time|stamp|date|_ns$|_us$|_ms$|^t$|^ts$)", re.I)
DIGITS = re.compile(rb"(?<![0-9A-Za-z])(?<![0-9]\.)([0-9]{9,19})(?:\.([0-9]+))?(?![0-9A-Za-z])")
IMAGE_EXT = (".png", ".jpg", ".jpeg")
TEXT_EXT = (".json", ".yaml", ".yml", ".txt", ".csv", ".xml", ".md")
BAG_EXT = (".bag", ".db3", ".mcap")
BAG_STORAGE_EXT = (".db3", ".mcap")  # the files a rosbag2 folder's metadata.yaml names
POINT_EXT = (".pcd", ".ply", ".npy", ".bin")
COLOUR_FIELDS = {"rgb", "rgba"}  # packed colours, not numbers
PNG_SIG = b"\x89PNG\r\n\x1a\n"
PNG_LEAK_CHUNKS = {b"tEXt", b"zTXt", b"iTXt", b"eXIf", b"tIME"}


@dataclass(frozen=True)
class Finding:
    # absolute_time | latlon | image_metadata | unblurred_face | unblurred_plate | unreadable
    # (could not be read or parsed) | unscannable (no scanner for this kind of file)
    kind: str
    location: str
    detail: str


class AuditError(ValueError):
    """The audit could not look at anything (a missing or empty lake, release or folder):
    an error, never "0 findings"."""


@dataclass
class AuditReport:
    findings: list[Finding] = field(default_factory=list)
    n_files: int = 0
    n_tables: int = 0
    n_images_checked: int = 0
    # projected head / plate locations (from the clip's boxes) in the checked images: blurred,
    # or searched by the audit's own detector and found empty (back of a head, occluded)
    n_regions: int = 0
    n_regions_blurred: int = 0
    n_regions_not_visible: int = 0

    @property
    def ok(self) -> bool:
        return not self.findings

    def summary(self) -> str:
        head = (
            f"audit: {self.n_files} files, {self.n_tables} tables, "
            f"{self.n_images_checked} images re-checked ({self.n_regions} projected head/plate "
            f"locations: {self.n_regions_blurred} blurred, {self.n_regions_not_visible} with "
            f"nothing visible): {len(self.findings)} findings"
        )
        return "\n".join([head, *(f"  [{f.kind}] {f.location}: {f.detail}" for f in self.findings)])


@dataclass(frozen=True)
class AuditConfig:
    latlon_max_spread_deg: float = 0.05
    latlon_min_rows: int = 10
    stationary_span_m: float = 5.0
    span_factor_lo: float = 0.2
    span_factor_hi: float = 5.0
    face_min_score: float = 0.6
    plate_min_score: float = 0.5
    text_max_bytes: int = 4 << 20
    # which files of a release folder are camera images to re-check with the detector (in a
    # lake zone they are exactly the blobs its camera_frames name); plots, BEV rasters, maps,
    # depth previews and release-note figures are not dataset images
    camera_image_pattern: str = r"(^|/)(blobs|samples|sweeps|images|image_\d+)/|(^|/)CAM_[A-Z_]+/"
    not_camera_pattern: str = r"(^|/)(maps?|plots?|figures?|depth_preview|bev|preview)(/|_)"
    # the audit's own scan plan (a different one from the blur's): faces at 1.5x in tiles and
    # at native size, plates natively and at 2x; projected regions at larger targets
    audit_face_fine_scale: float = 1.5
    # plates: natively over the frame (an upscaled text detector reads foliage and facades
    # as text), and in the projected vehicle faces at their own scale
    audit_plate_fine_scale: float | None = None
    region_face_target_px: float = 56.0
    region_plate_target_px: float = 128.0
    region_min_face_px: float = 10.0  # projected locations checked from these sizes
    region_min_plate_px: float = 16.0


# ------------------------------------------------------------------------------- rules
def epoch_unit(lo: float, hi: float, name: str = "") -> str | None:
    """The epoch unit in which both ``lo`` and ``hi`` fall in 1990..2100, else None."""
    m = re.search(r"_(ns|us|ms|s)$", name)
    units = [m.group(1)] if m else list(UNIT_SCALE)
    for u in units:
        k = UNIT_SCALE[u]
        if EPOCH_LO_S * k <= lo and hi <= EPOCH_HI_S * k:
            return u
    return None


def _decimals(v: np.ndarray) -> float:
    """Median count of decimals in the shortest round-trip text of float values (up to 200)."""
    v = v[np.isfinite(v)][:200]
    if v.size == 0:
        return 0.0
    d = [len(np.format_float_positional(x, unique=True, trim="-").partition(".")[2]) for x in v]
    return float(np.median(d))


def _tight_cluster(v: np.ndarray, bound: float, max_spread: float) -> bool:
    v = v[np.isfinite(v)]
    if v.size == 0:
        return False
    lo, hi = float(v.min()), float(v.max())
    med = float(np.median(v))
    return (
        abs(med) > 1.0
        and -bound <= lo
        and hi <= bound
        and 0 < hi - lo < max_spread
        and _decimals(v) >= 5
    )


def _smooth(v: np.ndarray) -> bool:
    """A trajectory sampled in time order is smooth (tiny 2nd differences); sensor noise is not."""
    v = v[np.isfinite(v)]
    rng = float(np.ptp(v)) if v.size else 0.0
    return v.size >= 3 and rng > 0 and float(np.std(np.diff(v, 2))) <= 0.05 * rng


def _extent_m(lat: np.ndarray, lon: np.ndarray) -> float:
    """Extent in metres of a (lat, lon) pair read as degrees (equirectangular is plenty here)."""
    la, lo = lat[np.isfinite(lat)], lon[np.isfinite(lon)]
    k = 111_320.0
    return float(max(np.ptp(la) * k, np.ptp(lo) * k * np.cos(np.radians(np.median(la)))))


def scan_table(
    t: pa.Table,
    where: str,
    cfg: AuditConfig,
    value_rule: bool = True,
    span_range: tuple[float, float] | None = None,
) -> list[Finding]:
    """Absolute-time and lat/lon findings for one table.

    ``span_range``: (low, high) metres a WGS84 pair of this zone would span, from the clips'
    own ego poses; a tightly clustered pair whose extent read as degrees falls outside it
    (velocities of a cruising car: centimetres or tens of kilometres) is not latitude/longitude.
    """
    out: list[Finding] = []
    floats: dict[str, np.ndarray] = {}
    for f in t.schema:
        col = t.column(f.name)
        typ = f.type
        if pa.types.is_dictionary(typ):
            col = col.cast(typ.value_type) if pa.types.is_string(typ.value_type) else col
            typ = col.type
        if pa.types.is_string(typ) or pa.types.is_large_string(typ):
            uniq = [v for v in pc.unique(col).to_pylist()[:5000] if v]
            hit = scan_text("\n".join(uniq).encode(), f"{where}:{f.name}")
            if hit:
                out.extend(hit)
                continue
        if pa.types.is_dictionary(typ):
            continue
        nonnull = col.null_count < len(col)
        if (
            LATLON_NAME.search(f.name)
            and nonnull
            and (pa.types.is_floating(typ) or pa.types.is_integer(typ) or pa.types.is_string(typ))
        ):
            out.append(
                Finding(
                    "latlon",
                    f"{where}:{f.name}",
                    "column named like latitude/longitude holds values",
                )
            )
            continue
        if (
            pa.types.is_integer(typ) or pa.types.is_floating(typ) or pa.types.is_timestamp(typ)
        ) and nonnull:
            if pa.types.is_timestamp(typ):
                out.append(
                    Finding("absolute_time", f"{where}:{f.name}", f"timestamp column of type {typ}")
                )
                continue
            mm = pc.min_max(col).as_py()
            lo, hi = mm["min"], mm["max"]
            if lo is not None and math.isfinite(lo) and math.isfinite(hi):
                unit = epoch_unit(float(lo), float(hi), f.name)
                if (
                    unit is not None
                    and COUNT_NAME.search(f.name)
                    and not re.search(r"_(ns|us|ms|s)$", f.name)
                ):
                    unit = None  # file sizes, point counts: big integers, not times
                if unit is not None and (
                    pa.types.is_integer(typ) or unit == "s" or TIME_KEY.search(f.name)
                ):
                    out.append(
                        Finding(
                            "absolute_time",
                            f"{where}:{f.name}",
                            f"all values in the 1990-2100 epoch window in {unit} "
                            f"(min {lo}, max {hi})",
                        )
                    )
                    continue
            if pa.types.is_floating(typ) and t.num_rows >= cfg.latlon_min_rows:
                floats[f.name] = col.to_numpy(zero_copy_only=False).astype(float)
    if value_rule:
        lats = [n for n, v in floats.items() if _tight_cluster(v, 90.0, cfg.latlon_max_spread_deg)]
        lons = [n for n, v in floats.items() if _tight_cluster(v, 180.0, cfg.latlon_max_spread_deg)]
        for a, b in ((a, b) for a in lats for b in lons if a != b):
            extent = _extent_m(floats[a], floats[b])
            lo, hi = span_range if span_range else (5.0, 5000.0)
            if lo <= extent <= hi and _smooth(floats[a]) and _smooth(floats[b]):
                out.append(
                    Finding(
                        "latlon",
                        f"{where}:{a},{b}",
                        "pair of float columns tightly clustered away from 0 with many decimals "
                        f"(medians {np.nanmedian(floats[a]):.6f}, {np.nanmedian(floats[b]):.6f}); "
                        f"read as degrees they span {extent:.0f} m, like the clip: WGS84 degrees",
                    )
                )
                break
    return out


def _walk_json(obj: Any, path: str) -> Iterator[tuple[str, str, Any]]:
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _walk_json(v, f"{path}.{k}" if path else str(k))
            if not isinstance(v, dict | list):
                yield path, str(k), v
    elif isinstance(obj, list):
        for i, v in enumerate(obj[:100000]):
            yield from _walk_json(v, f"{path}[{i}]")


def scan_structured(obj: Any, where: str) -> list[Finding]:
    """JSON / YAML documents: epoch-like numbers and lat/lon keys (first hit per key name)."""
    out: list[Finding] = []
    seen: set[tuple[str, str]] = set()
    for path, key, v in _walk_json(obj, ""):
        if isinstance(v, bool) or v is None:
            continue
        if (
            LATLON_NAME.search(key)
            and isinstance(v, int | float | str)
            and ("latlon", key) not in seen
        ):
            seen.add(("latlon", key))
            out.append(
                Finding(
                    "latlon", f"{where}:{path}.{key}".replace(":.", ":"), f"key {key!r} = {v!r}"
                )
            )
        elif isinstance(v, int | float) and math.isfinite(v) and ("time", key) not in seen:
            unit = epoch_unit(float(v), float(v), key)
            if (
                unit is not None
                and (isinstance(v, int) or unit == "s")
                and (TIME_KEY.search(key) or v > 1e12)
            ):
                seen.add(("time", key))
                out.append(
                    Finding(
                        "absolute_time",
                        f"{where}:{path}.{key}".replace(":.", ":"),
                        f"{key} = {v} is an epoch time in {unit}",
                    )
                )
    return out


def scan_text(data: bytes, where: str) -> list[Finding]:
    """Plain text: digit runs that are epoch times (>= 12 digits, or seconds with decimals)."""
    for m in DIGITS.finditer(data):
        ip = int(m.group(1))
        if len(m.group(1)) < 12 and not m.group(2):
            continue  # bare 9-11 digit integers are too often counters or ids
        unit = epoch_unit(float(ip), float(ip))
        if unit is not None:
            return [
                Finding(
                    "absolute_time",
                    where,
                    f"number {m.group(0).decode()} is an epoch time in {unit}",
                )
            ]
    return []


BENIGN_TEXT_KEYS = {b"Software"}  # e.g. matplotlib's own tag on release plots


def png_metadata(data: bytes) -> list[str]:
    """Leaking chunks of a PNG: text (except a bare ``Software`` tag), EXIF, time."""
    if not data.startswith(PNG_SIG):
        return ["not a PNG"]
    found = []
    pos = 8
    while pos + 8 <= len(data):
        (n,) = struct.unpack(">I", data[pos : pos + 4])
        ctype = data[pos + 4 : pos + 8]
        if ctype in PNG_LEAK_CHUNKS:
            key = data[pos + 8 : pos + 8 + min(n, 80)].split(b"\x00", 1)[0]
            if not (ctype in (b"tEXt", b"iTXt", b"zTXt") and key in BENIGN_TEXT_KEYS):
                found.append(ctype.decode("latin-1"))
        if ctype == b"IEND":
            break
        pos += 12 + n
    return found


def jpeg_metadata(data: bytes) -> list[str]:
    """APP1 (EXIF/XMP), other APPn with payload beyond JFIF, and COM segments of a JPEG."""
    if not data.startswith(b"\xff\xd8"):
        return ["not a JPEG"]
    found = []
    pos = 2
    while pos + 4 <= len(data) and data[pos] == 0xFF:
        marker = data[pos + 1]
        if marker in (0xD9, 0xDA):  # EOI / start of scan: metadata comes before
            break
        (n,) = struct.unpack(">H", data[pos + 2 : pos + 4])
        payload = data[pos + 4 : pos + 2 + n]
        if marker == 0xE1:
            found.append("APP1 " + ("EXIF" if payload.startswith(b"Exif") else "XMP/other"))
        elif marker == 0xFE:
            found.append("COM")
        elif 0xE2 <= marker <= 0xEF:
            found.append(f"APP{marker - 0xE0}")
        pos += 2 + n
    return found


# ------------------------------------------------------------------------------- points
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


# ------------------------------------------------------------------------------- rosbags
@dataclass(frozen=True)
class _BagImage:
    """One Image / CompressedImage message of a bag, for the detector re-check."""

    bag: str  # local path of the bag (file or rosbag2 folder)
    topic: str
    index: int  # n-th message on the topic
    location: str


_PF_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


def _cloud_columns(msg: Any) -> dict[str, np.ndarray]:
    """The fields of a ``sensor_msgs/PointCloud2`` as arrays."""
    step = int(msg.point_step)
    raw = np.ascontiguousarray(np.asarray(msg.data, dtype=np.uint8))
    n = raw.size // step if step else 0
    bo = ">" if msg.is_bigendian else "<"
    names, fmts, offs = [], [], []
    for f in msg.fields:
        t = _PF_TYPES.get(int(f.datatype))
        if t and f.name not in names and int(f.offset) + np.dtype(t).itemsize <= step:
            names.append(f.name)
            fmts.append(bo + t)
            offs.append(int(f.offset))
    if not names or n == 0:
        return {}
    dt = np.dtype({"names": names, "formats": fmts, "offsets": offs, "itemsize": step})
    rec = raw[: n * step].view(dt)
    return {name: rec[name] for name in names}


def _walk_msg(obj: Any, path: str, stamps: list[tuple[str, int]], names: set[str],
              strings: set[str], depth: int = 0) -> None:
    """Collect Time stamps (path, sec), lat/lon-named numeric fields and strings of a
    deserialized message (rosbags messages are dataclasses; number arrays are numpy)."""
    fields = getattr(obj, "__dataclass_fields__", None)
    if not fields or depth > 12:
        return
    if "sec" in fields and "nanosec" in fields:
        stamps.append((path or "stamp", int(obj.sec)))
        return
    for n in fields:
        v = getattr(obj, n)
        p = f"{path}.{n}" if path else n
        if isinstance(v, str):
            strings.add(v)
        elif isinstance(v, bool):
            continue
        elif isinstance(v, int | float | np.ndarray):
            if LATLON_NAME.search(n):
                names.add(p)
        elif isinstance(v, list):
            for x in v[:10000]:
                if isinstance(x, str):
                    strings.add(x)
                else:
                    _walk_msg(x, f"{p}[]", stamps, names, strings, depth + 1)
        else:
            _walk_msg(v, p, stamps, names, strings, depth + 1)


def _open_bag(path: Path) -> Any:
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    # bags without embedded definitions (older sqlite3 rosbag2) decode with the ROS 2 set
    return AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))


def scan_bag(path: Path, where: str) -> tuple[list[Finding], list[_BagImage]]:
    """Findings of one bag (file or rosbag2 folder) and its image messages. A bag that
    cannot be opened or read through is an ``unreadable`` finding."""
    out: list[Finding] = []
    images: list[_BagImage] = []
    flagged: set[tuple[str, str]] = set()

    def flag(kind: str, topic: str, detail: str) -> None:
        if (kind, topic) not in flagged:
            flagged.add((kind, topic))
            out.append(Finding(kind, f"{where}:{topic}", detail))

    try:
        with _open_bag(path) as r:
            counts: dict[str, int] = {}
            log_hit: int | None = None
            for con, t, raw in r.messages():
                topic, typ = con.topic, con.msgtype
                k = counts.get(topic, 0)
                counts[topic] = k + 1
                if log_hit is None and epoch_unit(float(t), float(t), "t_ns") is not None:
                    log_hit = int(t)
                if typ.endswith(("/Image", "/CompressedImage")):
                    images.append(_BagImage(str(path), topic, k, f"{where}:{topic}[{k}]"))
                if typ.endswith("/NavSatFix"):
                    flag("latlon", topic, f"{typ} messages: GNSS latitude/longitude")
                msg = r.deserialize(raw, typ)
                stamps: list[tuple[str, int]] = []
                names: set[str] = set()
                strings: set[str] = set()
                _walk_msg(msg, "", stamps, names, strings)
                for p, sec in stamps:
                    if EPOCH_LO_S <= sec <= EPOCH_HI_S:
                        flag("absolute_time", topic, f"{typ} {p}.sec = {sec}: an epoch time")
                        break
                for p in sorted(names):
                    flag("latlon", topic, f"{typ} field {p}: latitude/longitude")
                if strings and ("absolute_time", topic) not in flagged:
                    for f in scan_text("\n".join(sorted(strings)).encode(), f"{where}:{topic}"):
                        flag(f.kind, topic, f"{typ} string: {f.detail}")
                if typ.endswith("/PointCloud2") and ("absolute_time", topic) not in flagged:
                    for f in scan_points(_cloud_columns(msg), f"{where}:{topic}"):
                        flag(f.kind, topic, f"{typ} {f.location.rsplit(':', 1)[-1]}: "
                                            f"{f.detail}")
            if log_hit is not None:
                out.append(Finding("absolute_time", where,
                                   f"message log time {log_hit} ns is an epoch time"))
    except Exception as e:
        return [Finding("unreadable", where,
                        f"bag cannot be scanned: {type(e).__name__}: {e}")], []
    return out, images


def _decode_ros_image(msg: Any, typ: str) -> np.ndarray | None:
    """A decoded Image / CompressedImage message (BGR or mono), None if it does not decode."""
    import cv2

    data = np.asarray(msg.data, dtype=np.uint8).tobytes()
    if typ.endswith("/CompressedImage"):
        return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    enc = str(msg.encoding).lower()
    table = {"mono8": ("u1", 1), "8uc1": ("u1", 1), "mono16": ("u2", 1), "16uc1": ("u2", 1),
             "bgr8": ("u1", 3), "rgb8": ("u1", 3), "8uc3": ("u1", 3), "bgra8": ("u1", 4),
             "rgba8": ("u1", 4), "8uc4": ("u1", 4)}
    if enc not in table:
        return None
    t, ch = table[enc]
    dt = np.dtype((">" if msg.is_bigendian else "<") + t)
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if step * h > len(data) or w * ch * dt.itemsize > step:
        return None
    rows = np.frombuffer(data[: step * h], np.uint8).reshape(h, step)[:, : w * ch * dt.itemsize]
    img = np.ascontiguousarray(rows).view(dt).reshape(h, w, ch).astype(dt.newbyteorder("="))
    if ch == 1:
        return img[:, :, 0]
    if enc.startswith("rgb"):
        return cv2.cvtColor(img, cv2.COLOR_RGB2BGR if ch == 3 else cv2.COLOR_RGBA2BGRA)
    return img


def _read_bag_images(refs: Sequence[_BagImage]) -> dict[_BagImage, np.ndarray | None]:
    """The sampled image messages, each bag read through once."""
    out: dict[_BagImage, np.ndarray | None] = dict.fromkeys(refs)
    for bag in sorted({r.bag for r in refs}):
        want = {(r.topic, r.index): r for r in refs if r.bag == bag}
        topics = {t for t, _ in want}
        try:
            with _open_bag(Path(bag)) as rd:
                cons = [c for c in rd.connections if c.topic in topics]
                counts: dict[str, int] = {}
                for con, _, raw in rd.messages(connections=cons):
                    k = counts.get(con.topic, 0)
                    counts[con.topic] = k + 1
                    ref = want.get((con.topic, k))
                    if ref is not None:
                        out[ref] = _decode_ros_image(rd.deserialize(raw, con.msgtype),
                                                     con.msgtype)
        except Exception:
            continue  # left None: reported as "does not decode"
    return out


# ------------------------------------------------------------------------------- walking
class _Files:
    """The files of a lake zone or of a local folder, through one filesystem."""

    def __init__(self, lake: Lake | None, zone: str | os.PathLike[str],
                 release: str | None = None) -> None:
        z = str(zone)
        self.fs: pafs.FileSystem
        if lake is not None and release is None and z in ("clean", "raw"):
            self.fs, self.root = lake.fs, lake.path(z)
        elif lake is not None and (release is not None or isinstance(zone, str)):
            # a release name, never a path: the same rule as ``release verify``
            name = release if release is not None else z
            from v2xlake.flows.release import ReleaseError, check_release_name

            try:
                check_release_name(name)
            except ReleaseError as e:
                raise AuditError(str(e)) from e
            self.fs, self.root = lake.fs, lake.path("releases", name)
            if not lake.exists(self.root):
                raise AuditError(f"no release {name!r} in {lake.uri}")
        else:
            self.fs, self.root = pafs.LocalFileSystem(), str(Path(z).resolve())

    @property
    def is_local(self) -> bool:
        return isinstance(self.fs, pafs.LocalFileSystem)

    def local(self, path: str, members: Sequence[str], stack: ExitStack) -> Path:
        """A local path of ``path`` (a file, or a folder whose files are ``members``), copied
        to a temporary folder that lives as long as ``stack`` when the lake is remote."""
        if self.is_local:
            return Path(path)
        tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="v2xlake-audit-")))
        if not members:
            dst = tmp / Path(path).name
            dst.write_bytes(self.read(path))
            return dst
        for m in members:
            dst = tmp / m[len(path) :].lstrip("/")
            dst.parent.mkdir(parents=True, exist_ok=True)
            dst.write_bytes(self.read(m))
        return tmp

    def list(self) -> list[str]:
        info = self.fs.get_file_info(self.root)
        if info.type == pafs.FileType.NotFound:
            return []
        sel = pafs.FileSelector(self.root, recursive=True)
        return sorted(
            i.path
            for i in self.fs.get_file_info(sel)
            if i.type == pafs.FileType.File and not i.base_name.startswith(".")
        )

    def read(self, path: str, limit: int | None = None) -> bytes:
        with self.fs.open_input_stream(path) as f:
            return bytes(f.read(limit) if limit else f.read())

    def rel(self, path: str) -> str:
        return path[len(self.root) :].lstrip("/")


def _ego_spans(files: _Files, paths: list[str]) -> list[float]:
    """xy extent of every ego_poses file (empty when the zone has none)."""
    spans = []
    for p in paths:
        if "ego_poses" in p and p.endswith(".parquet"):
            t = read_parquet(p, ["x", "y"], files.fs)
            if t.num_rows:
                x, y = t.column("x").to_numpy(), t.column("y").to_numpy()
                spans.append(float(max(np.ptp(x), np.ptp(y))))
    return spans


def audit(
    lake: Lake | None,
    zone: str | os.PathLike[str] = "clean",
    sample_images: int = 20,
    config: AuditConfig | None = None,
    detector: Any = None,
    *,
    release: str | None = None,
) -> AuditReport:
    """Scan every table and file of ``zone`` ("clean", "raw", a release name, or without a
    lake a folder path), or of release ``release`` (always ``releases/NAME``).

    ``detector``: what re-checks images (default: the anonymizer's default detector);
    ``sample_images``: how many images, spread evenly over the sorted list, are re-checked.
    """
    cfg = config or AuditConfig()
    files = _Files(lake, zone, release)
    if release is not None:
        # a release, whatever its name (even "clean"): never the clean zone's tables
        zone = f"releases/{release}"
    with ExitStack() as stack:
        return _audit(lake, zone, files, sample_images, cfg, detector, stack)


def _bag_dirs(paths: Sequence[str]) -> dict[str, list[str]]:
    """rosbag2 folders (a ``metadata.yaml`` next to ``.db3`` / ``.mcap`` files) -> their
    files: each is read as one bag, its storage files not again on their own."""
    dirs = {p.rsplit("/", 1)[0] for p in paths if p.endswith("/metadata.yaml")}
    out: dict[str, list[str]] = {}
    for p in paths:
        d = p.rsplit("/", 1)[0]
        if d in dirs:
            out.setdefault(d, []).append(p)
    return {d: m for d, m in out.items() if any(x.lower().endswith(BAG_STORAGE_EXT) for x in m)}


def _audit(lake: Lake | None, zone: str | os.PathLike[str], files: _Files, sample_images: int,
           cfg: AuditConfig, detector: Any, stack: ExitStack) -> AuditReport:
    paths = files.list()
    if not paths:
        raise AuditError(f"nothing to audit: {files.root} does not exist or holds no files")
    report = AuditReport(n_files=len(paths))
    spans = _ego_spans(files, paths)
    value_rule = not spans or max(spans) >= cfg.stationary_span_m
    span_range = (
        (
            cfg.span_factor_lo * min(s for s in spans if s >= cfg.stationary_span_m),
            cfg.span_factor_hi * max(spans),
        )
        if value_rule and spans
        else None
    )
    frames = _lake_frames(lake, zone, files) if lake is not None else None
    images: list[str | _BagImage] = []
    bags = _bag_dirs(paths)
    in_bag = {m: d for d, ms in bags.items() for m in ms}
    for p in paths:
        rel = files.rel(p)
        low = p.lower()
        base = low.rsplit("/", 1)[-1]
        try:
            if p in in_bag:
                d = in_bag[p]
                if p.endswith("/metadata.yaml"):  # the folder, once; the YAML below too
                    found, imgs = scan_bag(files.local(d, bags[d], stack), files.rel(d))
                    report.findings.extend(found)
                    images.extend(imgs)
                else:
                    continue  # a storage file of that folder
            if low.endswith(BAG_EXT):
                found, imgs = scan_bag(files.local(p, [], stack), rel)
                report.findings.extend(found)
                images.extend(imgs)
            elif low.endswith(".pcd"):
                header, cols = read_pcd(files.read(p))
                report.findings.extend(scan_text(header, rel) + scan_points(cols, rel))
            elif low.endswith(".ply"):
                header, cols = read_ply(files.read(p))
                report.findings.extend(scan_text(header, rel) + scan_points(cols, rel))
            elif low.endswith(".bin"):
                report.findings.extend(scan_bin(files.read(p), rel))
            elif low.endswith(".npy"):
                report.findings.extend(scan_npy(files.read(p), rel))
            elif low.endswith(".parquet"):
                report.n_tables += 1
                # points: first 3 row groups (frames) only; a column has one unit
                t = read_parquet_head(p, 3, files.fs)
                report.findings.extend(scan_table(t, rel, cfg, value_rule, span_range))
            elif low.endswith(IMAGE_EXT):
                data = files.read(p)
                meta = png_metadata(data) if low.endswith(".png") else jpeg_metadata(data)
                if meta:
                    report.findings.append(
                        Finding("image_metadata", rel, "metadata: " + ", ".join(meta))
                    )
                if frames is not None:
                    if rel in frames:
                        images.append(p)
                elif re.search(cfg.camera_image_pattern, rel) and not re.search(
                        cfg.not_camera_pattern, rel):
                    images.append(p)
            elif low.endswith((".json", ".yaml", ".yml")):
                data = files.read(p, cfg.text_max_bytes)
                try:
                    if low.endswith(".json"):
                        obj = json.loads(data)
                    else:
                        import yaml

                        obj = yaml.safe_load(data)
                except Exception:
                    report.findings.extend(scan_text(data, rel))
                else:
                    report.findings.extend(scan_structured(obj, rel))
            elif low.endswith(TEXT_EXT) or "." not in base:
                report.findings.extend(scan_text(files.read(p, cfg.text_max_bytes), rel))
            else:
                ext = "." + base.rsplit(".", 1)[-1]
                report.findings.append(Finding(
                    "unscannable", rel, f"the audit has no scanner for {ext} files: what "
                    "it holds is unchecked (remove it, or teach the audit its format)"))
        except Exception as e:
            report.findings.append(Finding("unreadable", rel, f"{type(e).__name__}: {e}"))
    if frames is not None and not frames and zone in ("clean", "raw") and images:
        # images in the zone but no camera_frames row to say whose they are; a lake whose
        # clips have no camera has neither, and that is no finding
        report.findings.append(Finding("unreadable", str(zone), f"{len(images)} image(s) "
                                       "but no camera_frames rows to check them against"))
    if sample_images > 0 and images:
        report.findings.extend(_recheck_images(files, images, sample_images, cfg, detector,
                                               report, frames or {}, lake, str(zone)))
    return report


@dataclass(frozen=True)
class _Frame:
    clip: str
    agent: str
    sensor: str
    frame_idx: int
    stamp_ns: int


def _lake_frames(lake: Lake, zone: str | os.PathLike[str], files: _Files
                 ) -> dict[str, _Frame] | None:
    """For a lake zone: the dataset images (blob path relative to the zone -> its frame),
    from the zone's own ``camera_frames``; None for a release or folder."""
    if str(zone) not in ("clean", "raw"):
        return None
    cf = lake.read_table(str(zone), "camera_frames")
    if cf.num_rows == 0:
        return {}
    d = cf.select(["clip_id", "agent_id", "sensor", "frame_idx", "stamp_ns", "blob"]).to_pydict()
    return {f"blobs/{b}": _Frame(c, a, s, int(f), int(t)) for c, a, s, f, t, b in zip(
        d["clip_id"], d["agent_id"], d["sensor"], d["frame_idx"], d["stamp_ns"], d["blob"],
        strict=True)}


def audit_detector(cfg: AuditConfig) -> Any:
    """The audit's detector: the same models, another scan plan (see ``AuditConfig``)."""
    from v2xlake.tasks.anonymize.detectors import ScanConfig
    from v2xlake.tasks.anonymize.run import AnonymizeConfig

    det = AnonymizeConfig(
        face_fine_scale=cfg.audit_face_fine_scale, face_full_threshold=cfg.face_min_score,
        region_face_target_px=cfg.region_face_target_px,
        region_window_face_target_px=cfg.region_face_target_px,
        region_plate_target_px=cfg.region_plate_target_px, face_threshold=cfg.face_min_score,
        plate_box_threshold=cfg.plate_min_score, safety_face_max_side=None,
        safety_plate_max_side=None, region_blob_below_px=0.0,
    ).build_detector()
    det.config = replace(det.config, full_plate_scan=ScanConfig(
        max_side=None, fine_scale=cfg.audit_plate_fine_scale, tile=2048, tile_overlap=128,
        upscale_min_side=0))
    return det


def _blurred(frames: dict[str, _Frame], lake: Lake | None, zone: str
             ) -> dict[tuple[str, str, str, int], list[tuple[float, ...]]]:
    """The boxes the anonymizer blurred, per (clip, agent, sensor, frame) (clean zone)."""
    if lake is None or zone != "clean" or not frames:
        return {}
    au = lake.read_table("clean", "anonymization_audit")
    out: dict[tuple[str, str, str, int], list[tuple[float, ...]]] = {}
    if au.num_rows == 0:
        return out
    d = au.to_pydict()
    for i in range(au.num_rows):
        key = (d["clip_id"][i], d["agent_id"][i], d["sensor"][i], int(d["frame_idx"][i]))
        out.setdefault(key, []).append((d["x0"][i], d["y0"][i], d["x1"][i], d["y1"][i]))
    return out


def _guides(lake: Lake | None, zone: str, clips: set[str], cfg: AuditConfig) -> dict[str, Any]:
    """Per clip, the projected-region guide built from the zone's own tables (clean zone)."""
    if lake is None or zone != "clean":
        return {}
    from v2xlake.tasks.anonymize.context import build_guide
    from v2xlake.tasks.anonymize.guide import GuideConfig
    from v2xlake.tasks.anonymize.timespace import T0_OFFSET_NS

    out = {}
    for clip in clips:
        ego = lake.read_table("clean", "ego_poses", clip_id=clip)
        if ego.num_rows == 0:
            continue
        agents = set(ego.column("agent_id").to_pylist())
        poses = {a: ego.filter(pc.equal(ego.column("agent_id"), a)) for a in agents}
        g = build_guide(clip, T0_OFFSET_NS, poses,
                        lake.read_table("clean", "calibrated_sensors", clip_id=clip),
                        lake.read_table("clean", "annotations", clip_id=clip),
                        lake.read_table("clean", "lidar_frames", clip_id=clip),
                        GuideConfig(min_face_px=cfg.region_min_face_px,
                                    min_plate_px=cfg.region_min_plate_px, windows=False))
        if g.boxes:
            out[clip] = g
    return out


def _overlaps(box: Sequence[float], boxes: Sequence[Sequence[float]], frac: float = 0.3) -> bool:
    """Whether ``frac`` of ``box`` lies under some box of ``boxes`` (grown by the blur
    margin: the blur covers more than the detector's box)."""
    x0, y0, x1, y1 = box
    area = max((x1 - x0) * (y1 - y0), 1e-9)
    for b in boxes:
        mx, my = 0.2 * (b[2] - b[0]) + 2, 0.2 * (b[3] - b[1]) + 2
        ix = max(0.0, min(x1, b[2] + mx) - max(x0, b[0] - mx))
        iy = max(0.0, min(y1, b[3] + my) - max(y0, b[1] - my))
        if ix * iy / area >= frac:
            return True
    return False


def _recheck_images(
    files: _Files, images: Sequence[str | _BagImage], n: int, cfg: AuditConfig, detector: Any,
    report: AuditReport, frames: dict[str, _Frame], lake: Lake | None, zone: str,
) -> list[Finding]:
    """Re-check a sample of dataset images with the audit's own plan: the whole frame, and
    (clean zone of a clip with boxes) every projected head / plate location, which must be
    blurred or hold nothing the audit's detector finds."""
    import cv2

    from v2xlake.tasks.anonymize.images import to_bgr8

    if detector is None:
        detector = audit_detector(cfg)
    idx = np.unique(np.linspace(0, len(images) - 1, min(n, len(images))).round().astype(int))
    sample = [images[int(i)] for i in idx]
    from_bags = _read_bag_images([p for p in sample if isinstance(p, _BagImage)])
    meta = [frames.get(files.rel(p)) if isinstance(p, str) else None for p in sample]
    blurred = _blurred(frames, lake, zone)
    guides = _guides(lake, zone, {m.clip for m in meta if m is not None}, cfg)
    out = []
    for p, m in zip(sample, meta, strict=True):
        if isinstance(p, _BagImage):
            img, rel = from_bags.get(p), p.location
        else:
            img = cv2.imdecode(np.frombuffer(files.read(p), np.uint8), cv2.IMREAD_UNCHANGED)
            rel = files.rel(p)
        if img is None:
            out.append(Finding("unreadable", rel, "image does not decode"))
            continue
        report.n_images_checked += 1
        img8 = to_bgr8(img)
        done = blurred.get((m.clip, m.agent, m.sensor, m.frame_idx), []) if m else []
        found = list(detector.detect(img8))
        g = guides.get(m.clip) if m is not None else None
        regions = g.regions(m.agent, m.sensor, m.stamp_ns) if g is not None and m else None
        for r in regions or []:
            report.n_regions += 1
            hits = [d for d in detector.in_regions(img8, [r]) if d.kind == r.kind]
            if any(not _overlaps(d.box, done) for d in hits):
                found += hits  # reported below
            elif any(_overlaps(b, [r.box], 0.5) for b in done):
                report.n_regions_blurred += 1
            else:
                report.n_regions_not_visible += 1
        seen: list[tuple[float, ...]] = []
        for d in found:
            thr = cfg.face_min_score if d.kind == "face" else cfg.plate_min_score
            if d.score < thr or _overlaps(d.box, done) or _overlaps(d.box, seen, 0.5):
                continue
            seen.append(d.box)
            b = ", ".join(f"{v:.0f}" for v in d.box)
            out.append(Finding(f"unblurred_{d.kind}", rel,
                               f"{d.detector or 'detector'} score {d.score:.2f} at [{b}]"))
    return out
