"""The anonymize stage: raw zone -> clean zone for one clip (INTERFACES.md, "anonymize"); the
only module of the package that reads or writes the lake, and the only way data reaches the
clean zone.

Every raw table of the clip is rewritten into the clean zone with relative time; ``ins``
becomes ``ego_poses`` in local ENU, ``gnss`` loses lat/lon/alt for local x/y/z, and every
camera image is replaced by an anonymized PNG (same blob key, clean blob store) with one
``anonymization_audit`` row per blurred box. The raw partition layout (one file per
clip/agent/name) is mirrored, so downstream readers see the same structure in both zones.
The guide (where each image's faces and plates can be) is built here from the clip's tables
(``build_guide``), the detection, carrying, blurring and encoding are the pure modules'.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import itertools
import logging
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
from pydantic import BaseModel

from v2xlake.schemas.arrow import rows_to_table
from v2xlake.schemas.errors import ClipError
from v2xlake.schemas.stage import OutputFile, Stage, StageReport, tables
from v2xlake.schemas.tables import INGEST_TABLES, RAW_ONLY_TABLES, AnonymizationAuditRow
from v2xlake.storage.files import read_parquet
from v2xlake.storage.frames import file_schema, iter_row_groups, partition_files
from v2xlake.storage.lake import Lake, ParquetOptions
from v2xlake.storage.reader import CameraCalib, calibrations, pose_samples
from v2xlake.tasks.anonymize import DECLARATION
from v2xlake.tasks.anonymize.config import AnonymizeConfig
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
from v2xlake.tasks.cores import available_cores
from v2xlake.tasks.geodesy import LocalFrame
from v2xlake.tasks.interpolate import PoseTrack

if TYPE_CHECKING:
    from v2xlake.tasks.anonymize.context import ClipGuide
    from v2xlake.tasks.anonymize.detectors import Box, Detection
    from v2xlake.tasks.anonymize.guide import GuideConfig, Region, WorldBoxes

# The numeric modules (detectors, plate reader, blur, images, guide, LiDAR clusters: cv2,
# onnxruntime and the models) are imported inside the functions that process images or
# build the guide, not here: a clip without cameras, ``v2xlake params`` and the flows that
# only name the stage import this module and never pay for them.

log = logging.getLogger(__name__)
STAGE = "anonymize"

Progress = Callable[[int, int], None]

# The clean copy of lidar_points, the one table whose size makes the copy cost anything (a
# camera-less clip's whole anonymize): the clean zone's encodings (BYTE_STREAM_SPLIT floats,
# DELTA times) under lz4 instead of zstd-1, without the float / dictionary min-max (they
# prune nothing: every scan spans the sensor's range, one sensor per file), PLAIN frame
# indices (constant in a row group: delta costs 3x for nothing) and big write batches: the
# raw zone's speed choices. Simulated 64 x 1024 scans, 61k points: encoding 6.2 -> 3.0 ms
# CPU per frame at 10.2 instead of 10.0 bytes per point (+2 %); lz4 also reads faster for
# deskew and the exports.
POINTS_OPTIONS = dataclasses.replace(
    ParquetOptions(), compression="lz4", compression_level=None, delta_int32=False,
    float_statistics=False, dictionary_statistics=False, write_batch_size=65_536)

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


class ProgressLog:
    """One plain log line (logger ``v2xlake.tasks.anonymize.stage``, INFO) every ``every``
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

    # everything is written to the stage's own run folder and published in one step at the
    # end, so a clip that fails half-way (a corrupt image) never leaves a half-clean zone
    stage = lake.for_stage(STAGE, [(t.zone, t.name) for t in ANONYMIZE.owns],
                           atomic_clip=clip_id, reads=lake.reads)
    try:
        _write_clean(lake, stage, clip_id, cfg, t0, frame, report, progress, map_xy)
        for table in CLEAN_TABLES:  # the clip's clean zone is this run's output, nothing else
            stage.delete_partition("clean", table, clip_id)
        stage.delete_blobs("clean", clip_id)
        stage.publish_stage()  # one journaled swap (a kill mid-way is rolled forward)
    except BaseException:
        stage.discard_stage()
        raise
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
        from v2xlake.tasks.anonymize.build import guide_config

        guide = build_guide(
            clip_id, t0, {a: pa.concat_tables(ts) for a, ts in ego.items()},
            lake.read_table("raw", "calibrated_sensors", clip_id=clip_id),
            lake.read_table("raw", "annotations", clip_id=clip_id),
            lake.read_table("raw", "lidar_frames", clip_id=clip_id), guide_config(cfg),
            lidar_clusters(lake, clip_id, t0, ego, cfg))
        report.notes.append(f"anonymize: regions from {guide.source}")
    stats: dict[str, float] = {}
    n_faces, n_plates, n_images, n_guided = _anonymize_images(
        lake, stage, clip_id, cfg, t0, write, progress, guide, stats)
    report.metrics.update(stats)
    report.metrics["n_images_guided"] = float(n_guided)
    report.metrics.update(
        n_images=float(n_images), n_faces=float(n_faces), n_plates=float(n_plates)
    )


