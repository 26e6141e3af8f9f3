"""The ``clip.yaml`` input contract (docs/recordings.md).

A clip folder holds one bag per agent plus this file, which says what the bags cannot: the
conditions, which agent is the reference, and per sensor the topic, message type, field
mapping, calibration source and timing model; per agent where its pose comes from. Real
recordings are ingested by writing one of these files, never by changing code, so every
driver-specific quirk (time field name, unit, reference; an INS's angle conventions; the
datum of a localisation stack's map frame) must be expressible here. ``docs/recordings.md``
is the cookbook.

Every model forbids unknown keys: a misspelled key (``extrinsics:`` for ``extrinsic:``)
would otherwise be ignored and its sensor silently calibrated from somewhere else.
"""

from __future__ import annotations

import math
from enum import StrEnum
from pathlib import Path
from typing import Annotated, Any, Literal, Self

import yaml
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from v2xlake.schemas.calibration import CameraIntrinsics
from v2xlake.schemas.geometry import Transform

#: libyaml's loader when PyYAML was built with it: a clip.yaml is parsed by several stages
#: and by every no-op check, and the pure-Python loader takes milliseconds on a large one.
_SafeLoader: type[yaml.SafeLoader] = getattr(yaml, "CSafeLoader", yaml.SafeLoader)

#: Largest YAML text ``load_yaml`` parses (bytes or characters). A real clip.yaml is a few
#: KB (a thousand-sensor one well under 1 MB); a larger one is a hostile or broken delivery,
#: and parsing it would cost memory and time before anything could say so.
MAX_YAML_SIZE = 16 * 1024 * 1024

#: Deepest nesting of collections ``load_yaml`` accepts. A clip.yaml nests about ten levels
#: deep. libyaml's composer (via PyYAML's C extension) recurses in C, about 320 bytes of
#: stack per level: 100,000 levels overflow the stack and kill the process (segfault, no
#: Python exception). 256 levels need ~85 KB, safe in any thread stack CPython itself runs
#: in, and stay within the pure-Python loader's recursion limit too.
MAX_YAML_NESTING = 256

_OPEN_EVENTS = (yaml.SequenceStartEvent, yaml.MappingStartEvent)
_CLOSE_EVENTS = (yaml.SequenceEndEvent, yaml.MappingEndEvent)


def _nesting_bound(text: str | bytes) -> int:
    """An upper bound of the collection nesting of ``text``, at C speed: a flow collection
    needs an opening bracket, and a block collection nests at a column no smaller than its
    parent's (strictly greater every other level), so its depth is at most twice the
    longest line. Loose (brackets in strings count), but never below the real depth."""
    if isinstance(text, bytes):
        openers = text.count(b"[") + text.count(b"{")
    else:
        openers = text.count("[") + text.count("{")
    longest = max(map(len, text.splitlines()), default=0)
    return openers + 2 * (longest + 1) + 1


def _nesting(text: str | bytes, limit: int) -> int:
    """The real nesting depth of ``text`` from its event stream (libyaml's parser is a state
    machine with a heap stack: no recursion), stopping as soon as it passes ``limit``."""
    depth = deepest = 0
    for event in yaml.parse(text, Loader=_SafeLoader):
        if isinstance(event, _OPEN_EVENTS):
            depth += 1
            deepest = max(deepest, depth)
            if depth > limit:
                break
        elif isinstance(event, _CLOSE_EVENTS):
            depth -= 1
    return deepest


#: Most nodes that aliases may add to a YAML document when expanded (``*a`` repeats the
#: whole collection anchored as ``&a``). A clip.yaml has no use for more than a few; a
#: "billion laughs" text of nine lines expands to 9**9 values, which parse into shared
#: objects in microseconds but hang whatever walks them (validation errors, reprs, logs).
MAX_YAML_ALIAS_EXPANSION = 100_000

_MERGE_TAG = "tag:yaml.org,2002:merge"


