"""The ingest stage: one clip folder -> landing copy + raw-zone tables
(docs/architecture.md, Stages).

This module is the stage's lake I/O and its ``INGEST`` Stage object; the parameters are
``config.py``, the clip folder (clip.yaml, the files it names, the landing rule)
``clipdir.py``, and decoding is in ``bagopen.py``, ``payloads.py``, ``rawmsg.py``,
``pointcloud.py``, ``images.py``, ``ins.py``, ``pose.py``, ``calibration.py``,
``annotations.py`` (bags and messages in, arrays and rows out).

Driven only by ``clip.yaml``. Each agent's bag is read in a single pass over the configured
topics; LiDAR frames stream into one Parquet row group each (never the whole clip in memory),
images go to PNG blobs. Throughput (``tests/bench/bench_ingest.py``): payloads of ROS 2 bags
are read in place (``payloads.py``), PointCloud2 and images are parsed straight from the wire
format (``rawmsg.py``, exact, rosbags as fallback), points are decoded in one compiled pass
on the reading thread while a second thread encodes the previous frames (raw zone encoding:
``v2xlake.storage.lake.RAW_OPTIONS``) and a third checksums and writes the bytes, so the report
carries every output's checksum and the manifest never re-reads them. Everything is written
through a staged handle (``Lake.for_stage(..., atomic_clip=)``, the one publish protocol of
every stage) and published into ``raw/`` only when every agent succeeded, replacing the
clip's whole raw zone in one commit, so a clip that fails (unknown type, missing topic,
truncated file...) leaves nothing in the raw zone or the catalog, and concurrent ingests of
different clips never see each other's partial output.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import xxhash
import yaml
from pydantic import BaseModel, ValidationError

from v2xlake.schemas.arrow import arrow_schema, columns_to_table
from v2xlake.schemas.clip import (
    MAX_SENSOR_OFFSET_M,
    AgentConfig,
    ClipConfig,
    Modality,
    SensorConfig,
)
from v2xlake.schemas.errors import ClipError, DeliveryConflict
from v2xlake.schemas.geometry import Transform
from v2xlake.schemas.stage import OutputFile, Stage, StageReport
from v2xlake.schemas.tables import (
    INGEST_TABLES,
    AgentRow,
    CalibratedSensorRow,
    CameraFrameRow,
    ClipRow,
    EgoPoseRow,
    GnssRow,
    ImuRow,
    InsRow,
    LidarFrameRow,
    LidarPointRow,
    RadarFrameRow,
    RadarPointRow,
    SensorRow,
)
from v2xlake.storage.lake import Lake, TableWriter
from v2xlake.tasks.cores import available_cores
from v2xlake.tasks.ingest import DECLARATION
from v2xlake.tasks.ingest.annotations import annotation_tables, load_annotations
from v2xlake.tasks.ingest.bagopen import (
    STAGE,
    build_typestore,
    connections_by_topic,
    header_stamp_ns,
    knows_type,
    open_bag,
    resolve,
)
from v2xlake.tasks.ingest.calibration import TfTree, intrinsics_from_camera_info
from v2xlake.tasks.ingest.clipdir import (
    bag_files,
    check_inputs,
    delivery_roots,
    load_clip_config,
    plain_files,
)
from v2xlake.tasks.ingest.config import IngestConfig
from v2xlake.tasks.ingest.images import JPEG_MAGIC, compressed_image, image_to_png
from v2xlake.tasks.ingest.ins import GnssDecoder, ImuDecoder
from v2xlake.tasks.ingest.payloads import messages as in_place_messages
from v2xlake.tasks.ingest.pointcloud import DecodedCloud, decode_cloud, decode_radar
from v2xlake.tasks.ingest.pose import (
    PoseCollector,
    PoseError,
    Track,
    ins_columns,
    map_columns,
)
from v2xlake.tasks.ingest.rawmsg import parser_for
from v2xlake.tasks.ingest.rows import table_of

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
ACCEPTED: dict[Modality, tuple[str, ...]] = {
    Modality.LIDAR: (POINTCLOUD2,),
    Modality.RADAR: (POINTCLOUD2,),
    Modality.CAMERA: ("sensor_msgs/msg/CompressedImage", "sensor_msgs/msg/Image"),
    Modality.IMU: ("sensor_msgs/msg/Imu",),
    Modality.GNSS: ("sensor_msgs/msg/NavSatFix",),
}


def _payload_digest(msg: Any) -> bytes:
    """Digest of what a LiDAR / camera / radar message carries (its data bytes and
    layout, not its header: a re-published frame may get a new sequence number)."""
    h = xxhash.xxh3_128()  # ~20 GB/s: nothing next to decoding the frame
    for name in ("height", "width", "point_step", "row_step", "encoding", "format",
                 "is_bigendian", "step"):
        h.update(f"{name}={getattr(msg, name, None)!r};".encode())
    for f in getattr(msg, "fields", None) or ():
        h.update(f"{getattr(f, 'name', '')}:{getattr(f, 'offset', '')}:"
                 f"{getattr(f, 'datatype', '')}:{getattr(f, 'count', '')};".encode())
    data = getattr(msg, "data", b"")
    h.update(memoryview(data).cast("B") if not isinstance(data, bytes | bytearray) else data)
    return h.digest()


DELIVERY = "delivery.json"


def delivery_of(clip_dir: Path, cfg: ClipConfig) -> dict[str, Any]:
    """The delivery's identity: the checksum of every bag file (clip.yaml may be fixed and
    re-delivered for the same bags; different bags are a different recording)."""
    from v2xlake.storage.manifest import file_checksum

    bags: dict[str, str] = {}
    for a in cfg.agents:
        bag = resolve(clip_dir, a.bag)
        for f in bag_files(bag):
            rel = f.relative_to(bag).as_posix() if bag.is_dir() else f.name
            bags[f"{a.agent_id}/{rel}"] = file_checksum(f)
    digest = hashlib.sha256(json.dumps(bags, sort_keys=True).encode()).hexdigest()
    return {"clip_id": cfg.clip_id, "fingerprint": digest, "bags": bags}


def check_delivery(lake: Lake, clip_dir: Path, cfg: ClipConfig, replace: bool
                   ) -> dict[str, Any]:
    """Refuse a different delivery under an existing clip id (``DeliveryConflict``)."""
    mine = delivery_of(clip_dir, cfg)
    path = lake.path("landing", cfg.clip_id, DELIVERY)
    if lake.exists(path) and not replace:
        theirs = lake.read_json(path)
        if theirs.get("fingerprint") != mine["fingerprint"]:
            changed = sorted(k for k in {*theirs.get("bags", {}), *mine["bags"]}
                             if theirs.get("bags", {}).get(k) != mine["bags"].get(k))
            raise DeliveryConflict(
                cfg.clip_id, f"clip id {cfg.clip_id!r} is already in the lake with other bags "
                f"({len(changed)} file(s) differ, e.g. {changed[:3]}); refused, the existing "
                "clip is untouched (give the recording its own clip_id, or replace it "
                "explicitly with ingest.replace_existing)", path=str(clip_dir / "clip.yaml"),
                stage=STAGE)
    return mine


def copy_to_landing(lake: Lake, clip_dir: Path, cfg: ClipConfig,
                    allowed_roots: Sequence[str] = ()) -> int:
    """Copy the clip as delivered into ``landing/<clip_id>/`` (the simulator's ``truth/`` is
    not part of the input contract and stays out). Bags that live outside the clip folder go
    to ``external/<agent>/`` and the landing clip.yaml is rewritten to point at them (the
    original is kept as ``clip.delivered.yaml``). Files are hard-linked when the lake is local
    and on the same filesystem (bags as delivered are immutable; copying a 10 GB clip would
    cost more than ingesting it), otherwise copied. Landing holds regular files only: every
    symlink is resolved first and refused when it points outside the clip folder and the
    operator-allowed roots (``plain_files``), before the old landing copy is touched."""
    roots = delivery_roots(clip_dir, allowed_roots)
    files = plain_files(clip_dir, roots, cfg.clip_id, skip_top=frozenset({"truth"}))
    rewrite: dict[str, str] = {}
    for a in cfg.agents:
        bag = resolve(clip_dir, a.bag)
        if bag.is_relative_to(clip_dir):
            continue
        dest = f"external/{a.agent_id}/{bag.name}"
        if bag.is_dir():
            files += [(f"{dest}/{rel}", real) for rel, real in plain_files(
                bag, roots, cfg.clip_id, agent_id=a.agent_id)]
        else:
            files.append((dest, os.path.realpath(bag)))
        rewrite[a.agent_id] = dest
    root = lake.path("landing", cfg.clip_id)
    lake.delete_dir(root)
    n = 0
    for rel, real in files:
        n += lake.copy_in(real, f"{root}/{rel}", link=True)
    if rewrite:
        data = cfg.model_dump(mode="json", exclude_none=True)
        for a in data["agents"]:
            a["bag"] = rewrite.get(a["agent_id"], a["bag"])
        lake.write_bytes(f"{root}/clip.delivered.yaml", (clip_dir / "clip.yaml").read_bytes())
        lake.write_bytes(f"{root}/clip.yaml", yaml.safe_dump(data, sort_keys=False).encode())
    return n


# --------------------------------------------------------------------------- per agent
@dataclass
class AgentResult:
    sensors: list[SensorRow] = field(default_factory=list)
    calib: list[CalibratedSensorRow] = field(default_factory=list)
    lidar_frames: dict[str, int] = field(default_factory=dict)
    n_points: int = 0
    n_camera_frames: int = 0
    bytes_read: int = 0
    t_min: int | None = None
    t_max: int | None = None
    has_ins: bool = False
    pose_frame: str | None = None  # "ecef" (written as raw ins) | "map" (raw ego_poses)

    def stamp(self, t0: int, t1: int | None = None) -> None:
        t1 = t0 if t1 is None else t1
        self.t_min = t0 if self.t_min is None else min(self.t_min, t0)
        self.t_max = t1 if self.t_max is None else max(self.t_max, t1)


class _AgentIngest:
    """State of one agent's single pass over its bag."""

    def __init__(self, staging: Lake, cfg: ClipConfig, agent: AgentConfig,
                 config: IngestConfig, notes: list[str]) -> None:
        self.staging, self.cfg, self.agent, self.config, self.notes = (
            staging, cfg, agent, config, notes)
        self.cid, self.aid = cfg.clip_id, agent.agent_id
        self.res = AgentResult()
        self.counts: dict[str, int] = {s.name: 0 for s in agent.sensors}
        self.frame_ids: dict[str, str] = {}
        self.lidar_rows: list[dict[str, Any]] = []
        self.radar_rows: list[dict[str, Any]] = []
        self.radar_parts: dict[str, list[pa.Table]] = {}
        self.cam_rows: list[dict[str, Any]] = []
        self.png_pool: ThreadPoolExecutor | None = None
        # camera frames being encoded: (sensor, frame index, stamp, blob key, (w, h, sha256))
        self.png_pending: deque[tuple[SensorConfig, int, int, str,
                                      Future[tuple[int, int, str]]]] = deque()
        self.pose = PoseCollector(agent, config.quat_tolerance)
        self.imu: dict[str, ImuDecoder] = {}
        self.gnss = GnssDecoder()
        self.tf = TfTree(config.quat_tolerance)
        # per sensor, in bag order: stamps seen (duplicates dropped), the last stamp, and
        # how many messages repeated a stamp or went back in time (QA reports both)
        self.stamps_seen: dict[str, set[int]] = {s.name: set() for s in agent.sensors}
        # LiDAR / camera / radar: stamp -> digest of the frame's payload (a repeat with the
        # same payload is dropped, one with another payload refused)
        self.frame_digest: dict[str, dict[int, bytes]] = {s.name: {} for s in agent.sensors}
        self.last_stamp: dict[str, int] = {}
        self.n_dup: dict[str, int] = {s.name: 0 for s in agent.sensors}
        self.n_dropped: dict[str, int] = {s.name: 0 for s in agent.sensors}
        self.n_back: dict[str, int] = {s.name: 0 for s in agent.sensors}
        self.camera_info: dict[str, Any] = {}
        self.writers: dict[str, TableWriter] = {}
        self.point_schema = arrow_schema(LidarPointRow)
        self.bag: Path | None = None

    def err(self, reason: str, topic: str | None = None, path: str | None = None) -> ClipError:
        return ClipError(self.cid, reason, agent_id=self.aid, topic=topic,
                         path=path or str(self.bag), stage=STAGE)

    # -- validation against the bag's connections
    def plan(self, reader: Any) -> dict[str, Callable[[Any, Any], None]]:
        conns = connections_by_topic(reader)
        topics = sorted(conns)
        handlers: dict[str, Callable[[Any, Any], None]] = {}
        for s in self.agent.sensors:
            if s.topic not in conns:
                raise self.err(f"topic configured for sensor {s.name} ({s.modality.value}) is "
                               f"not in the bag; the bag has {topics}", topic=s.topic)
            have = conns[s.topic].msgtype
            if have != s.msg_type:
                raise self.err(f"clip.yaml says sensor {s.name} carries {s.msg_type} but the "
                               f"bag's topic carries {have}", topic=s.topic)
            accepted = ACCEPTED.get(s.modality)
            if not knows_type(reader, have):
                hint = (f"; {s.modality.value} sensors need one of {list(accepted)}"
                        if accepted else "; add its .msg file to clip.yaml message_definitions")
                raise self.err(f"message type {have} is unknown: not defined in the bag, not a "
                               f"standard ROS 2 type and not in clip.yaml message_definitions"
                               f"{hint}", topic=s.topic)
            if accepted and have not in accepted:
                extra = (" (raw packets must be decoded to PointCloud2 before ingest)"
                         if s.modality is Modality.LIDAR else "")
                raise self.err(f"{s.modality.value} sensor {s.name} carries {have}, which "
                               f"ingest cannot read; expected one of {list(accepted)}{extra}",
                               topic=s.topic)
            handlers[s.topic] = self._handler(s)
            if (s.modality is Modality.INS and s.name not in self.pose.sensors):
                self.notes.append(f"{self.aid}/{s.name}: INS sensor not used by the agent's "
                                  "pose block; its messages are counted, not read")
            if s.modality is Modality.CAMERA and s.intrinsics is None:
                if not s.camera_info_topic:
                    raise self.err(f"camera {s.name} has neither intrinsics in clip.yaml nor a "
                                   "camera_info_topic", topic=s.topic)
                if s.camera_info_topic not in conns:
                    raise self.err(f"camera_info_topic of camera {s.name} is not in the bag; "
                                   f"the bag has {topics}", topic=s.camera_info_topic)
                handlers[s.camera_info_topic] = self._camera_info(s.name)
        try:
            self.pose.plan()
        except PoseError as e:
            raise self.err(str(e), topic=self._topic_of(e.sensor)) from e
        tf_topic = self.agent.tf_static_topic
        if tf_topic and tf_topic in conns:
            handlers[tf_topic] = self._tf_static
        elif tf_topic and any(s.extrinsic is None for s in self.agent.sensors
                              if s.modality in (Modality.LIDAR, Modality.CAMERA)):
            raise self.err(f"tf_static topic is not in the bag and not every LiDAR/camera has "
                           f"an extrinsic in clip.yaml; the bag has {topics}", topic=tf_topic)
        return handlers

    def _topic_of(self, sensor: str | None) -> str | None:
        return self.agent.sensor(sensor).topic if sensor else None

    def _tf_static(self, msg: Any, _c: Any) -> None:
        try:
            self.tf.add_message(msg)
        except ValueError as e:
            raise self.err(str(e), topic=self.agent.tf_static_topic) from e

    def _camera_info(self, name: str) -> Callable[[Any, Any], None]:
        def h(msg: Any, _c: Any) -> None:
            self.camera_info.setdefault(name, msg)
        return h

    def _handler(self, s: SensorConfig) -> Callable[[Any, Any], None]:
        if s.modality is Modality.LIDAR:
            return lambda msg, _c: self._lidar(s, msg)
        if s.modality is Modality.CAMERA:
            return lambda msg, _c: self._camera(s, msg)
        if s.modality is Modality.RADAR:
            return lambda msg, _c: self._radar(s, msg)
        if s.modality is Modality.INS:
            return lambda msg, _c: self._simple(s, msg, None)
        if s.modality is Modality.IMU:
            return lambda msg, _c: self._simple(s, msg, self.imu.setdefault(s.name, ImuDecoder()))
        return lambda msg, _c: self._simple(s, msg, self.gnss)

    def _order(self, s: SensorConfig, stamp: int, drop_duplicates: bool) -> bool:
        """Record the stamp's place in bag order; False for a repeated stamp that is dropped."""
        seen = self.stamps_seen[s.name]
        if stamp in seen:
            self.n_dup[s.name] += 1
            if drop_duplicates:
                return False
        seen.add(stamp)
        last = self.last_stamp.get(s.name)
        if last is not None and stamp < last:
            self.n_back[s.name] += 1
        self.last_stamp[s.name] = stamp
        return True

    def _frame_is_new(self, s: SensorConfig, stamp: int, msg: Any) -> bool:
        """LiDAR / camera / radar: False for a message repeating an earlier frame of its
        topic (same stamp, same payload: a driver publishing twice, a bag recorded from two
        nodes), which is dropped and counted; a ClipError for one that repeats a stamp with
        another payload (two different frames claim one time: which is right cannot be
        known). Before, both were kept: every scan twice, 1.5x the points."""
        digest = _payload_digest(msg)
        seen = self.frame_digest[s.name]
        first = seen.setdefault(stamp, digest)
        if first is digest:
            return True
        if first != digest:
            idx = self.counts[s.name] - self.n_dropped[s.name]
            raise self.err(f"two different {s.modality.value} frames with the same stamp "
                           f"{stamp} ns on this topic (message {idx} repeats the stamp of an "
                           "earlier one with another payload); which one is right cannot be "
                           "known", topic=s.topic)
        self.n_dup[s.name] += 1
        self.n_dropped[s.name] += 1
        return False

    def _new_frame(self, s: SensorConfig, msg: Any) -> tuple[int, int] | None:
        """(stamp, frame index) of a LiDAR / radar / camera message, recorded in bag order;
        None for a repeat of an earlier frame, which is counted and dropped."""
        stamp = header_stamp_ns(msg)
        if not self._frame_is_new(s, stamp, msg):
            self.counts[s.name] += 1
            return None
        idx = self._first(s, msg)
        self._order(s, stamp, drop_duplicates=False)
        return stamp, idx

    def _first(self, s: SensorConfig, msg: Any) -> int:
        """The frame index of this message (messages kept so far) and count it."""
        idx = self.counts[s.name] - self.n_dropped[s.name]
        self.counts[s.name] += 1
        if idx == 0 and (s.frame_id or hasattr(msg, "header")):
            self.frame_ids[s.name] = s.frame_id or str(msg.header.frame_id)
        return idx

    def _simple(self, s: SensorConfig, msg: Any, dec: ImuDecoder | GnssDecoder | None) -> None:
        """INS / IMU / GNSS: a message repeating a stamp of its topic is a duplicate (a
        driver publishing twice, a bag recorded from two nodes): dropped and counted."""
        self._first(s, msg)
        stamp = header_stamp_ns(msg) if hasattr(msg, "header") else None
        if stamp is not None and not self._order(s, stamp, drop_duplicates=True):
            self.n_dropped[s.name] += 1
            return
        if dec is not None:
            dec.add(msg)
        if s.name in self.pose.samples:
            try:
                self.pose.add(s.name, msg)
            except (AttributeError, PoseError) as e:
                raise self.err(f"pose message: {e}", topic=s.topic) from e
        if stamp is not None:
            self.res.stamp(stamp)

    def _lidar(self, s: SensorConfig, msg: Any) -> None:
        if (frame := self._new_frame(s, msg)) is None:
            return
        stamp, idx = frame
        assert s.fields is not None
        try:
            cloud = decode_cloud(msg, s.fields, stamp, min_range_m=self.config.min_range_m,
                                 max_time_offset_ns=int(self.config.max_point_time_offset_s
                                                        * 1e9))
        except (KeyError, ValueError) as e:
            raise self.err(f"LiDAR frame {idx}: {e}", topic=s.topic) from e
        if cloud.n_points == 0:
            self.notes.append(f"{self.aid}/{s.name} frame {idx}: no point with a return "
                              f"({cloud.n_nan} non-finite, {cloud.n_zero} at zero range)")
        w = self.writers.get(s.name)
        if w is None:
            w = self.staging.open_writer("raw", "lidar_points", self.point_schema,
                                         clip_id=self.cid, agent_id=self.aid, name=s.name,
                                         background=True)
            self.stack.enter_context(w)
            self.writers[s.name] = w
        w.write(_points_table(s.name, idx, cloud))
        self.res.n_points += cloud.n_points
        self.lidar_rows.append(dict(
            sensor=s.name, frame_idx=idx, stamp_ns=stamp, t_start_ns=cloud.t_start_ns,
            t_end_ns=cloud.t_end_ns, n_points=cloud.n_points, n_nan=cloud.n_nan,
            n_zero=cloud.n_zero))
        self.res.stamp(min(stamp, cloud.t_start_ns), max(stamp, cloud.t_end_ns))

    def _radar(self, s: SensorConfig, msg: Any) -> None:
        if (frame := self._new_frame(s, msg)) is None:
            return
        stamp, idx = frame
        assert s.fields is not None
        try:
            r = decode_radar(msg, s.fields, stamp, max_time_offset_ns=int(
                self.config.max_point_time_offset_s * 1e9))
        except (KeyError, ValueError) as e:
            raise self.err(f"radar frame {idx}: {e}", topic=s.topic) from e
        n = r.n_points
        self.radar_parts.setdefault(s.name, []).append(pa.Table.from_arrays([
            pa.DictionaryArray.from_arrays(pa.array(np.zeros(n, np.int32)), pa.array([s.name])),
            pa.array(np.full(n, idx, np.int32)), pa.array(r.t_ns), pa.array(r.x),
            pa.array(r.y), pa.array(r.z), pa.array(r.velocity), pa.array(r.rcs)],
            schema=RADAR_FILE_SCHEMA))
        self.radar_rows.append(dict(sensor=s.name, frame_idx=idx, stamp_ns=stamp,
                                    t_start_ns=r.t_start_ns, t_end_ns=r.t_end_ns,
                                    n_points=n, n_nan=r.n_nan))
        self.res.stamp(min(stamp, r.t_start_ns), max(stamp, r.t_end_ns))

    def _camera(self, s: SensorConfig, msg: Any) -> None:
        """Hand the frame to the PNG pool: encoding is most of a camera's ingest time
        (``bench_ingest.py``, camera case) and OpenCV releases the GIL, so frames are encoded
        on every core while the bag is read; rows are still recorded in frame order."""
        if (frame := self._new_frame(s, msg)) is None:
            return
        stamp, idx = frame
        compressed = s.msg_type.endswith("CompressedImage")
        # a JPEG is stored as delivered (its bytes, checksummed); other formats become PNG
        jpeg = compressed and bytes(np.asarray(msg.data[:3], np.uint8)) == JPEG_MAGIC
        key = self.staging.blob_key(self.cid, self.aid, s.name, idx,
                                    ext="jpg" if jpeg else "png")
        if self.png_pool is None:
            self.png_pool = self.stack.enter_context(
                ThreadPoolExecutor(PNG_WORKERS, thread_name_prefix="png"))
        job = self.png_pool.submit(_store_image, self.staging, key, msg, compressed,
                                   self.config.png_compression)
        self.png_pending.append((s, idx, stamp, key, job))
        self.res.n_camera_frames += 1
        self.res.stamp(stamp)
        self._collect_pngs(keep=2 * PNG_WORKERS)

    def _collect_pngs(self, keep: int = 0) -> None:
        """Record finished frames, oldest first, until at most ``keep`` are in flight."""
        while len(self.png_pending) > keep:
            s, idx, stamp, key, job = self.png_pending.popleft()
            try:
                w, h, digest = job.result()
            except ValueError as e:
                raise self.err(f"camera {s.name} frame {idx}: {e}", topic=s.topic) from e
            self.cam_rows.append(dict(sensor=s.name, frame_idx=idx, stamp_ns=stamp, width=w,
                                      height=h, blob=key, sha256=digest))

    # -- the pass
    def run(self, bag: Path, typestore: Any) -> AgentResult:
        self.bag = bag
        with ExitStack() as stack, open_bag(
            self.cid, self.agent, bag, typestore,
            recover_empty_storage_id=self.config.recover_empty_storage_id, notes=self.notes,
        ) as reader:
            self.stack = stack
            handlers = self.plan(reader)
            conns = [c for c in reader.connections if c.topic in handlers]
            seen: dict[int, int] = {id(c): 0 for c in conns}
            # PointCloud2 / images: direct parse of the wire format (rawmsg.py) when the bag
            # defines them as standard ROS does, from payloads read in place (payloads.py);
            # everything else through rosbags
            fdefs, ros2 = reader.typestore.fielddefs, bool(reader.is2)
            fast = {id(c): parser_for(fdefs, c.msgtype, ros2) for c in conns}
            try:
                # (rosbags reads every connection when given none: nothing to read then)
                for conn, _t, raw in in_place_messages(reader, conns) if conns else ():
                    self.res.bytes_read += len(raw)
                    seen[id(conn)] += 1
                    parse = fast[id(conn)]
                    msg: Any = parse(raw) if parse is not None else None
                    if msg is None:  # rosbags expects bytes (its messages may keep views)
                        msg = reader.deserialize(bytes(raw), conn.msgtype)
                    handlers[conn.topic](msg, conn)
            except ClipError:
                raise
            except Exception as e:  # rosbags / sqlite / mcap errors on a damaged file
                raise self.err(f"reading the bag failed after {sum(self.counts.values())} "
                               f"messages ({type(e).__name__}: {e}); truncated or corrupt?",
                               path=str(bag)) from e
            self._collect_pngs()
            for c in conns:  # a cut file can end cleanly between messages: count them
                if c.msgcount and seen[id(c)] < c.msgcount:
                    raise self.err(f"the bag's index promises {c.msgcount} messages on this "
                                   f"topic but only {seen[id(c)]} could be read; truncated?",
                                   topic=c.topic, path=str(bag))
        self.track = self._pose_track()
        self._write_tables()
        return self.res

    def _static(self, a: str, b: str) -> np.ndarray | None:
        """Static ``T_a_b``: a pose sensor's clip.yaml extrinsic when its frame is ``a`` and
        ``b`` is the ego frame, else tf_static."""
        ego = self.agent.ego_frame.lstrip("/")
        for s in self.agent.sensors:
            frame = (s.frame_id or self.frame_ids.get(s.name) or "").lstrip("/")
            if s.extrinsic is not None and frame == a and b == ego:
                return np.linalg.inv(s.extrinsic.matrix())
        return self.tf.lookup(a, b)

    def _pose_track(self) -> Track | None:
        span = (self.res.t_min or 0, self.res.t_max or 0)
        try:
            track = self.pose.build(self._static, span)
        except PoseError as e:
            raise self.err(f"pose ({self.pose.pose.kind}): {e}",
                           topic=self._topic_of(e.sensor)) from e
        except ValueError as e:
            raise self.err(f"pose ({self.pose.pose.kind}): {e}") from e
        if track is not None:
            self.res.pose_frame = track.frame
            self.res.stamp(int(track.t_ns[0]), int(track.t_ns[-1]))
        self.res.has_ins = track is not None
        return track

    def _write_tables(self) -> None:
        st, cid, aid = self.staging, self.cid, self.aid
        for s in self.agent.sensors:
            self.res.sensors.append(SensorRow(
                clip_id=cid, agent_id=aid, sensor=s.name, modality=s.modality.value,
                topic=s.topic, msg_type=s.msg_type,
                n_messages=self.counts[s.name] - self.n_dropped[s.name],
                n_duplicates=self.n_dup[s.name], n_backwards=self.n_back[s.name]))
            if self.n_dup[s.name]:
                self.notes.append(f"{aid}/{s.name}: {self.n_dup[s.name]} message(s) on "
                                  f"{s.topic} repeat an earlier stamp"
                                  + (": dropped" if self.n_dropped[s.name] else ""))
            if s.modality is Modality.LIDAR:
                self.res.lidar_frames[s.name] = self.counts[s.name] - self.n_dropped[s.name]
        self.res.calib = self._calibration()
        self._check_image_sizes()
        ins_cols = (ins_columns(self.track) if self.track is not None
                    and self.track.frame == "ecef" else {c: np.zeros(0) for c in _INS_COLS})
        map_cols = (map_columns(self.track) if self.track is not None
                    and self.track.frame == "map" else {c: np.zeros(0) for c in _MAP_COLS})
        tables: dict[str, pa.Table] = {
            "sensors": table_of(SensorRow, self.res.sensors),
            "calibrated_sensors": table_of(CalibratedSensorRow, self.res.calib),
            "lidar_frames": _frame_table(LidarFrameRow, self.lidar_rows, cid, aid),
            "camera_frames": _frame_table(CameraFrameRow, self.cam_rows, cid, aid),
            "radar_frames": _frame_table(RadarFrameRow, self.radar_rows, cid, aid),
            "ins": _cols_table(InsRow, ins_cols, cid, aid),
            "gnss": _cols_table(GnssRow, self.gnss.cols, cid, aid),
            "imu": pa.concat_tables([
                _cols_table(ImuRow, {**d.cols, "sensor": [n] * len(d.cols["t_ns"])}, cid, aid)
                for n, d in self.imu.items()]) if self.imu else arrow_schema(ImuRow).empty_table(),
        }
        for name, parts in self.radar_parts.items():  # one file per radar, like LiDARs
            st.write_table("raw", "radar_points", pa.concat_tables(parts).unify_dictionaries(),
                           clip_id=cid, agent_id=aid, name=name, row_group_by="frame_idx")
        if len(map_cols["t_ns"]):  # only a track in a local map (the catalog's ego_poses
            # name reads raw until anonymize has written the clean one)
            tables["ego_poses"] = _cols_table(EgoPoseRow, map_cols, cid, aid)
        for name, t in tables.items():
            st.write_table("raw", name, t, clip_id=cid, agent_id=aid)

    def _check_image_sizes(self) -> None:
        """Every frame of a camera must have the size its intrinsics were calibrated for:
        a 1920x1080 calibration on 1920x1200 images projects every point to the wrong row."""
        sizes: dict[str, set[tuple[int, int]]] = {}
        for r in self.cam_rows:
            sizes.setdefault(r["sensor"], set()).add((int(r["width"]), int(r["height"])))
        for c in self.res.calib:
            if c.modality != "camera" or c.width is None or c.sensor not in sizes:
                continue
            s = self.agent.sensor(c.sensor)
            got = sorted(sizes[c.sensor])
            if got != [(c.width, c.height)]:
                # where the intrinsics came from (``source`` also names the extrinsic's)
                src = ("clip.yaml intrinsics" if s.intrinsics is not None
                       else f"CameraInfo intrinsics (topic {s.camera_info_topic})")
                raise self.err(
                    f"camera {c.sensor}: images are {', '.join(f'{w}x{h}' for w, h in got)} "
                    f"but its {src} are for {c.width}x{c.height}; the calibration does not "
                    "belong to these images", topic=s.topic)

    def _calibration(self) -> list[CalibratedSensorRow]:
        rows = []
        for s in self.agent.sensors:
            frame = s.frame_id or self.frame_ids.get(s.name)
            source: list[str] = []
            T: Transform | None = None
            if s.extrinsic is not None:
                T, source = s.extrinsic, ["clip.yaml"]
            elif frame is not None and (
                    m := self.tf.lookup(self.agent.ego_frame, frame)) is not None:
                T, source = Transform.from_matrix(m), ["tf_static"]
                if (d := float(np.linalg.norm(T.translation))) > MAX_SENSOR_OFFSET_M:
                    raise self.err(
                        f"sensor {s.name}: tf_static puts frame {frame!r} {d:.6g} m from ego "
                        f"frame {self.agent.ego_frame!r} (at most {MAX_SENSOR_OFFSET_M:g} m: a "
                        "sensor sits on its agent)", topic=s.topic)
            elif s.modality is Modality.INS:
                T, source = Transform.identity(), ["ego_frame"]
            if T is None:
                if s.modality in (Modality.LIDAR, Modality.CAMERA):
                    raise self.err(
                        f"no extrinsic for sensor {s.name}: frame {frame!r} is not connected to "
                        f"ego frame {self.agent.ego_frame!r} in tf_static (frames "
                        f"{self.tf.frames}) and clip.yaml gives no extrinsic", topic=s.topic)
                self.notes.append(f"{self.aid}/{s.name}: no extrinsic (frame {frame!r}); "
                                  "no calibrated_sensors row")
                continue
            intr = s.intrinsics
            if s.modality is Modality.CAMERA and intr is None:
                info = self.camera_info.get(s.name)
                if info is None:
                    raise self.err(f"camera {s.name}: no CameraInfo message on its "
                                   "camera_info_topic", topic=s.camera_info_topic)
                try:
                    intr = intrinsics_from_camera_info(info)
                except (ValidationError, ValueError) as e:
                    raise self.err(f"camera {s.name}: bad CameraInfo: {e}",
                                   topic=s.camera_info_topic) from e
                source.append("camera_info")
            elif intr is not None:
                source.append("clip.yaml")
            t, q = T.translation, T.rotation
            rows.append(CalibratedSensorRow(
                clip_id=self.cid, agent_id=self.aid, sensor=s.name, modality=s.modality.value,
                tx=t[0], ty=t[1], tz=t[2], qw=q[0], qx=q[1], qy=q[2], qz=q[3],
                width=intr.width if intr else None, height=intr.height if intr else None,
                fx=intr.fx if intr else None, fy=intr.fy if intr else None,
                cx=intr.cx if intr else None, cy=intr.cy if intr else None,
                distortion_model=intr.distortion_model.value if intr else None,
                distortion=list(intr.distortion) if intr else None,
                source="+".join(dict.fromkeys(source))))
        return rows


