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
"""

from __future__ import annotations

import json
import math
import os
import re
import struct
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.fs as pafs
import pyarrow.parquet as pq

from v2xlake.storage.lake import Lake

EPOCH_LO_S = 631_152_000  # 1990-01-01
EPOCH_HI_S = 4_102_444_800  # 2100-01-01
UNIT_SCALE = {"s": 1, "ms": 10**3, "us": 10**6, "ns": 10**9}
LATLON_NAME = re.compile(r"(^|_)(lat|lon|lng|latitude|longitude|gps|wgs84|geo)(_|$|itude)", re.I)
COUNT_NAME = re.compile(r"(size|bytes|count|^n_|_n$|num_|rows|points)", re.I)
TIME_KEY = re.compile(r"(time|stamp|date|_ns$|_us$|_ms$|^t$|^ts$)", re.I)
DIGITS = re.compile(rb"(?<![0-9A-Za-z])(?<![0-9]\.)([0-9]{9,19})(?:\.([0-9]+))?(?![0-9A-Za-z])")
IMAGE_EXT = (".png", ".jpg", ".jpeg")
TEXT_EXT = (".json", ".yaml", ".yml", ".txt", ".csv", ".xml", ".pcd")
PNG_SIG = b"\x89PNG\r\n\x1a\n"
PNG_LEAK_CHUNKS = {b"tEXt", b"zTXt", b"iTXt", b"eXIf", b"tIME"}


@dataclass(frozen=True)
class Finding:
    # absolute_time | latlon | image_metadata | unblurred_face | unblurred_plate | unreadable
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


# ------------------------------------------------------------------------------- walking
class _Files:
    """The files of a lake zone or of a local folder, through one filesystem."""

    def __init__(self, lake: Lake | None, zone: str | os.PathLike[str]) -> None:
        z = str(zone)
        if lake is not None and z in ("clean", "raw", "releases", "landing"):
            self.fs: pafs.FileSystem = lake.fs
            self.root = lake.path(z)
        elif lake is not None and not os.path.isabs(z) and lake.exists(lake.path("releases", z)):
            self.fs, self.root = lake.fs, lake.path("releases", z)
        else:
            self.fs, self.root = pafs.LocalFileSystem(), str(Path(z).resolve())

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
            t = pq.read_table(p, filesystem=files.fs, columns=["x", "y"])
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
) -> AuditReport:
    """Scan every table and file of ``zone`` ("clean", a release name, or a folder path).

    ``detector``: what re-checks images (default: the anonymizer's default detector);
    ``sample_images``: how many images, spread evenly over the sorted list, are re-checked.
    """
    cfg = config or AuditConfig()
    files = _Files(lake, zone)
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
    images: list[str] = []
    for p in paths:
        rel = files.rel(p)
        low = p.lower()
        try:
            if low.endswith(".parquet"):
                report.n_tables += 1
                pf = pq.ParquetFile(files.fs.open_input_file(p))
                # points: first 3 row groups (frames) only; a column has one unit
                t = pf.read_row_groups(list(range(min(pf.num_row_groups, 3))))
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
            elif low.endswith(TEXT_EXT):
                report.findings.extend(scan_text(files.read(p, cfg.text_max_bytes), rel))
        except Exception as e:
            report.findings.append(Finding("unreadable", rel, f"{type(e).__name__}: {e}"))
    if frames is not None and not frames and zone in ("clean", "raw"):
        report.findings.append(Finding("unreadable", str(zone), "no camera_frames table"))
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
    files: _Files, images: list[str], n: int, cfg: AuditConfig, detector: Any,
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
    meta = [frames.get(files.rel(p)) for p in sample]
    blurred = _blurred(frames, lake, zone)
    guides = _guides(lake, zone, {m.clip for m in meta if m is not None}, cfg)
    out = []
    for p, m in zip(sample, meta, strict=True):
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