def _expanded_size(root: yaml.Node) -> tuple[int, int]:
    """(distinct nodes, nodes once every alias is expanded) of a composed document, without
    expanding anything: each node's expanded size is computed once (memoised by identity,
    iteratively: no recursion on deep documents)."""
    size: dict[int, int] = {}
    distinct = 0
    todo: list[tuple[yaml.Node, bool]] = [(root, False)]
    while todo:
        node, done = todo.pop()
        key = id(node)
        if key in size:
            continue
        children: list[yaml.Node] = []
        if isinstance(node, yaml.SequenceNode):
            children = list(node.value)
        elif isinstance(node, yaml.MappingNode):
            children = [n for pair in node.value for n in pair]
        if not done:
            todo.append((node, True))
            todo.extend((c, False) for c in children if id(c) not in size)
            continue
        distinct += 1
        size[key] = 1 + sum(size.get(id(c), 1) for c in children)
    return distinct, size[id(root)]


class DuplicateKeyError(yaml.constructor.ConstructorError):
    """A mapping that names one key twice (YAML 1.2 forbids it; PyYAML keeps the last)."""


def _no_duplicate_keys(loader: Any, node: yaml.MappingNode) -> None:
    """Refuse a mapping whose keys repeat (merge keys ``<<`` excepted: overriding merged
    values is what they are for). A clip.yaml with ``rate_hz`` twice would silently take
    the second; which one the author meant cannot be known."""
    seen: dict[Any, yaml.Node] = {}
    for key_node, _ in node.value:
        if key_node.tag == _MERGE_TAG or not isinstance(key_node, yaml.ScalarNode):
            continue
        key = loader.construct_object(key_node, deep=False)
        try:
            first = seen.setdefault(key, key_node)
        except TypeError:  # an unhashable key: the constructor says so itself
            continue
        if first is not key_node:
            from v2xlake.schemas.errors import bounded

            raise DuplicateKeyError(
                "while constructing a mapping", node.start_mark,
                f"found duplicate key {bounded(repr(key), 200)} (first at line "
                f"{first.start_mark.line + 1})", key_node.start_mark)


_STRICT_LOADERS: dict[type, type] = {}


def _strict_loader() -> type:
    """``_SafeLoader`` (libyaml's when available) refusing duplicate keys (built per base
    class: tests swap ``_SafeLoader`` for the pure-Python one)."""
    base = _SafeLoader
    if base not in _STRICT_LOADERS:
        def construct_mapping(self: Any, node: yaml.MappingNode, deep: bool = False) -> Any:
            if isinstance(node, yaml.MappingNode):
                _no_duplicate_keys(self, node)
            return base.construct_mapping(self, node, deep=deep)

        _STRICT_LOADERS[base] = type(f"Strict{base.__name__}", (base,),
                                     {"construct_mapping": construct_mapping})
    return _STRICT_LOADERS[base]


def load_yaml(text: str | bytes) -> Any:
    """Parse YAML safely (no Python objects), with libyaml when available.

    A clip.yaml is untrusted input, so the parse is bounded: a text above ``MAX_YAML_SIZE``,
    nested deeper than ``MAX_YAML_NESTING``, whose aliases expand to more than
    ``MAX_YAML_ALIAS_EXPANSION`` extra nodes (an alias bomb), or with a key repeated in one
    mapping raises ``yaml.YAMLError`` (which every caller already turns into its own error)
    instead of exhausting memory, overflowing the C stack, hanging what walks the result or
    silently keeping the last of two values. The nesting is measured only when a cheap bound
    cannot rule it out."""
    if len(text) > MAX_YAML_SIZE:
        raise yaml.YAMLError(f"YAML text too large ({len(text):,} > {MAX_YAML_SIZE:,} bytes)")
    too_deep = f"YAML nesting too deep (more than {MAX_YAML_NESTING} levels)"
    if (_nesting_bound(text) > MAX_YAML_NESTING
            and _nesting(text, MAX_YAML_NESTING) > MAX_YAML_NESTING):
        raise yaml.YAMLError(too_deep)
    loader = _strict_loader()(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        has_alias = b"*" in text if isinstance(text, bytes) else "*" in text
        if has_alias:  # no alias: nothing to expand
            distinct, expanded = _expanded_size(node)
            if expanded - distinct > MAX_YAML_ALIAS_EXPANSION:
                raise yaml.YAMLError(
                    f"YAML aliases expand to {expanded:,} nodes from {distinct:,} (more than "
                    f"{MAX_YAML_ALIAS_EXPANSION:,} added): an alias bomb? refused")
        return loader.construct_document(node)
    except RecursionError as e:  # the pure-Python composer recurses (a caller deep already)
        raise yaml.YAMLError(too_deep) from e
    finally:
        loader.dispose()


#: Clip, agent and sensor ids: they name folders and files of the lake (``clip_id=<id>``,
#: ``quarantine/<id>``), so a letter or digit first and at most 128 characters (file names
#: stop at 255 bytes; a 300-character id was an OSError, not a refused clip).
MAX_ID_LENGTH = 128
ID_PATTERN = rf"^[A-Za-z0-9][A-Za-z0-9_\-]{{0,{MAX_ID_LENGTH - 1}}}$"

#: Highest sensor or pose-sample rate accepted, Hz. Above any real sensor (a fast IMU runs at
#: a few kHz); an absurd rate sizes buffers and sample grids (a fixed pose is sampled at it).
MAX_RATE_HZ = 100_000.0
#: Farthest a sensor may sit from its agent's ego frame, metres (``extrinsic`` and the
#: tf_static chain alike). Sensors are on the vehicle or the RSU mast; a kilometre is a
#: generous bound that still catches a unit mistake (mm for m) or a world pose given as an
#: extrinsic. World poses (a fixed RSU's ``local`` pose, a datum) are not bounded: they may
#: be UTM or other large local coordinates.
MAX_SENSOR_OFFSET_M = 1000.0
#: Bound of each coordinate of an agent's body-box centre in its ego frame, metres.
MAX_BODY_OFFSET_M = 50.0


class _Strict(BaseModel):
    """Frozen, and an unknown key is an error naming the key."""

    # No NaN or infinity anywhere in a clip.yaml: no field means "unknown" or "unbounded"
    # by them, and a NaN compares false with every bound, so it would pass range checks.
    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)


