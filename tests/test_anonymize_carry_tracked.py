"""LiDAR cluster tracks (``clusters.track_ids``, across agents ``clusters.object_ids``) and
the frames between key frames of a clip guided by them (``carry.between_tracked``): pure
functions, no detector."""

from __future__ import annotations

import dataclasses

import numpy as np

from v2xlake.tasks.anonymize.carry import (
    between_tracked,
    key_windows,
    merge_overlapping,
    unconfirmed,
)
from v2xlake.tasks.anonymize.clusters import object_ids, track_ids
from v2xlake.tasks.anonymize.detectors import Detection
from v2xlake.tasks.anonymize.guide import Region

MS = 1_000_000
SHAPE = (1080, 1920, 3)


def test_a_moving_car_keeps_its_track_across_scans() -> None:
    """A car 1.5 m further each 100 ms scan (returned in both orientations, as a short
    cluster is), a walker beside it, and a car seen as person-sized slivers in the third
    scan: each copy continues its own track; a box 5 m away starts a new one."""
    t = np.repeat([0, 100 * MS, 200 * MS], 4)
    car = [[10, 0, 1], [10, 0, 1], [5, 5, 1], [30, 0, 1]]
    car2 = [[11.5, 0.1, 1], [11.5, 0, 1], [5.1, 5, 1], [35, 0, 1]]
    car3 = [[13, 0.1, 1], [13.1, 0, 1], [5.2, 5.1, 1], [40, 0, 1]]
    centre = np.array(car + car2 + car3, float)
    one = [[1.8, 3, 1.5], [3, 1.8, 1.5], [0.5, 0.5, 1.7], [1.8, 4.5, 1.5]]
    size = np.array(one * 3, float)
    yaw = np.array([0, np.pi / 2, 0, 0] * 3)
    cat = np.array(["Car", "Car", "Pedestrian", "Car"] * 2
                   + ["Car", "Car", "Pedestrian", "Pedestrian"])
    ids = track_ids(t, centre, size, yaw, cat, 2.0, 250 * MS)
    first, second, third = ids[:4], ids[4:8], ids[8:]
    assert len(set(first)) == 4
    assert list(second[:3]) == list(first[:3]) and list(third[:3]) == list(first[:3])
    assert second[3] not in first and third[3] not in second  # 5 m a scan: beyond the gate
    # without a gate the same boxes get a new number in every scan
    assert len(set(track_ids(t, centre, size, yaw, cat, 0.0, 250 * MS))) == 12


def test_two_agents_tracks_of_one_object_share_it() -> None:
    """Two agents' LiDARs scanning 50 ms out of phase, each with its own track numbers: a
    car driving 15 m/s (1.5 m a scan), a parked car 5 m behind it (two tracks of agent A:
    its cluster's end-on copy too), and two walkers 1 m apart. Each object's tracks share
    one number, and only theirs: the walkers are each other's second nearest, the parked
    car is 5 m from the moving one at its first scan. Agent B's box of the parked car 4 m
    off (beyond the 3 m gate) is another object; one LiDAR's tracks are joined alone only
    when they are one cluster's copies (the moving car's track split in A is two objects
    without B)."""
    t_a = np.arange(5) * 100 * MS
    t_b = t_a + 50 * MS
    rows: list[tuple[int, float, float, str, int]] = []  # t, x, y, lidar, track
    for t0, lid, dy in ((t_a, "a", 0.0), (t_b, "b", 0.3)):
        for ts in t0:
            x = 10.0 + 15.0 * ts / 1e9
            rows.append((int(ts), x, dy, lid, 1 if lid == "a" else 7))
            rows.append((int(ts), 5.0, dy - 0.2, lid, 2 if lid == "a" else 8))
            rows.append((int(ts), 20.0, 6.0 + dy, lid, 4 if lid == "a" else 10))
            rows.append((int(ts), 20.0, 7.0 + dy, lid, 5 if lid == "a" else 11))
        if lid == "a":
            rows += [(int(ts), 5.0, -0.2, "a", 3) for ts in t0]  # the end-on copy
    t = np.array([r[0] for r in rows], np.int64)
    c = np.array([[r[1], r[2], 1.0] for r in rows])
    lid_ = np.array([r[3] for r in rows])
    trk = np.array([r[4] for r in rows])
    obj = object_ids(t, c, trk, lid_, 3.0)

    def of(lidar: str, track: int) -> set[int]:
        return set(obj[(lid_ == lidar) & (trk == track)].tolist())

    assert of("a", 1) == of("b", 7) and len(of("a", 1)) == 1
    assert of("a", 2) == of("a", 3) == of("b", 8)
    assert of("a", 4) == of("b", 10) != of("a", 5) == of("b", 11)
    assert len({next(iter(of("a", k))) for k in (1, 2, 4, 5)}) == 4
    # the parked car 4 m off in agent B's world (its pose wrong): no shared object
    far = c.copy()
    far[(lid_ == "b") & (trk == 8), 1] += 4.0
    obj_far = object_ids(t, far, trk, lid_, 3.0)
    assert set(obj_far[(lid_ == "b") & (trk == 8)]) != set(obj_far[(lid_ == "a") & (trk == 2)])
    # one LiDAR alone: its tracks keep apart, however close (a track that ended and one
    # that began where it would be), but for the copies of one cluster
    only_a = lid_ == "a"
    split = trk[only_a].copy()
    split[(t[only_a] >= 300 * MS) & (split == 1)] = 9
    alone = object_ids(t[only_a], c[only_a], split, lid_[only_a], 3.0)
    assert len(set(alone)) == len(set(split)) - 1