def _stream_points(
    lake: Lake, stage: Lake, path: str, clip_id: str, agent: str | None, name: str, t0: int
) -> tuple[int, str | None]:
    """lidar_points row group by row group (a clip need not fit in memory), one group per
    frame. Only ``t_ns`` changes; every other column goes through as read (no conversion),
    encoded with ``POINTS_OPTIONS``. One thread: a frame's columns are too small for
    pyarrow's pool to pay (reading 1.5 -> 0.9 ms per 61k-point frame), and a background
    encoder saved no time on the loaded 2-core machine (a fleet worker has one core)."""
    with stage.open_writer(
        "clean", "lidar_points", file_schema(lake, path), clip_id=clip_id, agent_id=agent,
        name=name, options=POINTS_OPTIONS,
    ) as w:
        for group in iter_row_groups(lake, path, use_threads=False):
            data = shift_times(group, "lidar_points", t0)
            if data.num_rows == 0:
                continue
            keys = data.column("frame_idx").to_numpy()
            if keys[0] == keys[-1] and (keys == keys[0]).all():  # the lake's one frame per group
                w.write(data)
                continue
            bounds = [0, *(np.flatnonzero(np.diff(keys)) + 1).tolist(), data.num_rows]
            for a, b in itertools.pairwise(bounds):
                w.write(data.slice(a, b - a))
    return w.rows, w.checksum


