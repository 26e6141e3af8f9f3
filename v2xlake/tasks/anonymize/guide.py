"""Where faces and plates can be: 3D object boxes projected into each image at its own time.

Why: a face detector shown a whole 1080p frame has to find a 16 px face among two million
pixels, and can only do so by upscaling everything (the x2 fine pass cost ~20x the pixels of
one native pass at 4K). The recording already knows where every vehicle and person is (the
annotations, or LiDAR clusters): a plate can only be on the front or rear face of a vehicle,
near the ground; a face only on a person's head or behind a vehicle's windows. Projecting
those parts of the 3D boxes into the image at the image's own time gives a few small regions
and, from the depth, the size a plate or face there must have, so each region is searched at
the scale that makes its object as big as the detector likes it (small and distant ones
upsampled) and the size seen can be checked against the size expected.

Pure functions on arrays; the stage reads the tables (``guided.py``). Box convention as in
``tasks.geometry``: size (w, l, h), the box x-axis is its length / heading, z up.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from v2xlake.schemas.calibration import CameraIntrinsics
from v2xlake.tasks.anonymize.params import FromParams, param
from v2xlake.tasks.geometry import apply, invert, quat_to_matrix, transform_boxes
from v2xlake.tasks.projection import project_boxes_2d, project_points

VEHICLES = frozenset({"Car", "Van", "Truck", "Trailer", "Bus", "Others"})
PEOPLE = frozenset({"Pedestrian", "Scooter", "Bicycle", "Motorcycle"})  # a rider's head on top


def _ms_to_ns(ms: float) -> int:
    return int(ms * 1e6)


@dataclass(frozen=True)
class GuideConfig(FromParams):
    """The parts of a box that can hold a plate or a face, and how regions are grown; the
    fields made with ``param`` are user parameters (params.py: ``GuideConfig.of``)."""

    plate_width_m: float = 0.52  # EU plate; US 0.305: the size prior allows for it
    face_height_m: float = 0.23
    plate_z_m: tuple[float, float] = (0.15, 1.4)  # plate height above the box bottom
    # a LiDAR cluster's bottom is the ground estimated under it (a low percentile of the
    # returns of its 2 m cells: a few cm to 0.2 m off), not a labelled one: its plate slab
    # starts this far above it (a low plate on the simulated clip was cut by the face's
    # lower edge 0.15 m up, 3 px in the image, and missed)
    cluster_plate_z0_m: float = 0.0
    plate_depth_m: float = 0.4  # slab thickness at a vehicle face (bumper curvature)
    windows: bool = param("regions.windows")  # search faces behind vehicle windows
    window_z_m: float = 0.9  # faces behind windows: above this height over the box bottom
    window_max_h_m: float = 2.5  # taller vehicles (trucks, buses): the front cab only
    window_cab_m: float = 2.5
    head_m: float = 0.5  # a person's head: the top of the box, this tall
    head_pad_m: float = 0.15  # the head may stick out of a tight box (box edges, arms)
    # projected regions grown by this share of their size, plus ``margin_px`` (calibration,
    # time stamp and box errors); a box is used this long before / after its own time
    margin_frac: float = param("regions.margin_frac")
    margin_px: float = param("regions.margin_px")
    max_age_ns: int = param("regions.box_max_age_ms", _ms_to_ns)
    near_m: float = 0.5
    # parts whose object would be smaller than this (px: face height, plate width) are not
    # searched: a 0.23 m face under 8 px or a 0.52 m plate under 12 px identifies no one
    min_face_px: float = 8.0
    min_plate_px: float = 12.0
    face_margin_m: float = 0.3  # a rectified vehicle face is this much wider on each side
    max_oblique_deg: float = 80.0  # a vehicle face seen more edge-on than this is not rectified
    # LiDAR clusters taller than this (m; a car or a van is lower, ``window_max_h_m``)
    # carry plates only on faces at least ``cluster_tall_face_min_m`` wide (0: every face)
    cluster_tall_m: float = 2.5
    cluster_tall_face_min_m: float = param("clusters.tall_face_min_m")
    # the far band (``band_region``; LiDAR clusters only): the image rows where plates of
    # vehicles from ``band_from_m`` out to the range where a plate is still
    # ``band_min_plate_px`` wide can be, searched whole (no object there to guide to: a
    # sparse LiDAR puts 0-3 returns on a car that far); 0: off
    band_from_m: float = param("clusters.band_from_m")
    band_min_plate_px: float = param("regions.plate_text_min_px")
    # the road's height there is known to this much (slope, pitch, the ground estimate)
    band_ground_margin_m: float = 0.5
    # LiDAR clusters: person boxes of the scans this close in time guide an image too, not
    # only the nearest scan's (``ClipGuide._at``); 0: the nearest scan only
    person_hold_ns: int = param("clusters.person_hold_ms", _ms_to_ns)
    # ... only persons farther than this from the LiDAR that saw them (nearer, a walker gets
    # returns in every sweep: holding it adds regions, not faces)
    person_hold_from_m: float = param("clusters.dense_range_m")
    # ... and only where the nearest scan has no person within this (m): the same walker,
    # seen again (it moves 0.2 m in 150 ms; two people side by side are ~0.6 m apart)
    person_hold_gap_m: float = 1.0


@dataclass(frozen=True)
class Region:
    """Image region (x0, y0, x1, y1 px) where a ``kind`` object is expected to be
    ``expected_px`` large (plate width or face height), from box ``instance``.

    A vehicle face also has ``quad``: its corners in the image (top-left, top-right,
    bottom-right, bottom-left as seen from outside the vehicle) and ``size_m`` (width,
    height in metres): the face can then be looked at head-on (a homography), where a plate
    seen obliquely by a side camera is an upright rectangle of known metric size."""

    kind: str
    box: tuple[float, float, float, float]
    expected_px: float
    instance: str = ""
    quad: tuple[tuple[float, float], ...] | None = None
    size_m: tuple[float, float] | None = None
    part: str = ""  # front | rear | window | head
    # the part's centre projected into the image (not clipped: may lie outside the frame);
    # with ``expected_px`` (inversely proportional to depth) it moves and scales a box found
    # in this region to where the same part is in a neighbouring frame (``carry.py``)
    anchor: tuple[float, float] | None = None
    # a region holding objects at several depths (the far band): the largest object size
    # expected in it (``expected_px`` the smallest); 0: ``expected_px`` alone
    expected_max_px: float = 0.0


@dataclass(frozen=True, eq=False)
class WorldBoxes:
    """Object boxes in the clip world at their own times (one row per box and time)."""

    t_ns: np.ndarray  # (M,) int64
    center: np.ndarray  # (M, 3)
    size: np.ndarray  # (M, 3) w, l, h
    quat: np.ndarray  # (M, 4) w, x, y, z
    velocity: np.ndarray  # (M, 3) world, NaN -> 0
    category: np.ndarray  # (M,) str
    instance: np.ndarray  # (M,) str

    def __len__(self) -> int:
        return len(self.t_ns)

    @staticmethod
    def empty() -> WorldBoxes:
        z = np.zeros((0, 3))
        return WorldBoxes(np.zeros(0, np.int64), z, z, np.zeros((0, 4)), z,
                          np.zeros(0, str), np.zeros(0, str))

    @staticmethod
    def concat(parts: list[WorldBoxes]) -> WorldBoxes:
        parts = [p for p in parts if len(p)]
        if not parts:
            return WorldBoxes.empty()
        return WorldBoxes(*(np.concatenate([getattr(p, f) for p in parts]) for f in
                            ("t_ns", "center", "size", "quat", "velocity", "category",
                             "instance")))

    def take(self, rows: np.ndarray) -> WorldBoxes:
        """The rows ``rows`` (a boolean mask or indices) of every field."""
        return WorldBoxes(self.t_ns[rows], self.center[rows], self.size[rows],
                          self.quat[rows], self.velocity[rows], self.category[rows],
                          self.instance[rows])

    def at(self, t_ns: int, max_age_ns: int) -> WorldBoxes:
        """Each instance once, from its box nearest in time to ``t_ns`` (within
        ``max_age_ns``), moved by its velocity to ``t_ns``."""
        if not len(self):
            return self
        dt = np.abs(self.t_ns - int(t_ns))
        order = np.lexsort((dt, self.instance))
        inst = self.instance[order]
        first = np.concatenate([[True], inst[1:] != inst[:-1]])
        sel = order[first]
        sel = sel[dt[sel] <= max_age_ns]
        step = (int(t_ns) - self.t_ns[sel]).astype(np.float64)[:, None] * 1e-9
        vel = np.nan_to_num(self.velocity[sel])
        return WorldBoxes(np.full(len(sel), int(t_ns), np.int64),
                          self.center[sel] + vel * step, self.size[sel], self.quat[sel],
                          vel, self.category[sel], self.instance[sel])


def _part(boxes: WorldBoxes, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centres and sizes (w, l, h) of the axis-aligned sub-boxes [lo, hi] given in each box's
    own frame (x length, y width, z up, origin at the centre), placed in the world."""
    mid = (lo + hi) / 2.0
    R = quat_to_matrix(boxes.quat)
    centre = boxes.center + np.einsum("mij,mj->mi", R, mid)
    ext = hi - lo
    return centre, np.stack([ext[:, 1], ext[:, 0], ext[:, 2]], 1)


