"""Frames of a LiDAR-only clip where carrying is unsure (``carry.between_tracked``'s
``unsure`` and ``zones``): image velocities at a constant velocity relative to the camera
(``carry._perspective``), a pair against its image velocity, and the regions searched
there (``carry.zone_regions``). Pure functions, no detector."""

from __future__ import annotations

import pytest

from v2xlake.tasks.anonymize.carry import _perspective, between_tracked, zone_regions
from v2xlake.tasks.anonymize.detectors import Box, Detection
from v2xlake.tasks.anonymize.guide import Region

MS = 1_000_000
SHAPE = (1080, 1920, 3)
C = (960.0, 540.0)  # the principal point


def _pinhole(x_m: float, z_m: float, f: float = 1000.0, h_m: float = 0.23) -> Box:
    """A face of height ``h_m`` at lateral offset ``x_m`` and depth ``z_m`` (its centre at
    the principal point's height)."""
    s = f * h_m / z_m
    u = C[0] + f * x_m / z_m
    return (u - 0.4 * s, C[1] - s / 2, u + 0.4 * s, C[1] + s / 2)


def test_an_object_nearing_the_camera_moves_on_at_constant_velocity() -> None:
    """A face 9 m to the side, 16.4 m ahead, then 12.8 m (the seed 1 walker of 14 and 18
    px, 150 px apart, at f = 1000 px): its image velocity grows as it nears. Moved on from
    the key frame before and the one before that, the box where a constant velocity
    relative to the camera puts it is within a pixel of where it is 67 and 100 ms later;
    the constant image velocity falls short by more than twice the face's size (its
    window's reach). An object standing still in the image stays where it is whatever its
    size does (a size found a pixel larger is no motion)."""
    e, b = _pinhole(9.0, 16.4), _pinhole(9.0, 12.8)
    for k in (0.67, 1.0):
        true = _pinhole(9.0, 12.8 - k * 3.6)
        per = _perspective(b, e, k, C)
        assert per == pytest.approx(true, abs=1.0)
        lin = [u + k * (u - v) for u, v in zip(b, e, strict=True)]
        assert true[0] - lin[0] > 2 * (b[3] - b[1])
    still = _perspective((1500.0, 500.0, 1514.0, 514.0), (1500.5, 500.5, 1513.5, 513.5), 1.0, C)
    assert (still[0] + still[2]) / 2 == pytest.approx(1507.0, abs=0.5)
    # a size that would more than double: the growth is held at 2x
    big = _perspective((1000.0, 500.0, 1040.0, 540.0), (1000.0, 510.0, 1020.0, 530.0), 1.0, C)
    assert big[2] - big[0] == pytest.approx(80.0)


def _head(inst: str, box: Box) -> Region:
    return Region("face", box, 16.0, inst, None, None, "head", None)


def test_a_walker_behind_another_is_not_the_first_walkers_partner() -> None:
    """Two walkers crossing the front camera one behind the other, in one cluster track
    (seed 1, 1.0 s, 400-500 ms): the first (14 -> 18 px, 150 px per key interval) has left
    the view by the key frame after, where the second is found where the first was. Paired
    by place, the frames between would blur neither (the first walker was 150 px further);
    its image velocity says the partner is another object: the frame is unsure, with a
    zone that holds where the first walker is, and the box between the two finds is only
    searched, not blurred."""
    inst = "lidar:black:L:t3@o1"
    a_e = Detection("face", (1507.0, 511.0, 1519.0, 525.0), 0.5, "centerface")
    b_e = Detection("face", (1407.0, 514.0, 1414.0, 524.0), 0.3, "centerface")
    a_0 = Detection("face", (1660.0, 508.0, 1676.0, 526.0), 0.6, "centerface")
    b_0 = Detection("face", (1509.0, 514.0, 1518.0, 524.0), 0.5, "centerface")
    b_1 = Detection("face", (1662.0, 511.0, 1675.0, 526.0), 0.7, "centerface")
    earlier = ([a_e, b_e], [_head(inst, (1350.0, 480.0, 1560.0, 560.0))], -100 * MS)
    before = ([a_0, b_0], [_head(inst, (1450.0, 480.0, 1720.0, 560.0))], 0)
    after = ([b_1], [_head(inst, (1600.0, 480.0, 1780.0, 560.0))], 100 * MS)
    here = [_head(inst, (1500.0, 480.0, 1760.0, 560.0))]
    truth = (1814.0, 503.0, 1844.0, 526.0)  # the first walker at 67 ms
    for centre in (C, None):
        unsure: list[str] = []
        zones: list[tuple[str, Box]] = []
        found, _again, _ = between_tracked(before, after, here, 67 * MS, 0.5, 2.0, SHAPE, (),
                                           earlier, unsure, zones, centre)
        assert any("paired against its velocity" in u for u in unsure), unsure
        assert len(zones) == len(unsure) and all(k == "face" for k, _z in zones)
        assert any(z[0] <= truth[0] and truth[2] <= z[2] for _k, z in zones), zones
        assert not any(1640 <= d.box[0] <= 1680 for d in found), found
    # the frame's own windows: with the principal point one reaches the first walker
    # (a constant velocity relative to the camera); the image velocity alone stops short
    assert any(r.box[0] <= truth[0] and truth[2] <= r.box[2]
               for r in between_tracked(before, after, here, 67 * MS, 0.5, 2.0, SHAPE, (),
                                        earlier, [], [], C)[1])