def lidar_clusters(lake: Lake, clip_id: str, t0: int, ego: dict[str, list[pa.Table]],
                   cfg: AnonymizeConfig) -> dict[str, WorldBoxes] | None:
    """Object boxes from LiDAR clusters (``clusters.py``), one set per scan, in the clip
    world, for clips without annotations; None when the clip has annotations (or no LiDAR,
    or no poses)."""
    from v2xlake.tasks.anonymize.build import cluster_config
    from v2xlake.tasks.anonymize.clusters import (
        cluster_boxes,
        object_ids,
        off_axis_copies,
        track_ids,
        yaw_quat,
    )
    from v2xlake.tasks.anonymize.guide import WorldBoxes, world_boxes_from_sensor
    from v2xlake.tasks.motion import deskew_points

    if not cfg.clusters.enabled or not ego:
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
    ccfg = cluster_config(cfg)
    for path, agent, _name in partition_files(lake, "raw", "lidar_points", clip_id):
        if agent is None or agent not in ego:
            continue
        samples = pose_samples(pa.concat_tables(ego[agent]), clip_id, agent)
        track = PoseTrack.create(samples.t_ns, samples.xyz, samples.quat_wxyz)
        sensors = calibrations(calib.filter(pc.equal(calib.column("agent_id"), agent)),
                               clip_id, agent)
        parts: dict[str, list[WorldBoxes]] = {}
        for g in iter_row_groups(lake, path,
                                 columns=["sensor", "frame_idx", "t_ns", "x", "y", "z"]):
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
            # each point into the LiDAR frame at the scan's start: a raw sweep's points are
            # in the frame of their own instant (anonymize runs before the deskew stage),
            # and the ego moves 1.5 m in a 0.1 s sweep at 15 m/s (a pedestrian 8 m to the
            # side of the simulated clip got its head region 1.4 m off, and its face missed)
            t_pts = g.column("t_ns").to_numpy().astype(np.int64) - t0 + T0_OFFSET_NS
            xyz = deskew_points(xyz, t_pts, track, T_ego, t_rel).xyz
            c, size, yaw, cat = cluster_boxes(xyz @ T_ego[:3, :3].T + T_ego[:3, 3], ccfg)
            if not len(c):
                continue
            m = len(c)
            parts.setdefault(sensor, []).append(world_boxes_from_sensor(
                np.full(m, t_rel, np.int64), np.broadcast_to(track.matrices(t_rel)[0], (m, 4, 4)),
                c, size, yaw_quat(yaw), np.zeros((m, 3)), cat,
                np.array([f"lidar:{agent}:{sensor}:{fidx}:{k}" for k in range(m)])))
        tracked = []
        for sensor, ps in parts.items():
            b = WorldBoxes.concat(ps)
            if cfg.clusters.carry and cfg.clusters.track_gate_m > 0:
                # one identity per object across scans (``track_ids``): the frames between
                # key frames carry detections with it (``carry.py``); without carrying every
                # frame is detected in full and the tracks would serve nothing
                w, z = b.quat[:, 0], b.quat[:, 3]
                ids = track_ids(b.t_ns, b.center, b.size, 2 * np.arctan2(z, w), b.category,
                                cfg.clusters.track_gate_m,
                                int(cfg.clusters.track_gap_ms * 1e6))
                b = dataclasses.replace(
                    b, instance=np.array([f"lidar:{agent}:{sensor}:t{k}" for k in ids]))
            tracked.append(b)
        if tracked:
            out[agent] = WorldBoxes.concat(tracked)
    if out and cfg.clusters.carry and cfg.clusters.track_gate_m > 0:
        # one identity per object across the agents' LiDARs (``object_ids``: their tracks'
        # centres in the clip world): a find in a region of agent A's track pairs with
        # one in agent B's (``carry.between_tracked``), kept after the track as
        # ``<track>@o<object>`` (a region's key stays its LiDAR's track)
        names = list(out)
        allb = WorldBoxes.concat([out[a] for a in names])
        inst = allb.instance.astype(str)
        lidar_of = np.array([i.rsplit(":", 1)[0] for i in inst])
        obj = object_ids(allb.t_ns, allb.center, inst, lidar_of, cfg.clusters.track_gate_m)
        tagged = np.array([f"{i}@o{k}" for i, k in zip(inst, obj, strict=True)])
        keep = np.ones(len(inst), bool)
        if cfg.clusters.orient_by_object_ms > 0:
            # a short cluster's two orientations: the one off the axis of a longer box of
            # the same object (another agent's, or its own track's) is dropped
            # (``clusters.off_axis_copies``)
            w, z = allb.quat[:, 0], allb.quat[:, 3]
            keep = ~off_axis_copies(allb.t_ns, allb.center, allb.size, 2 * np.arctan2(z, w),
                                    allb.category, obj,
                                    int(cfg.clusters.orient_by_object_ms * 1e6),
                                    ccfg.full_length_m, lidar_of)
        start_at = 0
        for a in names:
            rows = slice(start_at, start_at + len(out[a]))
            out[a] = dataclasses.replace(out[a], instance=tagged[rows]).take(keep[rows])
            start_at = rows.stop
    return out or None