Part = tuple[str, str, int, np.ndarray, np.ndarray, np.ndarray]


def part_boxes(boxes: WorldBoxes, cfg: GuideConfig, clusters: bool = False) -> list[Part]:
    """(kind, part, box index, centre, size, outward normal or zeros) of every plate / face
    part of every box. ``clusters``: the boxes are LiDAR clusters, and one taller than
    ``cluster_tall_m`` gets plate faces only where it is ``cluster_tall_face_min_m`` wide
    (its windows as any vehicle's). Why: vehicles that tall (trucks, buses, tall vans) are
    2-2.6 m wide, so a tall cluster's narrow face is the end of a facade piece, a tree, a
    pole or a sign, or the side view of a short cluster also returned end-on (whose wide
    face is then searched); on the simulated LiDAR-only 1080p clip (seed 0, 0.3 s) such
    faces were 123 of 845 plate regions, none holding a plate."""
    out: list[Part] = []
    R_all = quat_to_matrix(boxes.quat) if len(boxes) else np.zeros((0, 3, 3))
    zero = np.zeros(3)
    w, ln, h = boxes.size[:, 0], boxes.size[:, 1], boxes.size[:, 2]
    veh = np.isin(boxes.category, list(VEHICLES))
    ppl = np.isin(boxes.category, list(PEOPLE))
    plated = veh
    if clusters and cfg.cluster_tall_face_min_m > 0:
        plated = veh & ~((h > cfg.cluster_tall_m) & (w < cfg.cluster_tall_face_min_m))
    bottom = -h / 2
    d = cfg.plate_depth_m
    ztop = np.minimum(bottom + cfg.plate_z_m[1], h / 2)
    for part, sign, x0, x1 in (("front", 1.0, ln / 2 - d, ln / 2 + 0.1),
                               ("rear", -1.0, -ln / 2 - 0.1, -ln / 2 + d)):
        lo = np.stack([x0, -w / 2, bottom + cfg.plate_z_m[0]], 1)
        hi = np.stack([x1, w / 2, ztop], 1)
        c, s = _part(boxes, lo, hi)
        out += [("plate", part, int(i), c[i], s[i], sign * R_all[i][:, 0])
                for i in np.flatnonzero(plated)]
    if cfg.windows:
        tall = h > cfg.window_max_h_m
        back = np.where(tall, np.maximum(ln / 2 - cfg.window_cab_m, -ln / 2), -ln / 2)
        win_lo = np.stack([back, -w / 2, np.minimum(bottom + cfg.window_z_m, h / 2 - 0.2)], 1)
        win_hi = np.stack([ln / 2, w / 2, np.where(tall, bottom + cfg.window_z_m + 1.6,
                                                   h / 2)], 1)
        c, s = _part(boxes, win_lo, win_hi)
        out += [("face", "window", int(i), c[i], s[i], zero) for i in np.flatnonzero(veh)]
    r = np.maximum(w, ln) / 2 + cfg.head_pad_m
    head_lo = np.stack([-r, -r, h / 2 - cfg.head_m], 1)
    head_hi = np.stack([r, r, h / 2 + cfg.head_pad_m], 1)
    c, s = _part(boxes, head_lo, head_hi)
    out += [("face", "head", int(i), c[i], s[i], zero) for i in np.flatnonzero(ppl)]
    return out