PNG_WORKERS = min(8, available_cores())


def _store_image(lake: Lake, key: str, msg: Any, compressed: bool, level: int
                 ) -> tuple[int, int, str]:
    """One camera frame as a blob: a delivered JPEG or PNG as is, anything else as a lossless
    PNG; returns (width, height, SHA-256 of the stored bytes)."""
    data, w, h = (compressed_image if compressed else image_to_png)(msg, level)
    lake.write_blob("raw", key, data)
    return w, h, hashlib.sha256(data).hexdigest()


_INS_COLS = ("t_ns", "lat", "lon", "alt", "roll", "pitch", "azimuth", "ve", "vn", "vu",
             "rtk_status")
_MAP_COLS = ("t_ns", "x", "y", "z", "qw", "qx", "qy", "qz", "vx", "vy", "vz", "rtk_status")


POINT_FILE_SCHEMA = arrow_schema(LidarPointRow).remove(0).remove(0)  # minus clip_id, agent_id
RADAR_FILE_SCHEMA = arrow_schema(RadarPointRow).remove(0).remove(0)
_ZEROS = np.zeros(0, np.int32)


def _points_table(sensor: str, idx: int, c: DecodedCloud) -> pa.Table:
    """One frame as a table of exactly the writer's schema (no cast in ``TableWriter.write``);
    numeric columns wrap the decoded arrays without a copy."""
    global _ZEROS
    n = c.n_points
    if _ZEROS.size < n:  # shared, never written: the dictionary indices of the sensor column
        _ZEROS = np.zeros(max(n, 2 * _ZEROS.size), np.int32)
        _ZEROS.flags.writeable = False
    arrays = [
        pa.DictionaryArray.from_arrays(pa.array(_ZEROS[:n]), pa.array([sensor]), safe=False),
        pa.array(np.full(n, idx, np.int32)), pa.array(c.t_ns), pa.array(c.x), pa.array(c.y),
        pa.array(c.z), pa.array(c.intensity), pa.array(c.ring), pa.array(c.return_id),
    ]
    return pa.Table.from_arrays(arrays, schema=POINT_FILE_SCHEMA)