def test_a_plate_found_in_two_agents_tracks_gets_its_velocity() -> None:
    """The key frame before that found a plate in a region of agent B's track and the key
    frame before in agent A's (one car: ``object_ids`` gave both ``@o3``), gone on the key
    frame after: the two finds are one plate moving 300 px a key interval, so the frame
    between knows it is leaving the view (unsure: detected in full). Numbered as two
    objects, nothing pairs them (no velocity) and the car's region, whole in view on
    the key frame after, said the plate is there: the frame was carried and the plate,
    leaving the view, unblurred."""
    p_early = Detection("plate", (1400.0, 700.0, 1450.0, 712.0), 0.9, "text")
    p_key = Detection("plate", (1700.0, 700.0, 1750.0, 712.0), 0.9, "text")
    reg_b = Region("plate", (1350.0, 650.0, 1500.0, 760.0), 150.0, "lidar:b:L:t9@o3", None,
                   None, "front", None)
    reg_a = Region("plate", (1650.0, 650.0, 1800.0, 760.0), 150.0, "lidar:a:L:t5@o3", None,
                   None, "rear", None)
    # the car's region lags: 20 px further on the key frame after, whole in view
    reg_a1 = dataclasses.replace(reg_a, box=(1670.0, 650.0, 1820.0, 760.0))
    before = ([p_key], [reg_a], 0)
    after: tuple[list[Detection], list[Region], int] = ([], [reg_a1], 100 * MS)
    unsure: list[str] = []
    between_tracked(before, after, [], 33 * MS, 0.5, 2.0, SHAPE, (),
                    ([p_early], [reg_b], -100 * MS), unsure)
    assert any("velocity" in u for u in unsure)
    # another object in agent B's region: no velocity, the lagging region says in view
    other = dataclasses.replace(reg_b, instance="lidar:b:L:t9@o4")
    unsure = []
    between_tracked(before, after, [], 33 * MS, 0.5, 2.0, SHAPE, (),
                    ([p_early], [other], -100 * MS), unsure)
    assert not unsure


def test_a_find_past_its_fresh_region_is_not_left_to_that_region() -> None:
    """A find whose region is searched afresh here (its track is not in the key frame
    after) is left to that search, unless its image velocity, with its reach (the window:
    2 sizes), puts it outside the region: a close car's box lags the car (a 64 px plate at
    90 px a frame was past its region's edge, and the region's search missed it). Then
    it is judged as a find gone in the key frame after: leaving the view by its
    velocity, so unsure (detected in full). A slow one stays inside its region with its
    reach and is left to its search."""
    reg = Region("plate", (1590.0, 600.0, 1800.0, 760.0), 25.0, "lidar:a:L:t5@o3", None,
                 None, "rear", None)
    here = dataclasses.replace(reg, box=(1600.0, 600.0, 1810.0, 760.0))  # lags the car
    p_key = Detection("plate", (1700.0, 700.0, 1720.0, 706.0), 0.9, "text")
    before = ([p_key], [reg], 0)
    after: tuple[list[Detection], list[Region], int] = ([], [], 100 * MS)
    for x_early, expect in ((1400.0, True), (1690.0, False)):
        early = Detection("plate", (x_early, 700.0, x_early + 20.0, 706.0), 0.9, "text")
        e_reg = Region("plate", (x_early - 50.0, 650.0, x_early + 100.0, 760.0), 25.0,
                       "lidar:b:L:t9@o3", None, None, "front", None)
        unsure: list[str] = []
        between_tracked(before, after, [here], 33 * MS, 0.5, 2.0, SHAPE, [here],
                        ([early], [e_reg], -100 * MS), unsure)
        assert bool(unsure) == expect, (x_early, unsure)