def project_regions(boxes: WorldBoxes, T_cam_world: np.ndarray, intr: CameraIntrinsics,
                    cfg: GuideConfig, clusters: bool = False) -> list[Region]:
    """Image regions of every plate / face part visible in the camera (grown by the margins),
    with the object size expected there from the part's depth (``clusters``: the boxes are
    LiDAR clusters, ``part_boxes``)."""
    parts = part_boxes(boxes, cfg, clusters)
    if not parts:
        return []
    cam = invert(T_cam_world)[:3, 3]
    # a plate face turned away from the camera cannot show its plate
    parts = [p for p in parts if float(np.dot(p[5], cam - p[3])) >= 0.0]
    if not parts:
        return []
    centre = np.array([p[3] for p in parts])
    size = np.array([p[4] for p in parts])
    quat = boxes.quat[[p[2] for p in parts]]
    b2d = project_boxes_2d(centre, size, quat, T_cam_world, intr, near=cfg.near_m)
    cam_c = apply(T_cam_world, centre)
    depth = cam_c[:, 2]
    anchors, _ = project_points(np.where(depth[:, None] >= cfg.near_m, cam_c, np.nan), intr,
                                near=cfg.near_m)
    f = 0.5 * (intr.fx + intr.fy)
    out = []
    for (kind, name, i, c, sz, n), b, z, uv in zip(parts, b2d, depth, anchors, strict=True):
        if not np.isfinite(b).all() or z < cfg.near_m:
            continue
        mw, mh = cfg.margin_frac * (b[2] - b[0]) + cfg.margin_px, cfg.margin_frac * (
            b[3] - b[1]) + cfg.margin_px
        grown = (max(0.0, b[0] - mw), max(0.0, b[1] - mh),
                 min(float(intr.width), b[2] + mw), min(float(intr.height), b[3] + mh))
        size_m = cfg.plate_width_m if kind == "plate" else cfg.face_height_m
        if f * size_m / z < (cfg.min_plate_px if kind == "plate" else cfg.min_face_px):
            continue
        quad: tuple[tuple[float, float], ...] | None = None
        metric: tuple[float, float] | None = None
        if kind == "plate":
            view = cam - c
            cos = float(np.dot(n, view) / max(np.linalg.norm(view), 1e-9))
            if cos >= np.cos(np.radians(cfg.max_oblique_deg)):
                quad, metric = _face_quad(c, sz, boxes.quat[i], name, T_cam_world, intr, cfg)
        anchor = (float(uv[0]), float(uv[1])) if np.isfinite(uv).all() else None
        out.append(Region(kind, grown, float(f * size_m / z), str(boxes.instance[i]), quad,
                          metric, name, anchor))
    return out