def _encode(img: np.ndarray, key: str, cfg: AnonymizeConfig) -> tuple[bytes, str]:
    """The clean image bytes and the clean blob key (named by what is written)."""
    from v2xlake.tasks.anonymize.images import encode_image

    stem, _, ext = key.rpartition(".")
    fmt = cfg.output.image_format
    if fmt == "same":
        fmt = "jpeg" if ext.lower() in ("jpg", "jpeg") else "png"
    if fmt == "jpeg" and img.dtype != np.uint8:
        fmt = "png"  # JPEG holds 8 bits; deeper images stay lossless
    data = encode_image(img, fmt, cfg.output.png_compression, cfg.output.jpeg_quality)
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
    stats: dict[str, float] | None = None,
) -> tuple[int, int, int, int]:
    """Every camera image: detect (guided when the guide has regions for it), fill temporal
    gaps per camera, blur, encode; frames of one camera go in time order, ``frames_per_chunk``
    at a time, detected with one frame of look-ahead so a chunk's last frame has its next.
    ``stats``: where given, gets the number of frames carried between key frames
    (``n_images_carried``) and of those where carrying was unsure
    (``n_images_carried_in_full``, LiDAR-only clips: detected in full, or with
    ``clusters.carry_unsure_zones`` searched as in full where the unsure objects can be)."""
    files = partition_files(lake, "raw", "camera_frames", clip_id)
    tables = [(agent, name, read_parquet(path, filesystem=lake.fs)) for path, agent, name in files]
    total = sum(t.num_rows for _, _, t in tables)
    if total == 0:
        # no image (no camera_frames file, or ingest's empty ones for agents without
        # cameras): the clean zone still mirrors the raw files, but neither the detector
        # (its ONNX sessions took ~0.8 s to build) nor its modules (OpenCV, onnxruntime:
        # ~0.5 s to import) are loaded
        for agent, name, table in tables:
            write("camera_frames", _clean_frames(table, t0, [], "", []), agent, name)
            write("anonymization_audit", _audit_table([], agent), agent, name)
        return 0, 0, 0, 0

    from v2xlake.tasks.anonymize.blur import blur_boxes
    from v2xlake.tasks.anonymize.build import blur_config, build_detector, guide_config
    from v2xlake.tasks.anonymize.carry import (
        between,
        between_tracked,
        full_key_frames,
        key_frames,
        key_windows,
        merge_overlapping,
        new_regions,
        plate_windows,
        unconfirmed,
        unsure_kept,
        unsure_plan,
    )
    from v2xlake.tasks.anonymize.images import decode_image, to_bgr8
    from v2xlake.tasks.anonymize.temporal import fill_gaps

    detector = build_detector(cfg)
    blur = blur_config(cfg)
    anonymizer = cfg.provenance(detector.version)
    done = 0
    n_faces = n_plates = n_guided = 0
    if progress:
        progress(0, total)
    plog = ProgressLog(clip_id, total, cfg.work.progress_log_images, cfg.work.progress_log_s)

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

    full = cfg.clusters.full_frame and guide is not None and guide.source == "lidar clusters"
    # frames between key frames: carried, and (LiDAR-only) those detected in full instead
    counts: dict[str, list[int]] = {"carried": [], "carried_in_full": []}  # rows
    gcfg = guide_config(cfg)
    part_m = (gcfg.face_height_m, gcfg.plate_width_m)  # the sizes the regions expect

    def detect(item: tuple[str, str, str, int, int | None,
                           tuple[tuple[int, int], tuple[int, int] | None] | None],
               known: dict[int, list[Detection]] | None = None,
               kregions: dict[int, list[Region] | None] | None = None
               ) -> tuple[np.ndarray, list[Detection], list[Region] | None]:
        """A key frame: the whole plan. A light key frame (``item``'s fifth field: the row of
        the full key frame before it, whose detections ``known`` and regions ``kregions``
        hold): the whole plan with its vehicle faces' plate search narrowed to where that
        key frame found plates (``carry.plate_windows``). A LiDAR-only key frame without
        the full-frame plan (the last field: (row, stamp) of the key frame before it and of
        the one before that, ``clusters.full_frame_every``): the guided plan with the
        shrunk safety pass and windows around the key frame before's detections
        (``carry.key_windows``). The frame's own regions are returned either way (the
        frames between are carried with them)."""
        key, agent, sensor, stamp, full_row, prev = item
        img = decode(key, agent)
        regions = guide.regions(agent, sensor, stamp) if guide is not None else None
        look = regions
        if regions and full_row is not None and known is not None and kregions is not None:
            look = plate_windows(known[full_row], kregions[full_row], regions, img.shape)
        if prev is None or look is None or known is None or kregions is None:
            return img, detector.detect(to_bgr8(img), look, full), regions
        (b, tb), e = prev
        windows = key_windows((known[b], kregions[b], tb),
                              (known[e[0]], kregions[e[0]], e[1]) if e is not None else None,
                              regions, stamp, cfg.clusters.carry_window, img.shape,
                              cfg.clusters.key_window_mps, part_m)
        return img, detector.detect(to_bgr8(img), [*look, *windows], False), regions

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
                             cfg.carry.min_face_px, (known[a], known[b]),
                             tracked and cfg.clusters.carry_by_object) if regions else [])
        if tracked and cfg.clusters.carry_band and kregions[a] and kregions[b]:
            # the far band is the camera's own rows, not an object: the key frames' band
            # plates are paired and interpolated like any other (a far plate moves little)
            fresh = [r for r in fresh if r.part != "band"
                     or not any(q.part == "band" for q in kregions[a] or ())
                     or not any(q.part == "band" for q in kregions[b] or ())]
        if tracked:
            # the key frame before ``a``: its detections give an image velocity to those of
            # ``a`` that ``b`` lacks (``carry._ahead``: one leaving the view)
            e = next((rows[q] for q in range(pos[a] - 1, -1, -1) if is_key[q]), None)
            doubt: list[str] = []
            zones: list[tuple[str, Box]] = []
            cam = guide.cameras.get((agent_col[i], sensors[i])) if guide is not None else None
            found, again, fallback = between_tracked(
                (known[a], kregions[a], int(stamps[a])), (known[b], kregions[b], int(stamps[b])),
                regions, int(stamps[i]), cfg.carry.grow, cfg.clusters.carry_window, img.shape,
                fresh, (known[e], kregions[e], int(stamps[e])) if e is not None else None,
                doubt, zones, (cam[1].cx, cam[1].cy) if cam is not None else None,
                cfg.clusters.carry_by_object)
            if doubt and cfg.clusters.carry_unsure_full:
                # carrying cannot tell where an object is here (``carry.between_tracked``'s
                # ``unsure``)
                counts["carried_in_full"].append(i)
                if not cfg.clusters.carry_unsure_zones:  # detected in full, as without carrying
                    return img, detector.detect(to_bgr8(img), regions, full), regions
                # the carried frame's result and searches, and where the unsure objects can
                # be (``zones``) the full detection's (``carry.unsure_plan``)
                plan = unsure_plan(zones, again, fresh, regions, img.shape)
                bgr = to_bgr8(img)
                near = detector.in_regions(bgr, plan.look)
                if full:
                    near += detector.full_frame_in(bgr, plan.plan_at)
                if cfg.clusters.carry_safety:
                    near += detector.safety(bgr)
                # one box per object as on a carried frame: the union of its finds (a 19 px
                # face's window box and the full-frame plan's, each under IoU 0.3 alone)
                near = merge_overlapping(near)
                return img, found + near + unsure_kept(fallback, near, plan.doubt), regions
        else:
            (found, again), fallback = between(
                (known[a], kregions[a], int(stamps[a])), (known[b], kregions[b], int(stamps[b])),
                regions, int(stamps[i]), cfg.carry.grow, img.shape, fresh), []
        counts["carried"].append(i)
        safe = tracked and cfg.clusters.carry_safety
        seen: list[Detection] = []
        if fresh or again or safe:
            bgr = to_bgr8(img)
            seen = detector.in_regions(bgr, [*fresh, *again]) if fresh or again else []
            if safe:
                seen += detector.safety(bgr)
            if tracked:
                # the windows of one object's detections overlap (found before and after,
                # moved by its track): one box per object, the union of its finds
                seen = merge_overlapping(seen)
        return img, found + seen + unconfirmed(fallback, seen), regions

    def finish(img: np.ndarray, key: str, dets: list[Detection]) -> tuple[str, str]:
        out = img.copy()
        blur_boxes(out, [d.box for d in dets], blur, [d.kind for d in dets])
        data, clean_key = _encode(out, key, cfg)
        stage.write_blob("clean", clean_key, data)
        return hashlib.sha256(data).hexdigest(), clean_key

    det_names = {d.name: f"{d.name}@{d.version}" for d in detector.detectors}
    workers = cfg.work.workers if cfg.work.workers > 0 else available_cores()
    gap_ns = int(cfg.temporal.max_gap_ms * 1e6)
    key_ns = int(cfg.carry.key_interval_ms * 1e6)
    clustered = guide is not None and guide.source == "lidar clusters"
    if clustered and not cfg.clusters.carry:
        key_ns = 0  # every frame in full (clusters.carry)
    # regions of LiDAR cluster tracks: carried between key frames as their own detections
    # paired by track and interpolated (``carry.between_tracked``)
    tracked = clustered and cfg.clusters.carry and cfg.clusters.track_gate_m > 0
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
                # each key frame's full key frame: itself, or (a light key frame) the last
                # full one before it
                full_of = full_key_frames(is_key, cfg.carry.plate_full_every if key_ns else 1)
                # LiDAR-only: the key frames with the full-frame plan (the others search
                # windows around the key frame before's detections: ``carry.key_windows``)
                plan_of = full_key_frames(is_key, cfg.clusters.full_frame_every
                                          if tracked and full else 1)
                kpos = [p for p, k in enumerate(is_key) if k]
                kprev = {q: kpos[j - 1] for j, q in enumerate(kpos) if j > 0}
                # per key frame (row): the key frames (rows) whose detections it uses, and
                # for one without the full-frame plan (row, stamp) of the key frame before
                # it and of the one before that
                uses: dict[int, list[int]] = {}
                prev_of: dict[int, tuple[tuple[int, int], tuple[int, int] | None]] = {}
                for p in kpos:
                    uses[rows[p]] = [rows[full_of[p]]] if full_of[p] != p else []
                    if plan_of[p] != p:
                        q = kprev[p]
                        e = kprev.get(q)
                        prev_of[rows[p]] = ((rows[q], int(stamps[rows[q]])), (
                            (rows[e], int(stamps[rows[e]])) if e is not None else None))
                        uses[rows[p]] += [rows[q]] + ([rows[e]] if e is not None else [])
                pos = {i: p for p, i in enumerate(rows)}
                known: dict[int, list[Detection]] = {}
                kregions: dict[int, list[Region] | None] = {}
                # the look-ahead frames' decoded images, kept for the next chunk (a PNG
                # decode costs about what the encode does: 25 ms per simulated 1080p frame)
                ahead: dict[int, np.ndarray] = {}
                for c0 in range(0, len(rows), cfg.work.frames_per_chunk):
                    chunk = rows[c0 : c0 + cfg.work.frames_per_chunk]
                    end = c0 + len(chunk)
                    # look-ahead: the frame after the chunk (temporal fill) and the key frame
                    # the chunk's last frames are carried from
                    stop = end
                    while stop < len(rows) and not is_key[stop]:
                        stop += 1
                    span = rows[c0 : min(stop + 1, len(rows))]
                    todo = [i for i in span if is_key[pos[i]] and i not in known]
                    images: dict[int, np.ndarray] = {}

                    # in waves: a key frame once the key frames it uses are done (the full
                    # key frames first, the light ones after them use their plates)
                    while todo:
                        part = [i for i in todo if all(j in known for j in uses[i])]
                        assert part, "a key frame waits for one after it"
                        todo = [i for i in todo if i not in part]
                        items = [(keys[i], agent_col[i], sensors[i], int(stamps[i]),
                                  rows[full_of[pos[i]]] if full_of[pos[i]] != pos[i] else None,
                                  prev_of.get(i))
                                 for i in part]
                        job_k = functools.partial(detect, known=known, kregions=kregions)
                        for i, (img, found, regs) in zip(part, list(pool.map(job_k, items)),
                                                         strict=True):
                            known[i] = found  # every frame is detected once (chunk or ahead)
                            kregions[i] = regs
                            n_guided += regs is not None
                            (images if i in chunk else ahead)[i] = img
                    between_todo = [i for i in span[: end - c0 + 1] if i not in known]
                    job = functools.partial(carried, rows=rows, is_key=is_key, pos=pos,
                                            known=known, kregions=kregions)
                    for i, (img, found, regs) in zip(between_todo,
                                                     list(pool.map(job, between_todo)),
                                                     strict=True):
                        known[i] = found
                        n_guided += regs is not None
                        (images if i in chunk else ahead)[i] = img
                    # the detector's own boxes (``known``) are the evidence for the fill, never
                    # the filled ones: the result does not depend on the chunk size
                    final = {i: known[i] for i in chunk}
                    if cfg.temporal.fill:
                        order = rows[max(c0 - 1, 0) : c0 + len(chunk) + 1]
                        add = fill_gaps([known[i] for i in order], [stamps[i] for i in order],
                                        gap_ns)
                        for i, extra in zip(order, add, strict=True):
                            if i in final:
                                final[i] = known[i] + extra
                    for i in chunk:  # the previous chunk's look-ahead
                        if i not in images:
                            images[i] = (ahead.pop(i) if i in ahead
                                         else decode(keys[i], agent_col[i]))
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
            write("camera_frames", _clean_frames(table, t0, result, anonymizer,
                                                 [len(d) for d in dets]), agent, name)
            write("anonymization_audit", _audit_table(audit, agent), agent, name)
    if stats is not None:
        stats.update(
            n_images_carried=float(len(counts["carried"]) + len(counts["carried_in_full"])),
            n_images_carried_in_full=float(len(counts["carried_in_full"])))
    return n_faces, n_plates, int(total), n_guided