def test_the_regions_searched_where_carrying_is_unsure() -> None:
    """A zone keeps each region of its kind at its own scale, only where it lies: a
    vehicle face the rectified part around its zones (once), a window band its part in the
    zone;
    a region of the other kind, one outside every zone, one searched already and the far
    band (carried as on any frame between key frames) are left out."""
    quad = ((200.0, 500.0), (600.0, 500.0), (600.0, 700.0), (200.0, 700.0))
    car = Region("plate", (200.0, 500.0, 600.0, 700.0), 104.0, "lidar:a:L:t1", quad,
                 (2.0, 1.0), "rear", (400.0, 600.0))
    band = Region("plate", (0.0, 520.0, 1920.0, 560.0), 20.0, "", None, None, "band", None,
                  60.0)
    window = Region("face", (100.0, 400.0, 900.0, 480.0), 30.0, "lidar:a:L:t2", None, None,
                    "window", None)
    far = Region("face", (1500.0, 100.0, 1560.0, 160.0), 20.0, "lidar:a:L:t3", None, None,
                 "head", None)
    fresh = Region("plate", (300.0, 520.0, 340.0, 560.0), 30.0, "lidar:a:L:t4", None, None,
                   "front", None)
    zones: list[tuple[str, Box]] = [("plate", (350.0, 550.0, 450.0, 650.0)),
                                    ("plate", (400.0, 540.0, 500.0, 600.0)),
                                    ("face", (300.0, 380.0, 500.0, 470.0))]
    out = zone_regions([car, band, window, far, fresh], zones, SHAPE, [fresh])
    (sub,) = [r for r in out if r.quad is not None]
    assert sub.expected_px == car.expected_px
    # the two zones' parts of the face, 0.4 m / 0.2 m of face around them (200 px / m),
    # clipped to the face
    assert sub.box == pytest.approx((270.0, 500.0, 580.0, 690.0))
    assert [r.box for r in out if r.part == "window"] == [(300.0, 400.0, 500.0, 470.0)]
    assert not any(r.part in ("head", "front", "band") for r in out)
    assert len(out) == 2


def test_a_far_band_plate_gone_is_unsure_only_near_the_edge() -> None:
    """A 25 px plate of the far band found on the key frame before and not on the one
    after (far plates flicker): the band is in view on every frame and has no track, so in
    the middle of the frame it is searched for over its columns, not a reason to doubt the
    frame; within its reach of the frame edge it may have left the view: unsure."""
    band = Region("plate", (0.0, 500.0, 1920.0, 560.0), 20.0, "band", part="band",
                  expected_max_px=60.0)
    for x, expect in ((900.0, False), (1880.0, True)):
        p = Detection("plate", (x, 520.0, x + 25.0, 526.0), 0.5, "text")
        unsure: list[str] = []
        zones: list[tuple[str, Box]] = []
        _f, again, _fb = between_tracked(([p], [band], 0), ([], [band], 100 * MS), [band],
                                         33 * MS, 0.5, 2.0, SHAPE, (), None, unsure, zones, C)
        assert bool(unsure) == expect, (x, unsure)
        assert any(r.part == "band" and r.box[0] <= x and x + 25 <= r.box[2] for r in again)
        if expect:  # the zone reaches the right edge
            assert zones[0][1][2] == 1920.0


def test_the_full_frame_plan_over_parts_of_the_frame() -> None:
    """``GuidedDetector.full_frame_in``: each box grown by the margin (a small one to the
    minimum side), overlapping ones searched once as one cut-out, finds read back in frame
    pixels and kept only where their centre lies in one of the boxes (not in the margin)."""
    import numpy as np

    from v2xlake.tasks.anonymize.guided import GuidedDetector

    det = GuidedDetector(None, None)
    crops: list[tuple[int, int]] = []

    def plan(image: np.ndarray) -> list[Detection]:  # a face in the middle, a plate in a corner
        crops.append(image.shape[:2])
        cy, cx = image.shape[0] / 2, image.shape[1] / 2
        return [Detection("face", (cx - 10, cy - 10, cx + 10, cy + 10), 0.9, "stub"),
                Detection("plate", (0.0, 0.0, 10.0, 10.0), 0.9, "stub")]

    det.full_frame = plan  # type: ignore[method-assign]
    image = np.zeros((1080, 1920, 3), np.uint8)
    boxes: list[Box] = [(100.0, 100.0, 300.0, 200.0), (250.0, 150.0, 400.0, 300.0),
                        (1000.0, 500.0, 1010.0, 510.0)]
    out = det.full_frame_in(image, boxes, margin=32, min_side=96)
    # the first two as one (68-432 x 68-332), the small one grown to 96 px
    assert sorted(crops) == [(96, 96), (264, 364)]
    assert [(d.kind, d.box) for d in out] == [("face", (240.0, 190.0, 260.0, 210.0)),
                                              ("face", (995.0, 495.0, 1015.0, 515.0))]