def test_a_face_crossing_the_view_is_searched_where_it_went() -> None:
    """A face 20 px high crossing a narrow camera 30 px a frame: at 130 px in the key frame
    before, 43 px in the key frame after (too far apart to pair); the frame 67 ms after the
    first key frame must search where the face is now (72-93 px), and a face inside a
    close car's whole-frame region (a track new here, searched at the car's scale) is not
    given up to that region's search."""
    car = Region("face", (0.0, 0.0, 1920.0, 1080.0), 364.0, "lidar:a:L:t67", None, None,
                 "window", (900.0, 500.0))
    before = ([Detection("face", (130.0, 404.0, 148.0, 426.0), 0.73, "centerface")], [], 0)
    after = ([Detection("face", (43.0, 402.0, 62.0, 425.0), 0.58, "centerface")], [car],
             100 * MS)
    found, again, fallback = between_tracked(before, after, [car], 67 * MS, 0.5, 2.0, SHAPE,
                                             [car])
    assert not found and not fallback  # nothing paired, nothing leaving the view
    assert any(r.kind == "face" and r.box[0] <= 72 and r.box[2] >= 93
               and r.box[1] <= 401 and r.box[3] >= 428 and r.expected_px < 30 for r in again)
    # the same face found in both key frames a few px apart: interpolated, no search
    after2 = ([Detection("face", (140.0, 404.0, 158.0, 426.0), 0.7, "centerface")], [], 100 * MS)
    found, again, _ = between_tracked(before, after2, [], 50 * MS, 0.5, 2.0, SHAPE)
    assert not again and len(found) == 1 and abs(found[0].box[0] - 135.0) < 1e-6


def test_a_plate_leaving_the_view_is_kept_when_its_search_fails() -> None:
    """A plate cut by the right edge in the key frame before and gone in the one after: its
    window is searched and, where that finds nothing, the plate stays blurred (the
    detector scores a 20 px sliver of a plate low); one inside the frame is not kept."""
    before = ([Detection("plate", (1867.0, 689.0, 1920.0, 717.0), 0.85, "text"),
               Detection("plate", (900.0, 689.0, 980.0, 705.0), 0.9, "text")], [], 0)
    _found, again, fallback = between_tracked(before, ([], [], 100 * MS), [], 33 * MS, 0.5,
                                              2.0, SHAPE)
    assert len(again) == 2 and len(fallback) == 1
    region, kept = fallback[0]
    assert kept.box[2] == 1920.0 and region.box[0] < 1867.0
    # the window's search decides: a plate of its size found there replaces the carried
    # box; a face found there, a piece of a plate under half its size, or nothing keeps it
    cx = (region.box[0] + region.box[2]) / 2
    found = Detection("plate", (cx - 20, 690.0, cx + 20, 700.0), 0.7, "text")
    face = Detection("face", found.box, 0.7, "face")
    piece = Detection("plate", (cx - 10, 690.0, cx + 10, 700.0), 0.7, "text")
    assert unconfirmed(fallback, [found]) == []
    assert unconfirmed(fallback, [face]) == [kept] == unconfirmed(fallback, [])
    assert unconfirmed(fallback, [piece]) == [kept]