def _clean_frames(table: pa.Table, t0: int, result: list[tuple[str, str]], anonymizer: str,
                  n_blurred: list[int]) -> pa.Table:
    """One raw ``camera_frames`` file's clean rows: relative stamps, the clean blob key and
    its sha256 (``result``: (sha256, key) per row), the provenance, the boxes blurred."""
    clean = shift_times(table, "camera_frames", t0)
    for col, values, typ in (
        ("blob", [r[1] for r in result], pa.string()),
        ("sha256", [r[0] for r in result], pa.string()),
        ("anonymizer", [anonymizer] * len(result), pa.string()),
        ("n_blurred", n_blurred, pa.int64()),
    ):
        arr = pa.array(values, typ)
        if col in clean.column_names:
            clean = clean.set_column(clean.column_names.index(col), pa.field(col, typ), arr)
        else:
            clean = clean.append_column(col, arr)
    return clean


def _audit_table(audit: list[AnonymizationAuditRow], agent: str | None) -> pa.Table:
    """The ``anonymization_audit`` rows of one camera_frames file, without the partition
    columns its path holds."""
    table = rows_to_table(AnonymizationAuditRow, list[BaseModel](audit))
    return table.drop_columns(["clip_id"] + (["agent_id"] if agent is not None else []))


def build_guide(clip_id: str, t0_abs: int, ego_poses: dict[str, pa.Table], calib: pa.Table,
                annotations: pa.Table, lidar_frames: pa.Table, config: GuideConfig,
                clusters: dict[str, WorldBoxes] | None = None) -> ClipGuide:
    """The guide from the clip's tables (``ego_poses`` clean, the others raw): pose tracks and
    calibration parsed here, the guide assembled by ``context.assemble_guide``."""
    from v2xlake.tasks.anonymize.context import assemble_guide, camera_intrinsics

    tracks: dict[str, PoseTrack] = {}
    for agent, ego in ego_poses.items():
        if ego.num_rows < 2:
            continue
        s = pose_samples(ego, clip_id, agent)
        try:
            tracks[agent] = PoseTrack.create(s.t_ns, s.xyz, s.quat_wxyz)
        except ValueError:
            continue
    cameras = {}
    extrinsics: dict[str, dict[str, np.ndarray]] = {}
    for agent in tracks:
        mine = (calib.filter(pc.equal(calib.column("agent_id"), agent))
                if "agent_id" in calib.column_names else calib)
        sensors = calibrations(mine, clip_id, agent) if calib.num_rows else {}
        extrinsics[agent] = {name: c.T_ego_sensor for name, c in sensors.items()}
        for name, c in sensors.items():
            if isinstance(c, CameraCalib):
                intr = camera_intrinsics(c)
                if intr is not None:
                    cameras[(agent, name)] = (c.T_ego_sensor, intr)
    return assemble_guide(t0_abs, tracks, cameras, extrinsics, annotations, lidar_frames,
                          config, clusters)