class Weather(StrEnum):
    CLEAR = "clear"
    OVERCAST = "overcast"
    RAIN = "rain"
    SNOW = "snow"
    FOG = "fog"


class Lighting(StrEnum):
    DAY = "day"
    DAWN = "dawn"
    DUSK = "dusk"
    DIRECT_SUN = "direct_sun"
    NIGHT = "night"


class RoadType(StrEnum):
    HIGHWAY = "highway"
    ARTERIAL = "arterial"
    COLLECTOR = "collector"
    LOCAL = "local"


class AgentKind(StrEnum):
    VEHICLE = "vehicle"
    ROADSIDE = "roadside"


class AgentRole(StrEnum):
    REFERENCE = "reference"
    COOPERATIVE = "cooperative"


class Modality(StrEnum):
    LIDAR = "lidar"
    CAMERA = "camera"
    INS = "ins"  # any pose message: vendor INS, Odometry, PoseStamped, /tf ...
    IMU = "imu"
    GNSS = "gnss"
    RADAR = "radar"


class TimeUnit(StrEnum):
    S = "s"
    MS = "ms"
    US = "us"
    NS = "ns"


class TimeReference(StrEnum):
    """What a per-point time field is measured from."""

    ABSOLUTE = "absolute"  # GNSS epoch time
    HEADER = "header"  # offset from the message header stamp (Ouster ``t``, Velodyne ``time``)


class PointTimeField(_Strict):
    field: str
    unit: TimeUnit
    reference: TimeReference


class LidarFields(_Strict):
    """Which PointCloud2 fields carry what. ``None`` means the sensor does not provide it.

    Radar point clouds use the same mapping plus ``velocity`` (radial, m/s) and ``rcs``;
    their ``time`` may be omitted (one time per scan: the header stamp)."""

    x: str = "x"
    y: str = "y"
    z: str = "z"
    intensity: str | None = "intensity"
    ring: str | None = "ring"
    return_id: str | None = None
    time: PointTimeField | None = None
    velocity: str | None = Field(default=None, description="radar: radial velocity field (m/s)")
    rcs: str | None = Field(default=None, description="radar: radar cross-section field (dBsm)")


class SyncMode(StrEnum):
    PPS = "pps"  # triggered from the GNSS PPS edge: stamps on a grid (sec + phase + k/rate)
    FREE = "free"  # free-running clock: checked for gaps and jitter only


class SyncModel(_Strict):
    """How a sensor's stamps are timed; QA derives its grid and tolerance from this."""

    mode: SyncMode = SyncMode.PPS
    phase_ms: float = Field(0.0, description="PPS-locked: offset of the first stamp after "
                            "each PPS edge (e.g. a camera triggered 5 ms after the edge)")
    tolerance_ms: float | None = Field(
        default=None, gt=0, description="largest allowed distance to the grid (PPS) or "
        "deviation from the period (free-running); default: QA's per-modality tolerance")