def test_a_plate_leaving_the_view_between_key_frames_stays_blurred() -> None:
    """A plate leaving the narrow camera at 45 px a frame (the simulated seed-1 clip): at
    1662-1771 px in one key frame, 1785-1906 px in the next (inside the frame, touching no
    edge), gone in the one after. Two frames later its 34-43 px still in view lie at
    1877-1920 px: the image velocity of the two key frames before puts it there, cut by
    the frame edge, and it is kept when its window search finds nothing. Without the
    earlier key frame nothing is kept (the old behaviour: not blurred at all); a plate
    that moves on inside the frame is not kept either (searched, as before)."""
    earlier = ([Detection("plate", (1662.0, 671.0, 1771.0, 695.0), 0.92, "text"),
                Detection("plate", (900.0, 600.0, 980.0, 616.0), 0.9, "text")], [], 0)
    before = ([Detection("plate", (1785.0, 712.0, 1906.0, 737.0), 0.91, "text"),
               Detection("plate", (910.0, 600.0, 990.0, 616.0), 0.9, "text")], [],
              100 * MS)
    after: tuple[list[Detection], list[Region], int] = ([], [], 200 * MS)
    t = 167 * MS
    _f, again, fallback = between_tracked(before, after, [], t, 0.5, 2.0, SHAPE, (), earlier)
    assert len(again) == 2 and len(fallback) == 1
    region, kept = fallback[0]
    assert kept.box[0] <= 1877.0 and kept.box[2] == 1920.0
    assert kept.box[1] <= 741.0 and kept.box[3] >= 760.0
    assert region.box[0] <= kept.box[0] and region.box[2] == 1920.0
    assert unconfirmed(fallback, []) == [kept]
    _f, _again, fallback = between_tracked(before, after, [], t, 0.5, 2.0, SHAPE)
    assert not fallback


def test_faces_of_two_tracks_are_not_interpolated_into_one() -> None:
    """Two walkers 30 px a frame apart in time: walker A at 1351 px in the key frame
    before (its head region: track t1), walker B at 1352 px in the key frame after (track
    t2). They are not paired (an interpolated box would sit at 1351 px while A is at 1383
    px): each is searched for around it. A pair of one track that moved more than its size
    is checked in a window around the interpolated box, which is kept only as a fallback."""
    def head(inst: str, x: float) -> Region:
        return Region("face", (x - 40, 480.0, x + 60, 560.0), 10.0, inst, None, None, "head",
                      (x + 5, 520.0))

    a = Detection("face", (1351.0, 517.0, 1358.0, 527.0), 0.5, "centerface")
    b = Detection("face", (1352.0, 513.0, 1364.0, 527.0), 0.68, "centerface")
    ra, rb = head("lidar:a:L:t1", 1351), head("lidar:a:L:t2", 1352)
    # both walkers are seen in both scans (B 90 px behind A before, A 110 px ahead after)
    before, after = [ra, head("lidar:a:L:t2", 1261)], [head("lidar:a:L:t1", 1461), rb]
    found, again, _ = between_tracked(([a], before, 0), ([b], after, 100 * MS), [ra, rb],
                                      33 * MS, 0.5, 2.0, SHAPE)
    assert not found and len(again) == 2
    # a track that broke between the key frames (t1 gone after) does not block the pair
    found, again, _ = between_tracked(([a], [ra], 0), ([b], [rb], 100 * MS), [ra, rb],
                                      33 * MS, 0.5, 2.0, SHAPE)
    assert len(found) == 1 and not again
    # one track, 60 px between key frames: the interpolated box is a fallback of a window
    c = Detection("face", (1411.0, 517.0, 1418.0, 527.0), 0.6, "centerface")
    rc = head("lidar:a:L:t1", 1411)
    found, again, fallback = between_tracked(([a], [ra], 0), ([c], [rc], 100 * MS), [ra],
                                             50 * MS, 0.5, 2.0, SHAPE)
    assert not found and len(again) == 1 and len(fallback) == 1
    assert abs(fallback[0][1].box[0] - 1381.0) < 1e-6


def test_overlapping_finds_of_one_face_become_their_union() -> None:
    """A carried frame's overlapping windows find one 16 px face (GT 180-200 x 523-539)
    several times, each box a pixel off: one box is kept, the union of those that overlap
    it (the best scoring one alone was under IoU 0.3 of the face); a face elsewhere and a
    plate on the same pixels stay their own."""
    faces = [Detection("face", (185.2, 527.5, 194.3, 537.7), 0.36, "cf"),
             Detection("face", (183.3, 527.9, 191.4, 537.2), 0.21, "cf"),
             Detection("face", (185.8, 528.9, 195.1, 539.3), 0.23, "cf"),
             Detection("face", (400.0, 500.0, 410.0, 510.0), 0.3, "cf")]
    plate = Detection("plate", (185.0, 527.0, 195.0, 538.0), 0.9, "text")
    out = merge_overlapping([*faces, plate])
    assert len(out) == 3 and plate in out and faces[3] in out
    one = next(d for d in out if d.kind == "face" and d.box[0] < 300)
    assert one.box == (183.3, 527.5, 195.1, 539.3) and one.score == 0.36