def _frame_table(model: type[BaseModel], rows: list[dict[str, Any]], cid: str, aid: str
                 ) -> pa.Table:
    return table_of(model, [{**r, "clip_id": cid, "agent_id": aid} for r in rows])


def _cols_table(model: type[BaseModel], cols: Mapping[str, Sequence[Any] | np.ndarray],
                cid: str, aid: str) -> pa.Table:
    n = len(cols["t_ns"])
    data: dict[str, Any] = {k: np.asarray(v) if k != "sigma_h" else pa.array(v, pa.float64())
                            for k, v in cols.items()}
    data["clip_id"], data["agent_id"] = [cid] * n, [aid] * n
    return columns_to_table(model, data)


def check_agents(cfg: ClipConfig, results: dict[str, AgentResult], config: IngestConfig
                 ) -> None:
    """What makes several recordings one clip: their pose tracks live in one world (all
    georeferenced, or all in the same local map), and every agent recorded while the
    reference agent did."""
    frames = {aid: r.pose_frame for aid, r in results.items() if r.pose_frame}
    if len(set(frames.values())) > 1:
        kinds = {"ecef": "georeferenced (WGS84)", "map": "in a local map without geodetic "
                 "reference (datum: local)"}
        raise ClipError(cfg.clip_id, "the agents' poses are not in one world: " + "; ".join(
            f"{aid} {kinds[f]}" for aid, f in sorted(frames.items())) + ". Give every agent a "
            "geodetic datum (UTM zone, geodetic origin) or none of them", stage=STAGE)
    ref = cfg.reference_agent.agent_id
    r0 = results[ref]
    if r0.t_min is None or r0.t_max is None:
        return
    need = int(config.min_agent_overlap_s * 1e9)
    for aid, r in results.items():
        if aid == ref or r.t_min is None or r.t_max is None:
            continue
        overlap = min(r.t_max, r0.t_max) - max(r.t_min, r0.t_min)
        if overlap <= need:
            raise ClipError(
                cfg.clip_id, f"agent {aid} recorded [{r.t_min}, {r.t_max}] ns and the "
                f"reference agent {ref} [{r0.t_min}, {r0.t_max}] ns: they "
                + ("do not overlap in time" if overlap <= 0 else
                   f"overlap by only {overlap / 1e9:.3f} s (ingest.min_agent_overlap_s "
                   f"{config.min_agent_overlap_s:g})")
                + "; recordings that were not made together are not one clip",
                agent_id=aid, stage=STAGE)


