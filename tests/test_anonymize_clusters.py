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