class SensorConfig(_Strict):
    """One sensor of one agent.

    Calibration comes from ``extrinsic`` / ``intrinsics`` when given, else from the agent's
    ``tf_static_topic`` (looked up by ``frame_id``) and ``camera_info_topic``.
    """

    name: str = Field(pattern=ID_PATTERN, description="channel name, e.g. LIDAR_TOP, CAM_FRONT")
    modality: Modality
    topic: str = Field(pattern=r"^/")
    msg_type: str = Field(description="ROS type name, e.g. sensor_msgs/msg/PointCloud2")
    frame_id: str | None = None
    fields: LidarFields | None = None
    extrinsic: Transform | None = Field(default=None, description="T_ego_sensor")
    intrinsics: CameraIntrinsics | None = None
    camera_info_topic: str | None = None
    rate_hz: float | None = Field(default=None, gt=0, le=MAX_RATE_HZ,
                                  description="nominal rate; QA estimates "
                                  "it from the stamps (and says so) when not given")
    sync: SyncModel | None = Field(default=None, description="PPS-locked or free-running; "
                                   "default: PPS-locked when the agent has a pose source "
                                   "(its GNSS supplies the PPS), else free-running")
    scan_fov_deg: float = Field(360.0, gt=0, le=360, description="LiDAR: azimuth range one "
                                "scan covers; a FOV-limited scan spans fov/360 of the period")

    @field_validator("extrinsic")
    @classmethod
    def _near_the_agent(cls, v: Transform | None) -> Transform | None:
        if v is not None and (d := math.hypot(*v.translation)) > MAX_SENSOR_OFFSET_M:
            raise ValueError(f"extrinsic translation is {d:.6g} m from the ego frame; at most "
                             f"{MAX_SENSOR_OFFSET_M:g} m (metres, not millimetres? a sensor "
                             "sits on its agent)")
        return v

    @model_validator(mode="after")
    def _lidar_needs_fields(self) -> Self:
        if self.modality is Modality.LIDAR and (self.fields is None or self.fields.time is None):
            raise ValueError(
                f"lidar sensor {self.name!r} needs a 'fields' mapping with a time field"
            )
        if self.modality is Modality.RADAR and (self.fields is None
                                                or self.fields.velocity is None):
            raise ValueError(f"radar sensor {self.name!r} needs a 'fields' mapping with its "
                             "radial velocity field (velocity: ...)")
        return self


# --------------------------------------------------------------------------- pose sources
class AngleUnit(StrEnum):
    DEG = "deg"
    RAD = "rad"


class AttitudeConvention(StrEnum):
    """What an orientation quaternion rotates: ``enu``: ``q_enu_flu`` (ROS REP-103,
    ``sensor_msgs/Imu``, Xsens default: body x forward, y left, z up, in east-north-up);
    ``ned``: ``q_ned_frd`` (aerospace: body x forward, y right, z down, in north-east-down)."""

    NED = "ned"
    ENU = "enu"


class Heading(StrEnum):
    NORTH_CW = "north_cw"  # azimuth: clockwise from true north (NovAtel, OxTS, Applanix, SBG)
    EAST_CCW = "east_ccw"  # yaw: counter-clockwise from east (REP-103)


class PitchSign(StrEnum):
    NOSE_UP = "nose_up"  # aerospace / most INS vendors
    NOSE_DOWN = "nose_down"  # REP-103 Euler angles (rotation about the left-pointing y axis)


class RollSign(StrEnum):
    RIGHT_DOWN = "right_down"  # aerospace and REP-103 alike
    LEFT_DOWN = "left_down"


class _Euler(_Strict):
    """How Euler attitude angles are meant; always Tait-Bryan heading, then pitch, then roll
    of the body relative to the local level. The defaults are the aerospace convention most
    INS vendors use; REP-103 Euler angles are ``heading: east_ccw, pitch: nose_down``."""

    angle_unit: AngleUnit = AngleUnit.RAD
    heading: Heading = Heading.NORTH_CW
    pitch: PitchSign = PitchSign.NOSE_UP
    roll: RollSign = RollSign.RIGHT_DOWN


