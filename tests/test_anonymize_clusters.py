"""LiDAR clusters and projected regions on a real scan and its real image, and the guide's
geometry on a box with a known answer.

The PJLab frame (``calib/pjlab_lidar2camera``: a real 64-beam scan, the camera intrinsics and
the LiDAR-to-camera extrinsic, and the image whose small blue plate is labelled in
``images/labels.json``): the car 40 m ahead is seen by the LiDAR only as its rear face (a
1.7 m x 0.5 m footprint), and the guide still puts a vehicle-face region over its 23 px plate,
expecting a plate of about that width. Skipped when the real data is absent.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from tests.fixtures.real import requires_real_data
from v2xlake.schemas.calibration import CameraIntrinsics
from v2xlake.tasks.anonymize.clusters import cluster_boxes, yaw_quat
from v2xlake.tasks.anonymize.guide import GuideConfig, WorldBoxes, project_regions
from v2xlake.tasks.anonymize.guided import GuidedConfig, plan_pieces

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"
PJLAB = REAL / "calib" / "pjlab_lidar2camera"
PLATE = np.array([981.0, 634.0, 1004.0, 643.0])  # labels.json, street_plate_small_pjlab_0


def _boxes(c: np.ndarray, s: np.ndarray, yaw: np.ndarray, cat: np.ndarray) -> WorldBoxes:
    n = len(c)
    return WorldBoxes(np.zeros(n, np.int64), c, s, yaw_quat(yaw), np.zeros((n, 3)),
                      np.asarray(cat), np.array([f"c{i}" for i in range(n)]))


@requires_real_data("calib/pjlab_lidar2camera")
def test_real_scan_guides_to_the_real_plate() -> None:
    pts = np.loadtxt(PJLAB / "0.pcd", skiprows=11)[:, :3]
    doc = json.loads((PJLAB / "center_camera-intrinsic.json").read_text())
    K = np.asarray(doc["center_camera-intrinsic"]["param"]["cam_K"]["data"], float)
    ext = json.loads((PJLAB / "top_center_lidar-to-center_camera-extrinsic.json").read_text())
    T_cam_lidar = np.asarray(
        ext["top_center_lidar-to-center_camera-extrinsic"]["param"]["sensor_calib"]["data"],
        float)
    c, s, yaw, cat = cluster_boxes(pts)  # the LiDAR frame has z up: it is the world here
    ahead = (cat == "Car") & (np.abs(c[:, 0] - 40.6) < 1.5) & (np.abs(c[:, 1] + 0.3) < 1.0)
    assert ahead.any(), "the car 40 m ahead is not a vehicle cluster"
    intr = CameraIntrinsics(width=1920, height=1200, fx=K[0, 0], fy=K[1, 1], cx=K[0, 2],
                            cy=K[1, 2])
    regions = project_regions(_boxes(c, s, yaw, cat), T_cam_lidar, intr, GuideConfig())
    over = [r for r in regions if r.kind == "plate" and r.box[0] <= PLATE[0]
            and r.box[1] <= PLATE[1] and r.box[2] >= PLATE[2] and r.box[3] >= PLATE[3]]
    assert over, "no vehicle-face region over the labelled plate"
    r = max(over, key=lambda r: r.expected_px)
    assert 0.5 <= (PLATE[2] - PLATE[0]) / r.expected_px <= 2.0  # a 0.44-0.52 m plate at 40 m
    assert r.quad is not None  # rectified head-on


def test_rectified_face_of_a_car_seen_from_behind() -> None:
    """A 4.5 m car 10 m ahead of a camera looking along +x (z up world, optical camera):
    its rear face is searched (the front is turned away), rectified at the plate scale, and
    the window band and nothing else is searched for faces."""
    boxes = _boxes(np.array([[10.0, 0.0, 0.75]]), np.array([[1.8, 4.5, 1.5]]), np.array([0.0]),
                   np.array(["Car"]))
    T_cam_world = np.array([[0, -1, 0, 0], [0, 0, -1, 1.5], [1, 0, 0, 0], [0, 0, 0, 1.0]])
    intr = CameraIntrinsics(width=1280, height=720, fx=1000, fy=1000, cx=640, cy=360)
    regions = project_regions(boxes, T_cam_world, intr, GuideConfig())
    assert sorted(r.part for r in regions) == ["rear", "window"]
    rear = next(r for r in regions if r.part == "rear")
    assert rear.quad is not None and rear.size_m is not None
    assert abs(rear.expected_px - 1000 * 0.52 / 7.75) < 8  # rear face at 10 - 2.25 m
    (piece,) = [p for p in plan_pieces(regions, (720, 1280), GuidedConfig()) if p.kind == "plate"]
    assert piece.ppm == pytest.approx(96 / 0.52)
    assert piece.out_w == round(rear.size_m[0] * piece.ppm)
    # the rectified view's corners land on the face's corners in the image
    assert np.allclose(piece.to_frame(np.array([0, 0, piece.out_w, piece.out_h]), 1280, 720),
                       [min(p[0] for p in rear.quad), min(p[1] for p in rear.quad),
                        max(p[0] for p in rear.quad), max(p[1] for p in rear.quad)], atol=1.0)


def test_boxes_without_velocity_move_with_their_track() -> None:
    """Annotations without velocities: a car at 10 m/s along x, boxes every 100 ms; at an
    image 50 ms after a box, it is where it drove to (not where the box left it)."""
    from v2xlake.tasks.anonymize.guide import world_boxes_from_sensor

    t = np.arange(4) * 100_000_000
    c = np.stack([np.arange(4) * 1.0, np.zeros(4), np.zeros(4)], 1)
    wb = world_boxes_from_sensor(t, np.eye(4), c, np.tile([1.8, 4.5, 1.5], (4, 1)),
                                 np.tile([1.0, 0, 0, 0], (4, 1)), np.full((4, 3), np.nan),
                                 np.array(["Car"] * 4), np.array(["a"] * 4))
    assert np.allclose(wb.velocity, [[10.0, 0, 0]] * 4)
    at = wb.at(150_000_000, 250_000_000)
    assert len(at) == 1 and at.center[0, 0] == pytest.approx(1.5)


def _solid(x: tuple[float, float], y: tuple[float, float], z: tuple[float, float],
           step: float = 0.1) -> np.ndarray:
    g = np.mgrid[x[0]:x[1]:step, y[0]:y[1]:step, z[0]:z[1]:step].reshape(3, -1).T
    return g


def test_a_row_of_touching_cars_is_cut_into_cars() -> None:
    """Three parked cars (4.5 x 1.8 x 1.5 m) touching bumper to bumper are one 13.5 m cluster;
    besides the row's own box, a car-length piece is returned at each car, so the plates
    between the row's ends are searched. Rear faces of four cars parked side by side (a thin
    7.6 m row seen end-on) give four end-on cars behind the row, away from the sensor."""
    ground = _solid((-20, 20), (-20, 20), (0.0, 0.05), 0.4)
    row = _solid((0.0, 13.5), (5.0, 6.8), (0.3, 1.5))
    c, s, yaw, _cat = cluster_boxes(np.vstack([ground, row]))
    long = np.abs(np.cos(yaw)) > 0.9
    pieces = c[long & (s[:, 1] < 6.0)]
    assert len(pieces) == 3, (c, s)
    assert np.allclose(np.sort(pieces[:, 0]), [2.25, 6.75, 11.25], atol=0.5)
    faces = _solid((10.0, 10.3), (-3.8, 3.8), (0.3, 1.4))
    c, s, yaw, _cat = cluster_boxes(np.vstack([ground, faces]))
    end_on = (np.abs(np.cos(yaw)) > 0.9) & (s[:, 1] >= 4.0)  # length along x: away from us
    assert end_on.sum() == 4, (c, s, yaw)
    assert (c[end_on, 0] > 11.0).all()  # the body lies behind the rear faces
    assert np.allclose(np.sort(c[end_on, 1]), [-2.85, -0.95, 0.95, 2.85], atol=0.4)


def test_a_sparsely_scanned_car_is_one_vehicle() -> None:
    """A car's rear face 16 m ahead seen by a LiDAR with a 1.1° azimuth step (the
    simulator's): its points are 0.3 m apart, so the 0.2 m grid cuts the 1.8 m face into
    person-sized slivers and no vehicle is found; bridged across gaps of ``gap_deg`` it is a
    car, and its slivers stay as they were (nothing the grid found is lost)."""
    from v2xlake.tasks.anonymize.clusters import ClusterConfig

    ground = _solid((-20, 20), (-20, 20), (0.0, 0.05), 0.4)
    az = np.radians(np.arange(-3.2, 3.3, 1.1))
    z = np.arange(0.3, 1.4, 0.27)
    face = np.array([(16.0, 16.0 * np.tan(a), h) for a in az for h in z])

    def cars(cfg: ClusterConfig) -> np.ndarray:
        c, s, _yaw, cat = cluster_boxes(np.vstack([ground, face]), cfg)
        return (cat == "Car") & (np.abs(c[:, 0] - 16.0) < 1.0) & (np.abs(c[:, 1]) < 1.0) \
            & (s[:, :2].max(1) > 1.5)

    assert not cars(ClusterConfig(gap_deg=0.0)).any()
    assert cars(ClusterConfig()).any()


def test_an_l_of_points_gets_the_cars_own_axes() -> None:
    """A parked car seen from behind-left: its rear face (1.8 m) and 2-4 m of its side, an L
    of points. The minimum-area rectangle around an L is as small turned diagonally as
    upright, and was diagonal here (25-45°, so the rear face searched for the plate was
    not the car's); the L-shape fit keeps the car's axes and its rear face at x = 10."""
    from v2xlake.tasks.anonymize.clusters import ClusterConfig

    rng = np.random.default_rng(0)
    ground = _solid((-20, 20), (-20, 20), (0.0, 0.05), 0.4)
    for seen in (2.0, 3.0, 4.0):
        rear = np.array([(10.0, y, z) for y in np.arange(-8.2, -6.39, 0.25)
                         for z in (0.4, 0.8, 1.2)])
        side = np.array([(x, -6.4, z) for x in np.arange(10.0, 10.0 + seen, 0.25)
                         for z in (0.4, 0.8, 1.2)])
        pts = np.vstack([ground, rear, side])
        pts = pts + rng.normal(0.0, 0.02, pts.shape)
        for cfg, upright in ((ClusterConfig(), True), (ClusterConfig(lshape_step_deg=0), False)):
            c, s, yaw, cat = cluster_boxes(pts, cfg)
            car = (cat == "Car") & (np.abs(c[:, 0] - 11.0) < 2.5)
            assert car.any(), seen
            off = np.abs((np.degrees(yaw[car]) + 45) % 90 - 45)  # 0: along the car's axes
            assert (off.max() < 3) == upright, (seen, np.degrees(yaw[car]))
            if upright:  # the box's near end is the rear face
                along_x = np.where(np.abs(np.cos(yaw[car])) > 0.5, s[car, 1], s[car, 0])
                assert np.allclose(c[car, 0] - along_x / 2, 10.0, atol=0.15), (seen, c, s)


def test_a_far_sparsely_scanned_car_face_is_searched_as_a_vehicle() -> None:
    """A car's rear face 25 m away under a sparse LiDAR (1.05° columns, 0.55 m rows: the
    simulator's) gets two columns of two returns above the ground: fewer than the 8 a near
    object needs, and 0.46 m wide (person-sized). Beyond ``dense_range_m`` fewer returns
    make an object (by range², at least ``min_points_far``) and its extent may be one point
    spacing larger on each side, so it is searched both as a person and as a vehicle; near,
    four returns stay nothing."""
    from v2xlake.tasks.anonymize.clusters import ClusterConfig

    ground = _solid((-40, 40), (-10, 10), (0.0, 0.05), 0.4)
    face = np.array([(-25.5, y, z) for y in (-3.41, -2.95) for z in (0.47, 1.06)])

    def kinds(pts: np.ndarray, cfg: ClusterConfig) -> set[str]:
        c, _s, _yaw, cat = cluster_boxes(np.vstack([ground, pts]), cfg)
        near = np.hypot(c[:, 0] - pts[:, 0].mean(), c[:, 1] - pts[:, 1].mean()) < 1.0
        return set(cat[near].tolist())

    assert kinds(face, ClusterConfig()) == {"Car", "Pedestrian"}
    assert kinds(face, ClusterConfig(dense_range_m=0.0)) == set()
    assert kinds(face, ClusterConfig(sparse_extent=False)) == {"Pedestrian"}
    assert kinds(face * [0.4, 1.0, 1.0], ClusterConfig()) == set()  # the same 10 m away


def test_a_far_car_alone_in_its_ground_cell_keeps_its_lower_returns() -> None:
    """27 m away a sparse LiDAR may hit no road in the 2 m cell a car stands in: the cell's
    lowest returns are the car's own, and taken as ground they dropped its lower row (and
    with it the car: 3 returns left). The road in the cells around is the ground there."""
    from v2xlake.tasks.anonymize.clusters import ClusterConfig

    ground = _solid((-40, 40), (-10, 10), (0.0, 0.05), 0.7)
    # no road return in the car's cell (x -28..-26, y -4..-2)
    ground = ground[~((ground[:, 0] >= -28) & (ground[:, 0] < -26) & (ground[:, 1] >= -4)
                      & (ground[:, 1] < -2))]
    car = np.array([(-27.3, y, z) for y in (-3.64, -3.15, -2.7) for z in (0.36, 0.99)])

    def found(cfg: ClusterConfig) -> bool:
        c, _s, _yaw, cat = cluster_boxes(np.vstack([ground, car]), cfg)
        near = np.hypot(c[:, 0] + 27.3, c[:, 1] + 3.15) < 1.0
        return bool((near & (cat == "Car")).any())

    assert found(ClusterConfig())
    assert not found(ClusterConfig(ground_neighbours=False))


def test_a_cluster_plate_slab_starts_at_its_estimated_ground() -> None:
    """A cluster's bottom is the ground estimated under it, not a labelled box bottom: its
    vehicle faces are searched for plates from that ground up (a low plate 3 px under the
    face's lower edge 0.15 m up was missed), annotated boxes keep 0.15 m."""
    import pyarrow as pa

    from v2xlake.tasks.anonymize.context import assemble_guide

    cfg = GuideConfig()
    boxes = _boxes(np.array([[10.0, 0.0, 0.75]]), np.array([[1.8, 4.5, 1.5]]),
                   np.array([0.0]), np.array(["Car"]))
    g = assemble_guide(0, {}, {}, {}, pa.table({"t_ns": pa.array([], pa.int64())}),
                       pa.table({}), cfg, {"red": boxes})
    assert g.source == "lidar clusters"
    assert g.config.plate_z_m == (cfg.cluster_plate_z0_m, cfg.plate_z_m[1])
    assert cfg.plate_z_m[0] == 0.15 and cfg.cluster_plate_z0_m == 0.0


def test_the_far_band_holds_far_plates_of_a_narrow_camera_only() -> None:
    """The far band (a guide region from geometry, for cars too far for the LiDAR to make):
    a narrow camera (f 3583 px, 1080p) 1.25 m above a flat road sees a 0.52 m plate 20 px
    wide out to 93 m; the band's rows hold a plate 0.3-1.1 m up at 35, 60 and 90 m ahead,
    and across the frame; it expects plates of 20 px (its farthest) to 62 px (30 m). A wide
    camera (f 554 px: a plate is 20 px at 14 m, where the LiDAR makes cars) gets none, nor
    does any camera with the band off."""
    from v2xlake.tasks.anonymize.guide import band_region
    from v2xlake.tasks.projection import project_points

    T_cam_ego = np.array([[0, -1, 0, 0], [0, 0, -1, 1.25], [1, 0, 0, 0], [0, 0, 0, 1.0]])
    T_world_ego = np.eye(4)
    T_world_ego[:3, 3] = (100.0, -20.0, 3.0)  # the ego somewhere in the world
    T_cam_world = T_cam_ego @ np.linalg.inv(T_world_ego)
    narrow = CameraIntrinsics(width=1920, height=1080, fx=3583, fy=3583, cx=960, cy=540)
    cfg = GuideConfig()
    band = band_region(T_cam_world, T_world_ego, narrow, 0.0, cfg)
    assert band is not None and band.kind == "plate" and band.part == "band"
    assert band.expected_px == cfg.band_min_plate_px == 20.0
    assert band.expected_max_px == pytest.approx(3583 * 0.52 / cfg.band_from_m)
    assert band.box[0] == 0 and band.box[2] == 1920
    plates = np.array([[r, y, z] for r in (35.0, 60.0, 90.0) for z in (0.3, 1.1)
                       for y in (-r * 0.2, 0.0, r * 0.2)])  # the frame is +-0.27 r wide
    uv, _ = project_points(plates @ T_cam_ego[:3, :3].T + T_cam_ego[:3, 3], narrow)
    assert (uv[:, 1] >= band.box[1]).all() and (uv[:, 1] <= band.box[3]).all()
    assert band.box[3] - band.box[1] < 0.3 * 1080  # a band, not the frame
    # a ground 0.4 m lower (an ego frame above the road) moves the band down
    low = band_region(T_cam_world, T_world_ego, narrow, -0.4, cfg)
    assert low is not None and low.box[3] > band.box[3]
    wide = CameraIntrinsics(width=1920, height=1080, fx=554, fy=554, cx=960, cy=540)
    assert band_region(T_cam_world, T_world_ego, wide, 0.0, cfg) is None
    off = GuideConfig(band_from_m=0.0)
    assert band_region(T_cam_world, T_world_ego, narrow, 0.0, off) is None


def test_the_far_band_is_one_piece_at_its_smallest_plates_scale() -> None:
    """The band is cut out whole (not merged with a vehicle face's crop) at the scale that
    brings its smallest plate to ``band_plate_px``, expecting plates of its whole size range."""
    from v2xlake.tasks.anonymize.guide import Region

    band = Region("plate", (0.0, 400.0, 1920.0, 600.0), 20.0, "band", part="band",
                  expected_max_px=62.0)
    other = Region("plate", (100.0, 450.0, 300.0, 550.0), 20.0, "c1", part="rear")
    cfg = GuidedConfig()
    pieces = plan_pieces([band, other], (1080, 1920), cfg)
    assert len(pieces) == 2
    p = next(p for p in pieces if p.out_w > 1000)
    assert p.crop == (0, 400, 1920, 600, pytest.approx(cfg.band_plate_px / 20.0))
    assert p.expected == (20.0, 62.0)


def test_the_cluster_ground_sets_the_band() -> None:
    """The ground under the far band is the median bottom of the LiDAR-cluster boxes near the
    ego (their estimated ground), in the ego frame; none near: the ego frame's z = 0."""
    from v2xlake.tasks.anonymize.guide import ground_height

    T_world_ego = np.eye(4)
    T_world_ego[:3, 3] = (50.0, 0.0, 10.0)
    boxes = _boxes(np.array([[55.0, 0.0, 9.6 + 0.75], [60.0, 3.0, 9.6 + 0.9],
                             [200.0, 0.0, 30.0]]),
                   np.array([[1.8, 4.5, 1.5], [0.6, 0.6, 1.8], [1.8, 4.5, 1.5]]),
                   np.zeros(3), np.array(["Car", "Pedestrian", "Car"]))
    assert ground_height(boxes, T_world_ego, 30.0) == pytest.approx(-0.4)
    assert ground_height(boxes, T_world_ego, 1.0) == 0.0
    assert ground_height(None, T_world_ego, 30.0) == 0.0


def test_a_plate_cut_by_the_frame_edge_is_found_on_a_large_face() -> None:
    """On a vehicle face whose plate the text detector looks for (expected over
    ``blob_below_px``), the blob test keeps only the plate-coloured, textured rectangles the
    frame edge cuts (``cut_only``): the visible 2 cm-wide strip of a plate is no text line.
    The whole plate beside it is the text detector's (not returned here), and a piece cut by
    the frame knows it is."""
    from v2xlake.tasks.anonymize.guided import _crop_piece, plate_blobs

    rng = np.random.default_rng(0)
    ppm = 185.0  # px per metre of the rectified face
    view = np.full((260, 600, 3), (60, 60, 160), np.uint8)  # a red car body
    outside = np.zeros(view.shape[:2], bool)
    outside[:, :40] = True  # the frame ends 40 px into the view
    view[outside] = 0
    for x0 in (40, 300):  # a plate cut at the frame edge (0.10 m visible), a whole one
        w = 18 if x0 == 40 else 96
        view[120:140, x0 : x0 + w] = 235
        view[124:136, x0 + 2 : x0 + w - 2] = rng.integers(0, 255, (12, w - 4, 1))
    found = plate_blobs(view, ppm, GuidedConfig(), outside, cut_only=True)
    assert len(found) == 1 and found[0][0][0] <= 41
    assert len(plate_blobs(view, ppm, GuidedConfig(), outside)) == 2
    piece = _crop_piece("plate", 0, 0, 100, 100, 1.0, (20.0, 20.0))
    assert not piece.cut_by_frame(200, 200) and piece.cut_by_frame(80, 200)


def test_a_blob_is_no_larger_than_the_plate_its_face_expects() -> None:
    """A plate-sized rectangle in a rectified face's metres can map to half the frame where
    the face's plane runs off the frame edge near the camera: such a box is no plate."""
    from v2xlake.tasks.anonymize.guided import plate_sized

    c = GuidedConfig()
    assert plate_sized((100.0, 500.0, 250.0, 540.0), 150.0, c)
    assert not plate_sized((5.0, 526.0, 1920.0, 1080.0), 150.0, c)
    assert not plate_sized((100.0, 100.0, 130.0, 600.0), 150.0, c)
    # a car 3 m ahead of a narrow camera: its plate 620 px wide, the half-frame box still no
    # plate, a plate cut to 40 x 150 px by the frame edge one
    assert not plate_sized((5.0, 526.0, 1920.0, 1080.0), 620.0, c)
    assert plate_sized((0.0, 600.0, 40.0, 750.0), 620.0, c)
