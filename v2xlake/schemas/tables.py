"""Row models of every lake table; Arrow schemas come from ``v2xlake.schemas.arrow.arrow_schema``.

Time columns ending in ``_ns`` are int64 nanoseconds: GNSS epoch time in the raw zone, the
clip's relative axis (starting at 0.1 s) in the clean zone. Positions in the clean zone are
local ENU metres (docs/architecture.md, "Space"). ``clip_id`` / ``agent_id`` are hive
partition keys in the lake (``table/clip_id=.../agent_id=.../*.parquet``): the storage layer
strips them from the file and the catalog adds them back from the path.
"""

from __future__ import annotations

from typing import Annotated, Any

import pyarrow as pa
from pydantic import BaseModel, ConfigDict

from v2xlake.schemas.arrow import F32, F64, I32, I64, U8, U16, ArrowType

# re-exported: the stages import them from here
from v2xlake.schemas.stage import INGEST_TABLES as INGEST_TABLES
from v2xlake.schemas.stage import RAW_ONLY_TABLES as RAW_ONLY_TABLES

DictStr = Annotated[str, ArrowType(pa.dictionary(pa.int32(), pa.string()))]


class _Row(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


class ClipRow(_Row):
    clip_id: str
    location: str
    road_type: str
    weather: str
    lighting: str
    work_zone: bool
    n_agents: int
    reference_agent: str
    duration_s: float
    source: str  # "simulated" | "recorded"
    status: str  # "ok" | "quarantined"


class AgentRow(_Row):
    """``has_ins``: the agent has a pose track (raw ``ins`` or ``ego_poses``, clean
    ``ego_poses``); ``pose_source`` says from what (clip.yaml ``pose.kind``: ins, odometry,
    split, tf, fixed, or none), ``pose_frame`` in what (wgs84: georeferenced, map: a local
    map frame without geodetic reference, null: no pose)."""

    clip_id: str
    agent_id: str
    kind: str
    role: str
    has_ins: bool
    pose_source: str | None = None
    pose_frame: str | None = None
    # declared body box (clip.yaml ``dimensions``), centre in the ego frame
    length_m: F64 | None = None
    width_m: F64 | None = None
    height_m: F64 | None = None
    body_dx: F64 | None = None
    body_dy: F64 | None = None
    body_dz: F64 | None = None


class SensorRow(_Row):
    clip_id: str
    agent_id: str
    sensor: str
    modality: str
    topic: str
    msg_type: str
    n_messages: int
    n_duplicates: int = 0  # messages repeating an earlier stamp of the topic: dropped
    n_backwards: int = 0  # messages whose stamp is earlier than the one before (bag order)


class CalibratedSensorRow(_Row):
    clip_id: str
    agent_id: str
    sensor: str
    modality: str
    tx: float
    ty: float
    tz: float
    qw: float
    qx: float
    qy: float
    qz: float
    width: int | None = None
    height: int | None = None
    fx: float | None = None
    fy: float | None = None
    cx: float | None = None
    cy: float | None = None
    distortion_model: str | None = None
    distortion: list[float] | None = None
    source: str  # "clip.yaml" | "tf_static" | "camera_info"


class InsRow(_Row):
    """Raw zone only: the agent's georeferenced pose track, in WGS84 and local-level attitude
    (what an INS reports; ingest converts every georeferenced pose source to it, for the
    agent's ego frame). ``rtk_status`` is the source's solution status, -2 if it has none.
    An agent whose pose is in a local map without geodetic reference has raw ``ego_poses``
    (map coordinates, absolute time) instead."""

    clip_id: str
    agent_id: str
    t_ns: I64
    lat: F64
    lon: F64
    alt: F64
    roll: F64
    pitch: F64
    azimuth: F64
    ve: F64
    vn: F64
    vu: F64
    rtk_status: int


class EgoPoseRow(_Row):
    """Clean zone: ``T_world_ego`` in the clip's local ENU frame."""

    clip_id: str
    agent_id: str
    t_ns: I64
    x: F64
    y: F64
    z: F64
    qw: F64
    qx: F64
    qy: F64
    qz: F64
    vx: F64
    vy: F64
    vz: F64
    rtk_status: int


class ImuRow(_Row):
    clip_id: str
    agent_id: str
    sensor: str
    t_ns: I64
    wx: F64
    wy: F64
    wz: F64
    ax: F64
    ay: F64
    az: F64


class GnssRow(_Row):
    """Raw: lat/lon/alt. Clean: the same fix as local ENU metres in ``x``/``y``/``z``."""

    clip_id: str
    agent_id: str
    t_ns: I64
    lat: F64 | None = None
    lon: F64 | None = None
    alt: F64 | None = None
    x: F64 | None = None
    y: F64 | None = None
    z: F64 | None = None
    status: int
    sigma_h: F64 | None = None


class LidarFrameRow(_Row):
    clip_id: str
    agent_id: str
    sensor: str
    frame_idx: I32
    stamp_ns: I64
    t_start_ns: I64
    t_end_ns: I64
    n_points: I64
    n_nan: I64
    n_zero: I64 = 0  # no-return points at the sensor origin (zero range): dropped


class DeskewFrameRow(_Row):
    """Deskew's per-frame figures (its own table: ``lidar_frames`` belongs to ingest and
    anonymize; the catalog's ``lidar_frames`` view joins these columns in)."""

    clip_id: str
    agent_id: str
    sensor: str
    frame_idx: I32
    n_uncovered: I64
    deskew_ref_ns: I64 | None = None
    deskew_max_shift_m: F32 | None = None
    deskew_rms_shift_m: F32 | None = None


class LidarPointRow(_Row):
    """One point; in the lake one row group per frame, floats without dictionary encoding."""

    clip_id: str
    agent_id: str
    sensor: DictStr
    frame_idx: I32
    t_ns: I64
    x: F32
    y: F32
    z: F32
    intensity: F32
    ring: U16
    return_id: U8


class RadarFrameRow(_Row):
    """One radar scan (``sensor_msgs/PointCloud2`` from a 4D imaging radar)."""

    clip_id: str
    agent_id: str
    sensor: str
    frame_idx: I32
    stamp_ns: I64
    t_start_ns: I64
    t_end_ns: I64
    n_points: I64
    n_nan: I64


class RadarPointRow(_Row):
    """One radar detection: position in the radar frame, radial (Doppler) velocity along the
    line of sight (m/s, positive away from the sensor), radar cross-section (dBsm; NaN when
    the radar gives none), time (per point, or the scan's stamp)."""

    clip_id: str
    agent_id: str
    sensor: DictStr
    frame_idx: I32
    t_ns: I64
    x: F32
    y: F32
    z: F32
    velocity: F32
    rcs: F32


class CameraFrameRow(_Row):
    clip_id: str
    agent_id: str
    sensor: str
    frame_idx: I32
    stamp_ns: I64
    width: int
    height: int
    blob: str  # key of the PNG in the zone's blob store
    sha256: str
    anonymizer: str | None = None  # detector name and version that blurred this image
    n_blurred: int | None = None


class AnnotationRow(_Row):
    clip_id: str
    agent_id: str
    sensor: str
    frame_idx: I32
    t_ns: I64
    instance_id: str
    category: str
    cx: F64
    cy: F64
    cz: F64
    w: F64
    l: F64
    h: F64
    qw: F64
    qx: F64
    qy: F64
    qz: F64
    vx: F64 | None = None
    vy: F64 | None = None
    vz: F64 | None = None
    links: list[str]
    num_lidar_pts: int | None = None


class AnnotationWorldRow(AnnotationRow):
    """The same boxes in the clip's local ENU world frame (``T_world_ego(t0) T_ego_lidar``);
    velocity rotated alike. Written by the annotate stage for exports (nuScenes, OpenCOOD)."""


class InstanceRow(_Row):
    clip_id: str
    instance_id: str
    category: str
    n_annotations: int
    agents: list[str]
    first_t_ns: I64
    last_t_ns: I64
    links: list[str]


class RegistrationRow(_Row):
    """Eq. 1a initial and eq. 1b refined ``T_L1_L2`` per frame pair, with its quality."""

    clip_id: str
    agent_ref: str
    agent_other: str
    frame_idx: I32
    t_ns: I64
    init_tx: F64
    init_ty: F64
    init_tz: F64
    init_qw: F64
    init_qx: F64
    init_qy: F64
    init_qz: F64
    tx: F64
    ty: F64
    tz: F64
    qw: F64
    qx: F64
    qy: F64
    qz: F64
    fitness: F64
    inlier_rmse: F64
    correction_m: F64
    correction_deg: F64
    accepted: bool
    method: str
    reason: str
    # static-scene filtering (issue #13): voxel centroids GICP saw, and what was removed from
    # both scans as annotated moving boxes, other agents' bodies, or inconsistent with the
    # neighbouring scans of the same agent
    n_points_ref: I64 | None = None
    n_points_other: I64 | None = None
    removed_boxes: I64 | None = None
    removed_bodies: I64 | None = None
    removed_dynamic: I64 | None = None
    # the clip-level solve (issue #13): the frame's own GICP result is a measurement; the
    # final estimate (tx..qz) is the clip solution at this frame, with its 1-sigma
    gicp_tx: F64 | None = None
    gicp_ty: F64 | None = None
    gicp_tz: F64 | None = None
    gicp_qw: F64 | None = None
    gicp_qx: F64 | None = None
    gicp_qy: F64 | None = None
    gicp_qz: F64 | None = None
    information: list[float] | None = None  # 6x6 row-major, [rot rad, trans m], left, L1
    observability: F64 | None = None
    weight: F64 | None = None  # robust weight in the clip solve (0: not used)
    loo_chi2: F64 | None = None  # leave-one-out test statistic (chi^2, 6 dof)
    outlier: bool | None = None
    std_m: F64 | None = None  # final estimate, largest 1-sigma translation
    std_deg: F64 | None = None  # final estimate, largest 1-sigma rotation


class CalibrationRefinedRow(_Row):
    """A LiDAR extrinsic refined by the register stage's clip-level solve (issue #13), beside
    the published one; ``calibrated_sensors`` (ingest's) is never rewritten. The correction is
    applied only in the components the clip determined (``refined_components``); the others
    keep the published value. ``cov``: 6x6 row-major covariance of the correction
    ``[rot rad, trans m]`` in the LiDAR frame (``T_ego_lidar = published @ exp(correction)``)."""

    clip_id: str
    agent_id: str
    sensor: str
    tx: F64
    ty: F64
    tz: F64
    qw: F64
    qx: F64
    qy: F64
    qz: F64
    pub_tx: F64
    pub_ty: F64
    pub_tz: F64
    pub_qw: F64
    pub_qx: F64
    pub_qy: F64
    pub_qz: F64
    correction_m: F64
    correction_deg: F64
    cov: list[float]
    std_m: F64  # largest 1-sigma over the refined translation components
    std_deg: F64  # largest 1-sigma over the refined rotation components
    refined_components: str  # e.g. "rx ry rz tx ty": the determined ones
    usable: bool  # register's own threshold (register.calibration.max_std_m / _deg)
    n_frames: I64
    source: str  # "refined"
    method: str
    # why the published extrinsic is kept (or which parts of it): "not determined: tx ty",
    # "correction not significant", "fit inconsistent ..."; None when refined as a whole
    reason: str | None = None


class AlignmentRow(_Row):
    """Which camera frame a LiDAR frame (or one target in it) is aligned with (Sec. 5)."""

    clip_id: str
    agent_id: str
    lidar_frame_idx: I32
    camera: str
    method: str  # stamp | frame | target
    instance_id: str | None = None
    camera_frame_idx: I32
    camera_t_ns: I64
    points_t_ns: I64  # the point time the association was made on
    mean_iou: F64 | None = None
    center_offset_px: F64 | None = None


class QaCheckRow(_Row):
    clip_id: str
    agent_id: str | None = None
    sensor: str | None = None
    check: str
    passed: bool
    severity: str  # "error" quarantines the clip, "warning" does not
    value: F64 | None = None
    threshold: F64 | None = None
    detail: str


class AnonymizationAuditRow(_Row):
    """What was blurred, never the pixels themselves."""

    clip_id: str
    agent_id: str
    sensor: str
    frame_idx: I32
    detector: str
    kind: str  # face | plate
    x0: F32
    y0: F32
    x1: F32
    y1: F32
    score: F32


class ManifestRow(_Row):
    clip_id: str
    stage: str
    status: str  # done | failed | skipped
    code_version: str
    params_hash: str
    inputs_hash: str
    outputs: str  # JSON list of {path, rows, checksum}
    error: str | None = None


LAKE_TABLES: dict[str, type[_Row]] = {
    "clips": ClipRow,
    "agents": AgentRow,
    "sensors": SensorRow,
    "calibrated_sensors": CalibratedSensorRow,
    "ins": InsRow,
    "ego_poses": EgoPoseRow,
    "imu": ImuRow,
    "gnss": GnssRow,
    "lidar_frames": LidarFrameRow,
    "deskew_frames": DeskewFrameRow,
    "lidar_points": LidarPointRow,
    "radar_frames": RadarFrameRow,
    "radar_points": RadarPointRow,
    "camera_frames": CameraFrameRow,
    "annotations": AnnotationRow,
    "annotations_world": AnnotationWorldRow,
    "instances": InstanceRow,
    "registrations": RegistrationRow,
    "calibration_refined": CalibrationRefinedRow,
    "alignments": AlignmentRow,
    "qa_checks": QaCheckRow,
    "anonymization_audit": AnonymizationAuditRow,
    "manifests": ManifestRow,
}


# The tables of the lake's export formats (not a stage: ``v2xlake export``).
EXPORT_TABLES: dict[tuple[str, str], str] = {
    ("clean", f"nuscenes_{t}"): "export" for t in (
        "scene", "sample", "sample_data", "sample_annotation", "instance", "category",
        "attribute", "visibility", "sensor", "calibrated_sensor", "ego_pose", "log", "map")}


def table_owners() -> dict[tuple[str, str], str]:
    """The single writer of every (zone, table): storage refuses a write by any other stage.
    Each stage declares its own tables in its package (``schemas.registry``), so a new
    stage adds its tables without editing this module."""
    from v2xlake.schemas.registry import table_owners as declared

    return {**declared(), **EXPORT_TABLES}


def table_owner(zone: str, table: str) -> str | None:
    """The stage that owns ``zone.table`` (None: not a known table)."""
    return table_owners().get((zone, table))


def __getattr__(name: str) -> Any:
    """``TABLE_OWNERS``, built from the stages' declarations on first use (importing this
    module must not import the stage packages: they import it)."""
    if name == "TABLE_OWNERS":
        return table_owners()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