class VelocityFrame(StrEnum):
    ENU = "enu"  # east, north, up at the vehicle
    NED = "ned"  # north, east, down at the vehicle
    BODY = "body"  # in the pose's body frame (nav_msgs/Odometry twist: child_frame_id)


class DatumKind(StrEnum):
    UTM = "utm"  # map x, y = UTM easting, northing (minus ``offset``); z = ellipsoidal height
    GEODETIC = "geodetic"  # map = the ENU tangent frame at ``origin``
    LOCAL = "local"  # already a local ENU frame; no geodetic reference (no lat/lon anywhere)


class GeodeticPoint(_Strict):
    latitude: float = Field(ge=-90, le=90, description="degrees, WGS84")
    longitude: float = Field(ge=-180, le=360, description="degrees, WGS84")
    height: float = Field(0.0, description="metres above the WGS84 ellipsoid")


class Datum(_Strict):
    """What a map frame's coordinates mean: ``datum = map + offset``."""

    kind: DatumKind
    utm_zone: int | None = Field(default=None, ge=1, le=60)
    hemisphere: Literal["north", "south"] = "north"
    origin: GeodeticPoint | None = None
    offset: tuple[float, float, float] = Field(
        (0.0, 0.0, 0.0), description="added to map coordinates (e.g. the UTM easting, "
        "northing, height of the map origin of an Autoware-style map)")

    @model_validator(mode="after")
    def _complete(self) -> Self:
        if self.kind is DatumKind.UTM and self.utm_zone is None:
            raise ValueError("datum kind 'utm' needs utm_zone (1..60)")
        if self.kind is DatumKind.GEODETIC and self.origin is None:
            raise ValueError("datum kind 'geodetic' needs origin: {latitude, longitude, height}")
        if self.kind is not DatumKind.UTM and self.utm_zone is not None:
            raise ValueError(f"utm_zone given for datum kind {self.kind.value!r}")
        if self.kind is not DatumKind.GEODETIC and self.origin is not None:
            raise ValueError(f"origin given for datum kind {self.kind.value!r}")
        return self

    @property
    def geodetic(self) -> bool:
        return self.kind is not DatumKind.LOCAL


class Vec3Paths(_Strict):
    """Dotted field paths of a 3-vector in a message (``velocity.x`` or ``north_velocity``)."""

    x: str
    y: str
    z: str


class GeoFields(_Strict):
    latitude: str = "latitude"
    longitude: str = "longitude"
    height: str = "altitude"
    undulation: str | None = Field(default=None, description="geoid undulation field added "
                                   "to height when height is above mean sea level (SBG)")


class EulerFields(_Strict):
    roll: str = "roll"
    pitch: str = "pitch"
    heading: str = Field("azimuth", description="heading (ned) or yaw (enu) field")


class InsFields(_Strict):
    """Field paths of a vendor INS solution message (dotted: ``lla.latitude``)."""

    latitude: str = "latitude"
    longitude: str = "longitude"
    height: str = "altitude"
    undulation: str | None = Field(default=None, description="geoid undulation field added "
                                   "to height when height is above mean sea level")
    roll: str = "roll"
    pitch: str = "pitch"
    heading: str = "azimuth"
    velocity: Vec3Paths | None = Field(default=None, description="components in "
                                       "velocity_frame order (ENU: e,n,u; NED: n,e,d; body)")
    status: str | None = Field(default=None, description="solution status (RTK fixed...)")


class _PoseBase(_Strict):
    body_frame: str | None = Field(
        default=None, description="the frame the pose is of, when it is not the agent's "
        "ego_frame (an INS box, an Imu's frame): T_body_ego comes from tf_static or the pose "
        "sensor's extrinsic")


class InsPose(_PoseBase, _Euler):
    """A vendor INS message: geodetic position, Euler attitude, velocity in one message."""

    kind: Literal["ins"] = "ins"
    sensor: str = Field(description="name of the agent's ins-modality sensor carrying it")
    fields: InsFields | None = Field(default=None, description="None: found by the names "
                                     "vendors use (latitude/lat, azimuth/heading/yaw, ...)")
    latlon_unit: AngleUnit = AngleUnit.DEG
    velocity_frame: VelocityFrame = VelocityFrame.ENU