def test_a_key_frame_without_the_full_frame_plan_searches_where_the_last_one_found() -> None:
    """``clusters.full_frame_every``: a LiDAR-only key frame without the full-frame plan
    gets a window around each detection of the key frame before that no region here
    searches at its scale: a face no cluster region covers (found by the full-frame plan),
    around where it was and where its image velocity from the key frame before that puts
    it (38 px in 100 ms: the window reaches 2 x its 20 px beyond either); none for a plate in its
    track's vehicle-face region, which is searched here, nor for a far-band plate (the band
    is searched whole on every key frame)."""
    face_e = Detection("face", (168.0, 404.0, 186.0, 424.0), 0.7, "centerface")
    face = Detection("face", (130.0, 404.0, 148.0, 424.0), 0.73, "centerface")
    quad = ((800.0, 600.0), (1000.0, 600.0), (1000.0, 700.0), (800.0, 700.0))
    car = Region("plate", (800.0, 600.0, 1000.0, 700.0), 60.0, "lidar:a:L:t3", quad,
                 (1.8, 0.9), "rear", None)
    car_here = Region("plate", (810.0, 600.0, 1010.0, 700.0), 60.0, "lidar:a:L:t3", quad,
                      (1.8, 0.9), "rear", None)
    band = Region("plate", (0.0, 500.0, 1920.0, 560.0), 20.0, "band", part="band",
                  expected_max_px=40.0)
    plate = Detection("plate", (870.0, 660.0, 930.0, 675.0), 0.9, "text")
    far = Detection("plate", (300.0, 520.0, 325.0, 528.0), 0.6, "band")
    earlier = ([face_e], [car, band], 0)
    before = ([face, plate, far], [car, band], 100 * MS)
    wins = key_windows(before, earlier, [car_here, band], 200 * MS, 2.0, SHAPE)
    assert len(wins) == 1, wins
    (r,) = wins
    assert r.kind == "face" and r.part == "head" and 15 <= r.expected_px <= 25
    assert r.box[0] <= 55.0 and r.box[2] >= 188.0  # where it was and where it went (92-110)
    assert r.box[1] <= 404.0 and r.box[3] >= 424.0
    # without the key frame before that: around where it was only (the old full-frame
    # plan's find left to this key frame's own search)
    (r,) = key_windows(before, None, [car_here, band], 200 * MS, 2.0, SHAPE)
    assert r.box[0] >= 85.0
    # the vehicle's region gone here (its track ended): its plate is searched for too
    assert len(key_windows(before, earlier, [band], 200 * MS, 2.0, SHAPE)) == 2


def test_a_key_frame_window_reaches_a_face_crossing_the_view() -> None:
    """``clusters.key_window_mps``: the first key frame after one with the full-frame plan
    has no key frame before that to give a velocity; a 22 px face crossing the narrow
    camera (the simulated seed-0 clip) was at 130-148 px there and at 43-62 px 100 ms
    later, 4 face heights away: a window of 2 heights around it missed it (found by the
    full-frame plan of every frame, not blurred here). At 15 m/s across the view the
    window reaches it; without the speed it does not."""
    face = Detection("face", (130.0, 404.0, 148.0, 426.0), 0.73, "centerface")
    before = ([face], [], 0)
    (slow,) = key_windows(before, None, [], 100 * MS, 2.0, SHAPE)
    (fast,) = key_windows(before, None, [], 100 * MS, 2.0, SHAPE, 15.0)
    assert slow.box[0] > 62.0 and fast.box[0] <= 43.0
    assert fast.box[1] == slow.box[1] and fast.box[3] == slow.box[3]  # sideways only
    assert fast.expected_px == slow.expected_px  # at the face's own scale


def _plate_region(track: str, box: tuple[float, float, float, float]) -> Region:
    """A vehicle's rear face region of one LiDAR track (``lidar:<agent>:<sensor>:t<k>``)."""
    return Region("plate", box, box[2] - box[0], f"lidar:a:L:{track}", None, None, "rear",
                  None)