# --------------------------------------------------------------------------- entry point
def run_ingest(lake: Lake, clip_dir: str | Path, config: IngestConfig | None = None
               ) -> StageReport:
    """Ingest one clip folder into ``lake``'s landing and raw zones; see the module doc."""
    config = config or IngestConfig()
    t0 = time.perf_counter()
    d = Path(clip_dir).resolve()
    cfg = load_clip_config(d)
    cid = cfg.clip_id
    check_inputs(d, cfg, config.allowed_bag_roots)
    delivery = check_delivery(lake, d, cfg, config.replace_existing)
    typestore = build_typestore(d, cfg)
    notes: list[str] = []
    if config.copy_to_landing:
        copy_to_landing(lake, d, cfg, config.allowed_bag_roots)
        lake.write_json(lake.path("landing", cid, DELIVERY), delivery)
    if lake.discard_staging(cid):
        notes.append(f"removed stale staging output of an earlier, interrupted ingest of {cid}")
    # the flow hands ingest an unstaged handle (Stage.atomic is off): it stages itself, since
    # its publish replaces the clip's whole raw zone (replace_clip), not only its own tables
    staging = lake.for_stage(STAGE, _OWNS, atomic_clip=cid,
                             reads=lake.reads)
    try:
        results: dict[str, AgentResult] = {}
        for agent in cfg.agents:
            results[agent.agent_id] = _AgentIngest(staging, cfg, agent, config, notes).run(
                resolve(d, agent.bag), typestore)
            if not results[agent.agent_id].has_ins:
                notes.append(f"agent {agent.agent_id}: no pose (pose source "
                             f"{agent.effective_pose.kind!r}): deskew/registration impossible")
        check_agents(cfg, results, config)
        if cfg.annotations:
            path = resolve(d, cfg.annotations)
            frames = {(a, s): n for a, r in results.items() for s, n in r.lidar_frames.items()}
            try:
                for aid, t in annotation_tables(load_annotations(path, cid), frames).items():
                    staging.write_table("raw", "annotations", t, clip_id=cid, agent_id=aid)
            except (ValidationError, ValueError, OSError) as e:
                raise ClipError(cid, f"bad annotation file: {e}", path=str(path),
                                stage=STAGE) from e
        for aid, r in results.items():
            a = cfg.agent(aid)
            dims = a.dimensions
            staging.write_table("raw", "agents", table_of(AgentRow, [AgentRow(
                clip_id=cid, agent_id=aid, kind=a.kind.value, role=a.role.value,
                has_ins=r.has_ins, pose_source=a.effective_pose.kind,
                pose_frame={"ecef": "wgs84", "map": "map"}.get(r.pose_frame or ""),
                **({} if dims is None else dict(
                    length_m=dims.length_m, width_m=dims.width_m, height_m=dims.height_m,
                    body_dx=dims.center_in_ego[0], body_dy=dims.center_in_ego[1],
                    body_dz=dims.center_in_ego[2])))]), clip_id=cid, agent_id=aid)
        tmins = [r.t_min for r in results.values() if r.t_min is not None]
        tmaxs = [r.t_max for r in results.values() if r.t_max is not None]
        if not tmins:
            raise ClipError(cid, "no sensor message in any bag", stage=STAGE)
        duration = (max(tmaxs) - min(tmins)) / 1e9
        staging.write_table("raw", "clips", table_of(ClipRow, [ClipRow(
            clip_id=cid, location=cfg.location, road_type=cfg.road_type.value,
            weather=cfg.weather.value, lighting=cfg.lighting.value, work_zone=cfg.work_zone,
            n_agents=len(cfg.agents), reference_agent=cfg.reference_agent.agent_id,
            duration_s=duration, source="simulated" if (d / "truth").is_dir() else "recorded",
            status="ok")]), clip_id=cid)
        # rows and checksums were taken while writing (TableWriter hashes the bytes as they
        # stream out), so the manifest needs no second read of the outputs
        root = staging.stage_root
        assert root is not None
        # lake-relative: a staged file's path below the run folder is its final one
        outputs = [(f[len(root) + 1:], *staging.written[f]) if f in staging.written
                   else (f[len(root) + 1:], pq_rows(staging, f), None)
                   for f in staging.list_files(f"{root}/raw", ".parquet")]
        # one journaled swap replaces everything the clip had in raw (a kill mid-way is
        # rolled forward by the next run's sweep)
        staging.replace_clip("raw", cid)
        staging.publish_stage()
    except BaseException:
        staging.discard_stage()
        raise
    elapsed = time.perf_counter() - t0
    n_bytes = sum(r.bytes_read for r in results.values())
    return StageReport(
        stage=STAGE, clip_id=cid,
        outputs=[OutputFile(path=f, rows=n, checksum=sha) for f, n, sha in outputs],
        metrics={
            "seconds": elapsed, "bytes_read": float(n_bytes),
            "mb_per_s": n_bytes / 1e6 / elapsed if elapsed > 0 else 0.0,
            "lidar_frames": float(sum(sum(r.lidar_frames.values()) for r in results.values())),
            "lidar_points": float(sum(r.n_points for r in results.values())),
            "camera_frames": float(sum(r.n_camera_frames for r in results.values())),
            "duration_s": duration, "agents": float(len(results)),
        },
        notes=notes,
    )


def pq_rows(lake: Lake, path: str) -> int:
    return lake.count_rows(path)


_OWNS = [("raw", t) for t in INGEST_TABLES]

INGEST = Stage(
    name=DECLARATION.name, config_model=IngestConfig, input="clip_dir",
    reads=(), owns=DECLARATION.owns, run=run_ingest, atomic=False,
    doc="bags -> raw tables (points with per-point time, images, poses, calibration)")