class OdometryPose(_PoseBase):
    """``nav_msgs/Odometry``, ``geometry_msgs/PoseStamped`` or ``PoseWithCovarianceStamped``
    in a map frame whose meaning ``datum`` gives. The pose is of ``child_frame_id``
    (Odometry) unless ``body_frame`` says otherwise, else of the ego frame."""

    kind: Literal["odometry"] = "odometry"
    sensor: str
    datum: Datum
    map_frame: str | None = Field(default=None, description="expected header.frame_id; "
                                  "another frame is an error")


class SplitPose(_PoseBase, _Euler):
    """Position from one topic, attitude (and optionally velocity) from others, sampled at
    the attitude (or position) topic's stamps with the other interpolated (linear / SLERP,
    never across a gap longer than ``max_gap_ms``, never extrapolated)."""

    kind: Literal["split"] = "split"
    position: str = Field(description="sensor: NavSatFix, or a message with position_fields")
    attitude: str = Field(description="sensor: Imu (orientation), or attitude_fields")
    velocity: str | None = Field(default=None, description="sensor: TwistStamped, "
                                 "Vector3Stamped, or velocity_fields; None: differentiated")
    position_fields: GeoFields | None = None
    attitude_fields: EulerFields | None = Field(default=None, description="Euler angles "
                                                "(angle_unit, heading, pitch, roll say how); "
                                                "None: an orientation quaternion")
    velocity_fields: Vec3Paths | None = None
    quaternion_frame: AttitudeConvention = AttitudeConvention.ENU
    latlon_unit: AngleUnit = AngleUnit.DEG
    velocity_frame: VelocityFrame = VelocityFrame.ENU
    position_frame: str | None = Field(default=None, description="frame whose position the "
                                       "position topic gives (the GNSS antenna): lever arm "
                                       "from tf_static; default: the message's frame_id")
    sample_at: Literal["attitude", "position"] = "attitude"
    max_gap_ms: float = Field(250.0, gt=0)


class TfPose(_PoseBase):
    """Dynamic ``/tf`` (``tf2_msgs/TFMessage``): ``parent_frame -> child_frame`` through any
    chain of dynamic and static transforms."""

    kind: Literal["tf"] = "tf"
    sensor: str
    parent_frame: str = "map"
    child_frame: str | None = Field(default=None, description="default: the agent's ego_frame")
    datum: Datum


class FixedAttitude(_Strict):
    roll: float = 0.0
    pitch: float = 0.0
    heading: float = 0.0


class FixedPose(_Euler):
    """A surveyed pose (a roadside unit): geodetic with attitude angles (degrees by default;
    ``heading``, ``pitch``, ``roll`` conventions as for an INS), or local."""

    kind: Literal["fixed"] = "fixed"
    geodetic: GeodeticPoint | None = None
    attitude: FixedAttitude = FixedAttitude()
    angle_unit: AngleUnit = AngleUnit.DEG
    rate_hz: float = Field(50.0, gt=0, le=MAX_RATE_HZ,
                           description="samples of the constant pose per second "
                           "over the recording (deskew and QA bound the gap between poses)")
    local: Transform | None = Field(default=None, description="T_map_ego in a local map "
                                    "shared with the other agents (datum: local)")

    @model_validator(mode="after")
    def _one(self) -> Self:
        if (self.geodetic is None) == (self.local is None):
            raise ValueError("a fixed pose is either 'geodetic' (with roll/pitch/heading) or "
                             "'local' (a transform), exactly one")
        return self


class NoPose(_Strict):
    """No pose at all: ingest, QA and anonymize run; pose-dependent stages do not apply."""

    kind: Literal["none"] = "none"


PoseConfig = Annotated[InsPose | OdometryPose | SplitPose | TfPose | FixedPose | NoPose,
                       Field(discriminator="kind")]


_BodyOffset = Annotated[float, Field(ge=-MAX_BODY_OFFSET_M, le=MAX_BODY_OFFSET_M)]


class AgentDimensions(_Strict):
    """The agent's body as a box (ground to roof, nuScenes-style), for removing it from the
    other agents' scans before registration: size and the box centre in the ego frame."""

    length_m: float = Field(gt=0, le=30)
    width_m: float = Field(gt=0, le=5)
    height_m: float = Field(gt=0, le=10)
    center_in_ego: tuple[_BodyOffset, _BodyOffset, _BodyOffset] = Field(
        default=(0.0, 0.0, 0.0), description="box centre in the ego (INS) frame, metres")