def test_a_plate_leaving_the_view_fast_moves_on_by_its_track() -> None:
    """A 50 px plate 300 px (6 sizes) further each key interval, gone from the view on the
    key frame after: its partner in the key frame before that is found by its track (no
    size-bounded reach gets there), and the part still in view 67 ms later (its image
    velocity puts it at x 1900-1950) stays blurred when its window search finds nothing
    (with ``clusters.carry_unsure_full`` false); by its own velocity it is leaving the view,
    so the frame is unsure (detected in full). Without that key frame nothing tells where
    it went: the frame is unsure too, and there is no part to keep."""
    p_early = Detection("plate", (1400.0, 700.0, 1450.0, 712.0), 0.9, "text")
    p_key = Detection("plate", (1700.0, 700.0, 1750.0, 712.0), 0.9, "text")
    earlier = ([p_early], [_plate_region("t5", (1350.0, 650.0, 1500.0, 760.0))], -100 * MS)
    before = ([p_key], [_plate_region("t5", (1650.0, 650.0, 1800.0, 760.0))], 0)
    after: tuple[list[Detection], list[Region], int] = ([], [], 100 * MS)
    unsure: list[str] = []
    _f, _again, fallback = between_tracked(before, after, [], 67 * MS, 0.5, 2.0, SHAPE, (),
                                           earlier, unsure)
    assert unsure == ["plate of 50 px leaving the view at its velocity"]
    assert any(d.box[0] <= 1905 and d.box[2] >= 1919 for _r, d in fallback)
    # the partner of another track (another object 300 px away) gives no velocity
    other = ([p_early], [_plate_region("t9", (1350.0, 650.0, 1500.0, 760.0))], -100 * MS)
    unsure = []
    _f, _again, fallback = between_tracked(before, after, [], 67 * MS, 0.5, 2.0, SHAPE, (),
                                           other, unsure)
    assert unsure and not fallback


def test_a_find_gone_without_velocity_is_unsure_unless_its_track_stays_in_view() -> None:
    """The first key frame's plate (no key frame before it: no image velocity), missing
    on the next key frame: where its track's region is whole in view there, the object is
    there (a missed find, searched for in its window); where the region is gone or cut by
    the frame edge, it may have left the view anywhere: unsure (the frame is detected in
    full). A new find of the key frame after near the edge, its track not in view before,
    may have entered: unsure; in the middle of the frame: searched for in its window."""
    p = Detection("plate", (1000.0, 700.0, 1050.0, 712.0), 0.9, "text")
    reg = _plate_region("t3", (950.0, 650.0, 1100.0, 760.0))
    for after_regions, expect in (([reg], False), ([], True),
                                  ([_plate_region("t3", (1800.0, 650.0, 1920.0, 760.0))],
                                   True)):
        unsure: list[str] = []
        between_tracked(([p], [reg], 0), ([], after_regions, 100 * MS), [], 33 * MS, 0.5,
                        2.0, SHAPE, (), None, unsure)
        assert bool(unsure) == expect, (after_regions, unsure)
    for box, expect in (((1850.0, 700.0, 1900.0, 712.0), True),
                        ((1000.0, 700.0, 1050.0, 712.0), False)):
        unsure = []
        between_tracked(([], [], 0), ([Detection("plate", box, 0.9, "text")], [], 100 * MS),
                        [], 33 * MS, 0.5, 2.0, SHAPE, (), None, unsure)
        assert bool(unsure) == expect, (box, unsure)


def test_one_tracks_finds_of_different_size_are_one_object() -> None:
    """A plate found 10 px wide (a piece of its text line) on one key frame and 22 px on
    the other, in one track's region: paired, not two lost finds (each searched at its own
    scale, the 22 px plate was missed between), and unsure (the box between a piece and the
    whole is neither); of two tracks they stay apart."""
    small = Detection("plate", (700.0, 540.0, 710.0, 545.0), 0.6, "text")
    large = Detection("plate", (690.0, 539.0, 712.0, 546.0), 0.8, "text")
    ra = _plate_region("t4", (650.0, 500.0, 760.0, 580.0))
    unsure: list[str] = []
    found, again, fallback = between_tracked(([small], [ra], 0), ([large], [ra], 67 * MS), [],
                                             33 * MS, 0.5, 2.0, SHAPE, (), None, unsure)
    assert len(found) == 1 and not again and not fallback
    assert len(unsure) == 1 and "10 and 22 px" in unsure[0]
    rb = _plate_region("t8", (650.0, 500.0, 760.0, 580.0))
    unsure = []
    found, again, _ = between_tracked(([small], [ra], 0), ([large], [rb], 67 * MS), [],
                                      33 * MS, 0.5, 2.0, SHAPE, (), None, unsure)
    assert not found and len(again) == 2