def _face_quad(centre: np.ndarray, size: np.ndarray, quat: np.ndarray, name: str,
               T_cam_world: np.ndarray, intr: CameraIntrinsics, cfg: GuideConfig,
               ) -> tuple[tuple[tuple[float, float], ...] | None, tuple[float, float] | None]:
    """Image corners of a vehicle face (the outer side of its plate slab, grown by
    ``face_margin_m`` left and right) as seen from outside, and its metric size; (None, None)
    when a corner is behind the camera."""
    R = quat_to_matrix(quat[None])[0]
    sign = 1.0 if name == "front" else -1.0
    w, d, h = size[0] + 2 * cfg.face_margin_m, size[1], size[2]
    # seen from outside, the viewer's right is +y of the box for the front face, -y for the rear
    right = sign
    xo = sign * d / 2  # outer side of the slab
    local = np.array([[xo, -right * w / 2, h / 2], [xo, right * w / 2, h / 2],
                      [xo, right * w / 2, -h / 2], [xo, -right * w / 2, -h / 2]])
    world = centre + local @ R.T
    cam = apply(T_cam_world, world)
    if (cam[:, 2] < cfg.near_m).any():
        return None, None
    uv, _ = project_points(cam, intr, near=cfg.near_m)
    if not np.isfinite(uv).all():
        return None, None
    return tuple((float(u), float(v)) for u, v in uv), (float(w), float(h))


def ground_height(boxes: WorldBoxes | None, T_world_ego: np.ndarray, within_m: float) -> float:
    """The ground's height in the ego frame (z up) where the far band starts: the median
    bottom of the LiDAR-cluster boxes within ``within_m`` of the ego (each cluster's bottom
    is the ground estimated under it), 0 (the ego frame's origin on the road, as
    base_link conventions put it) when there are none. Why the clusters': an ego frame
    whose origin is at the rear axle or the LiDAR would put the band metres off."""
    if boxes is None or not len(boxes):
        return 0.0
    local = apply(invert(T_world_ego), boxes.center)
    near = np.hypot(local[:, 0], local[:, 1]) <= within_m
    if not near.any():
        return 0.0
    return float(np.median(local[near, 2] - boxes.size[near, 2] / 2))