def lake_image_keys(lake: Lake, clip_id: str) -> dict[tuple[str, str, int], tuple[str, int]]:
    """(agent, sensor, absolute stamp) -> (raw blob key, frame_idx) of every camera image
    (for benchmarks and tests that score what the stage wrote)."""
    cf = lake.read_table("raw", "camera_frames", clip_id=clip_id).to_pydict()
    return {
        (str(a), str(s), int(t)): (str(b), int(f))
        for a, s, f, t, b in zip(
            cf["agent_id"], cf["sensor"], cf["frame_idx"], cf["stamp_ns"], cf["blob"], strict=True
        )
    }


def audit_detections(lake: Lake, clip_id: str) -> dict[tuple[str, str, int], list[Detection]]:
    """The clean zone's ``anonymization_audit`` as detections per (agent, sensor, abs stamp)."""
    from v2xlake.tasks.anonymize.detectors import Detection

    keys = lake_image_keys(lake, clip_id)
    by_frame = {(a, s, f): (a, s, t) for (a, s, t), (_b, f) in keys.items()}
    out: dict[tuple[str, str, int], list[Detection]] = {k: [] for k in keys}
    au = lake.read_table("clean", "anonymization_audit", clip_id=clip_id).to_pydict()
    for i in range(len(au.get("kind", []))):
        k = by_frame[(str(au["agent_id"][i]), str(au["sensor"][i]), int(au["frame_idx"][i]))]
        box = (au["x0"][i], au["y0"][i], au["x1"][i], au["y1"][i])
        out[k].append(Detection(str(au["kind"][i]), box, float(au["score"][i])))
    return out


_CLEAN = tuple(t for t in INGEST_TABLES if t not in RAW_ONLY_TABLES)

ANONYMIZE = Stage(
    name=DECLARATION.name, config_model=AnonymizeConfig,
    reads=tables("raw", *INGEST_TABLES, "qa_checks"),
    owns=DECLARATION.owns,
    run=run_anonymize, atomic=False,  # stages the whole clean zone and publishes it itself
    doc="faces and plates blurred, time made relative, positions made local")
