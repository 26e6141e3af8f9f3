"""The audit's walk over a lake zone, a release or a folder: every table and file through
its scanner, then a sample of the dataset images re-checked with the anonymizer's models
(``audit``). See the package docstring for the rules."""

from __future__ import annotations

import json
import os
import re
import tempfile
from collections.abc import Sequence
from contextlib import ExitStack
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.compute as pc
import pyarrow.fs as pafs

from v2xlake.audit.bags import BagImage, read_bag_images, scan_bag
from v2xlake.audit.points import read_pcd, read_ply, scan_bin, scan_npy, scan_points
from v2xlake.audit.report import AuditConfig, AuditError, AuditReport, Finding
from v2xlake.audit.rules import (
    BAG_EXT,
    BAG_STORAGE_EXT,
    IMAGE_EXT,
    TEXT_EXT,
    jpeg_metadata,
    png_metadata,
    scan_structured,
    scan_table,
    scan_text,
)
from v2xlake.storage.files import read_parquet, read_parquet_head
from v2xlake.storage.lake import Lake


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
            from v2xlake.storage.releases import ReleaseError, check_release_name

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
    images: list[str | BagImage] = []
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
    from v2xlake.tasks.anonymize.build import build_detector
    from v2xlake.tasks.anonymize.config import AnonymizeConfig
    from v2xlake.tasks.anonymize.detectors import ScanConfig

    det = build_detector(AnonymizeConfig.model_validate({
        "faces": {"fine_scale": cfg.audit_face_fine_scale, "threshold": cfg.face_min_score,
                  "full_threshold": cfg.face_min_score},
        "plates": {"box_threshold": cfg.plate_min_score},
        "regions": {"face_target_px": cfg.region_face_target_px,
                    "window_face_target_px": cfg.region_face_target_px,
                    "plate_target_px": cfg.region_plate_target_px, "blob_below_px": 0.0},
        "safety": {"face_max_side": None, "plate_max_side": None},
        # every pixel: the audit must not share the anonymizer's proposal heuristics (a
        # face the first pass does not propose would be missed by both)
        "full_proposals": False,
    }))
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
    from v2xlake.tasks.anonymize.guide import GuideConfig
    from v2xlake.tasks.anonymize.stage import build_guide
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
    files: _Files, images: Sequence[str | BagImage], n: int, cfg: AuditConfig, detector: Any,
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
    from_bags = read_bag_images([p for p in sample if isinstance(p, BagImage)])
    meta = [frames.get(files.rel(p)) if isinstance(p, str) else None for p in sample]
    blurred = _blurred(frames, lake, zone)
    guides = _guides(lake, zone, {m.clip for m in meta if m is not None}, cfg)
    out = []
    for p, m in zip(sample, meta, strict=True):
        if isinstance(p, BagImage):
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