class AgentConfig(_Strict):
    agent_id: str = Field(pattern=ID_PATTERN)
    kind: AgentKind
    role: AgentRole
    bag: str = Field(description="bag path relative to the clip folder")
    ego_frame: str = Field(default="base_link", description="the INS/IMU frame in tf_static")
    tf_static_topic: str | None = "/tf_static"
    sensors: list[SensorConfig] = Field(min_length=1)
    pose: PoseConfig | None = Field(default=None, description="where the agent's pose comes "
                                    "from; default: its ins-modality sensor, else none")
    dimensions: AgentDimensions | None = Field(
        default=None, description="body box; registration removes it from the others' scans")

    @model_validator(mode="after")
    def _unique_sensors(self) -> Self:
        names = [s.name for s in self.sensors]
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise ValueError(f"agent {self.agent_id!r}: duplicate sensor names {sorted(dup)}")
        topics = [s.topic for s in self.sensors]
        dup = {t for t in topics if topics.count(t) > 1}
        if dup:
            raise ValueError(f"agent {self.agent_id!r}: several sensors on topic(s) "
                             f"{sorted(dup)}")
        for name in self.pose_sensor_names():
            if name not in names:
                raise ValueError(f"agent {self.agent_id!r}: pose names sensor {name!r}, which "
                                 f"is not in its sensors {names}")
        return self

    def pose_sensor_names(self) -> list[str]:
        p = self.effective_pose
        if isinstance(p, InsPose | OdometryPose | TfPose):
            return [p.sensor]
        if isinstance(p, SplitPose):
            return [n for n in (p.position, p.attitude, p.velocity) if n]
        return []

    @property
    def effective_pose(self) -> InsPose | OdometryPose | SplitPose | TfPose | FixedPose | NoPose:
        """The ``pose`` block, or what an agent without one means: its ins-modality sensor
        read as a vendor INS with fields found by name, else no pose."""
        if self.pose is not None:
            return self.pose
        ins = self.sensors_of(Modality.INS)
        return InsPose(sensor=ins[0].name) if ins else NoPose()

    def sensor(self, name: str) -> SensorConfig:
        for s in self.sensors:
            if s.name == name:
                return s
        raise KeyError(f"agent {self.agent_id!r} has no sensor {name!r}")

    def sensors_of(self, modality: Modality) -> list[SensorConfig]:
        return [s for s in self.sensors if s.modality is modality]


class ClipConfig(_Strict):
    """The whole ``clip.yaml``."""

    clip_id: str = Field(pattern=ID_PATTERN)
    location: str
    road_type: RoadType
    weather: Weather
    lighting: Lighting
    work_zone: bool = False
    agents: list[AgentConfig] = Field(min_length=1)
    message_definitions: list[str] = Field(
        default_factory=list,
        description=".msg files (relative to the clip folder) for custom types, e.g. a vendor INS",
    )
    annotations: str | None = Field(default=None, description="annotation file, relative path")
    params: dict[str, dict[str, Any]] = Field(
        default_factory=dict,
        description="pipeline parameters that belong to this recording, one section per stage "
                    "(e.g. qa tolerances of its rig); they override the run's parameters")

    @model_validator(mode="after")
    def _one_reference(self) -> Self:
        refs = [a.agent_id for a in self.agents if a.role is AgentRole.REFERENCE]
        if len(refs) != 1:
            raise ValueError(f"exactly one agent must have role 'reference', got {refs}")
        ids = [a.agent_id for a in self.agents]
        if len(set(ids)) != len(ids):
            raise ValueError(f"agent ids must be unique, got {ids}")
        return self

    @property
    def reference_agent(self) -> AgentConfig:
        return next(a for a in self.agents if a.role is AgentRole.REFERENCE)

    def agent(self, agent_id: str) -> AgentConfig:
        for a in self.agents:
            if a.agent_id == agent_id:
                return a
        raise KeyError(f"clip {self.clip_id!r} has no agent {agent_id!r}")

    @classmethod
    def load(cls, clip_dir: str | Path) -> ClipConfig:
        return cls.model_validate(load_yaml((Path(clip_dir) / "clip.yaml").read_text()))

    def dump(self, clip_dir: str | Path) -> Path:
        path = Path(clip_dir) / "clip.yaml"
        data = self.model_dump(mode="json", exclude_none=True)
        path.write_text(yaml.safe_dump(data, sort_keys=False))
        return path
