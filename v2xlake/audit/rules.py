"""The rules on values: absolute time (an epoch window per unit), latitude / longitude (by
name, and by value: a tight, smooth, trajectory-sized pair of columns), text, JSON / YAML
structures, and PNG / JPEG metadata."""

from __future__ import annotations

import math
import re
import struct
from collections.abc import Iterator
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from v2xlake.audit.report import AuditConfig, Finding

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