def band_region(T_cam_world: np.ndarray, T_world_ego: np.ndarray, intr: CameraIntrinsics,
                ground_z: float, cfg: GuideConfig) -> Region | None:
    """The far band of one image: where a plate of a vehicle between ``band_from_m`` and the
    range where it shrinks to ``band_min_plate_px`` (0.52 m at f px: f x 0.52 / 20 m, 93 m
    for a 30° 1080p camera) can be, from the camera's calibration and the ground (``ground_z``
    in the ego frame, z up): the full image width, the rows between the ground
    (``band_ground_margin_m`` below it) at the nearest range and the top of the plate slab
    (``plate_z_m``, plus the margin) at either range. None when the camera's plates are under
    ``band_min_plate_px`` already at ``band_from_m`` (a wide camera: its far plates need
    not be found) or the band is off.

    Why geometry and no object: beyond ~40 m a spinning LiDAR of 32 beams and 1° columns puts
    0-3 returns on a car (one ring at car height, one or two columns), too few to tell a car
    from a pole, while a narrow camera still sees its plate 20-40 px wide. The search is
    then bounded by where such a plate can be (a band ~0.1 of a narrow camera's rows),
    not by what the LiDAR saw."""
    if cfg.band_from_m <= 0:
        return None
    f = 0.5 * (intr.fx + intr.fy)
    r_far = f * cfg.plate_width_m / max(cfg.band_min_plate_px, 1e-6)
    if r_far <= cfg.band_from_m:
        return None
    T_ego_cam = invert(T_world_ego) @ invert(T_cam_world)
    axis = T_ego_cam[:3, 2]
    if np.hypot(axis[0], axis[1]) < 1e-6:
        return None  # a camera looking straight up or down sees no far road
    a0 = float(np.arctan2(axis[1], axis[0]))
    half = float(np.arctan(0.5 * intr.width / intr.fx))
    az = a0 + np.linspace(-half, half, 9)
    m = cfg.band_ground_margin_m
    pts = []
    for r in (cfg.band_from_m, r_far):
        for z in (ground_z - m, ground_z + cfg.plate_z_m[1] + m):
            xy = T_ego_cam[:2, 3] + r * np.stack([np.cos(az), np.sin(az)], 1)
            pts.append(np.column_stack([xy, np.full(len(az), z)]))
    world = apply(T_world_ego, np.concatenate(pts))
    cam = apply(T_cam_world, world)
    uv, _ = project_points(np.where(cam[:, 2:3] >= cfg.near_m, cam, np.nan), intr,
                           near=cfg.near_m)
    v = uv[:, 1][np.isfinite(uv[:, 1])]
    if not len(v):
        return None
    y0, y1 = max(0.0, float(v.min())), min(float(intr.height), float(v.max()))
    if y1 - y0 < 2:
        return None
    return Region("plate", (0.0, y0, float(intr.width), y1), cfg.band_min_plate_px, "band",
                  part="band", expected_max_px=float(f * cfg.plate_width_m / cfg.band_from_m))


def world_boxes_from_sensor(t_ns: np.ndarray, T_world_sensor: np.ndarray, center: np.ndarray,
                            size: np.ndarray, quat: np.ndarray, velocity: np.ndarray,
                            category: np.ndarray, instance: np.ndarray) -> WorldBoxes:
    """Boxes given in a sensor frame (one ``T_world_sensor`` per row) -> world boxes. Rows
    without a velocity (many datasets annotate none) get their instance's track velocity."""
    vel = np.asarray(velocity, float)
    missing = ~np.isfinite(vel).all(1)
    c, q, v = transform_boxes(T_world_sensor, center, quat, np.nan_to_num(vel))
    t = np.asarray(t_ns, np.int64)
    inst = np.asarray(instance).astype(str)
    if missing.any():
        v[missing] = track_velocity(t, c, inst)[missing]
    return WorldBoxes(t, c, np.asarray(size, float), q, v, np.asarray(category).astype(str),
                      inst)


def track_velocity(t_ns: np.ndarray, centre: np.ndarray, instance: np.ndarray) -> np.ndarray:
    """(M, 3) world velocity of each box from its instance's neighbouring boxes in time
    (central differences; one-sided at the ends; zero for an instance seen once)."""
    out = np.zeros((len(t_ns), 3))
    for name in np.unique(instance):
        idx = np.flatnonzero(instance == name)
        idx = idx[np.argsort(t_ns[idx], kind="stable")]
        t = t_ns[idx].astype(np.float64) * 1e-9
        keep = np.concatenate([[True], np.diff(t) > 0])  # one box per time (several agents)
        idx, t = idx[keep], t[keep]
        if len(idx) < 2:
            continue
        out[idx] = np.stack([np.gradient(centre[idx, k], t) for k in range(3)], 1)
    return out
