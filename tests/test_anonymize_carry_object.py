"""Regions of a LiDAR-only clip's frames between key frames known by object, not by track
(``clusters.carry_by_object``: ``carry.new_regions``, ``carry.between_tracked``); pure
functions, no detector."""

from __future__ import annotations

from v2xlake.tasks.anonymize.carry import between_tracked, new_regions
from v2xlake.tasks.anonymize.detectors import Detection
from v2xlake.tasks.anonymize.guide import Region

MS = 1_000_000
SHAPE = (1080, 1920, 3)
Box = tuple[float, float, float, float]


def _face(inst: str, box: Box, part: str = "rear") -> Region:
    """A vehicle face's plate region (``lidar:<agent>:<sensor>:t<k>@o<object>``)."""
    return Region("plate", box, 80.0, inst, None, None, part, None)


def test_a_region_under_another_agents_track_is_known_by_its_object() -> None:
    """One car seen by both agents' LiDARs: its rear region comes from the red agent's track
    on one key frame and the black agent's on the other (regions come from the scan nearest
    in time, of either agent). By track it is new on every frame between (searched afresh);
    by object it is known. A region whose object is cut by the frame edge on a key frame is
    searched afresh either way (its clipped box does not follow it), and so is one whose
    object is on neither key frame."""
    red = _face("lidar:red:L:t4@o25", (900.0, 500.0, 1200.0, 800.0))
    black = _face("lidar:black:L:t31@o25", (920.0, 500.0, 1220.0, 800.0))
    here = _face("lidar:black:L:t31@o25", (910.0, 500.0, 1210.0, 800.0))
    assert new_regions([here], [red], [black], SHAPE) == [here]
    assert new_regions([here], [red], [black], SHAPE, by_object=True) == []
    assert new_regions([here], [red], [], SHAPE, by_object=True) == []
    cut = _face("lidar:red:L:t4@o25", (1700.0, 500.0, 1920.0, 800.0))
    assert new_regions([here], [cut], [black], SHAPE, by_object=True) == [here]
    other = _face("lidar:red:L:t9@o40", (910.0, 500.0, 1210.0, 800.0))
    assert new_regions([other], [red], [black], SHAPE, by_object=True) == [other]


def test_a_part_of_one_object_elsewhere_in_the_image_is_searched() -> None:
    """Two agents may name a car's ends the other way round (a footprint's yaw is known
    modulo 180 degrees), and two cars may be given one object number: a region of the
    object's part far from where that part was on both key frames is another part, searched
    here (a review's case: the black agent's 'front' of the car, its other end, was taken
    as known from the red agent's 'front' on the key frames, and a plate there was neither
    carried nor searched). A region between the key frames' places is known."""
    front_a = _face("lidar:red:L:t4@o25", (900.0, 500.0, 1200.0, 800.0), "front")
    front_b = _face("lidar:red:L:t4@o25", (960.0, 500.0, 1260.0, 800.0), "front")
    other_end = _face("lidar:black:L:t31@o25", (300.0, 500.0, 500.0, 700.0), "front")
    assert new_regions([other_end], [front_a], [front_a], SHAPE, by_object=True) == [other_end]
    partly = _face("lidar:black:L:t31@o25", (1150.0, 500.0, 1450.0, 800.0), "front")
    assert new_regions([partly], [front_a], [front_b], SHAPE, by_object=True) == [partly]
    between = _face("lidar:black:L:t31@o25", (930.0, 510.0, 1230.0, 790.0), "front")
    assert new_regions([between], [front_a], [front_b], SHAPE, by_object=True) == []
    # an object moving diagonally: a corner of the box around both places was never its
    up_left = _face("lidar:red:L:t4@o25", (100.0, 100.0, 300.0, 300.0), "front")
    down_right = _face("lidar:red:L:t4@o25", (900.0, 700.0, 1100.0, 900.0), "front")
    corner = _face("lidar:black:L:t31@o25", (900.0, 100.0, 1100.0, 300.0), "front")
    assert new_regions([corner], [up_left], [down_right], SHAPE, by_object=True) == [corner]
    on_the_way = _face("lidar:black:L:t31@o25", (480.0, 380.0, 680.0, 580.0), "front")
    assert new_regions([on_the_way], [up_left], [down_right], SHAPE, by_object=True) == []


def test_a_find_in_two_cars_regions_is_not_left_to_one_of_them() -> None:
    """A plate of a car leaving the view fast, found on the first key frame where its
    centre lies both in its own car's rear region and in the front region of the parked car
    beside it (the smaller one, so ``_region_of`` picks it). That parked car's region is
    searched afresh on the frame between. Left to that search, the plate is not looked for
    where it went (it had left that region). With ``by_object`` it is carried as a find
    without a partner: its window is searched and the frame is unsure (nothing says where
    it went)."""
    plate = Detection("plate", (1500.0, 709.0, 1587.0, 734.0), 0.9, "text")
    parked = _face("lidar:black:L:t4@o23", (1147.0, 495.0, 1550.0, 793.0), "front")
    leaving = _face("lidar:black:L:t31@o25", (1207.0, 486.0, 1765.0, 888.0))
    parked_here = _face("lidar:black:L:t4@o23", (1172.0, 491.0, 1638.0, 832.0), "front")
    for by_object in (False, True):
        unsure: list[str] = []
        _f, again, _fb = between_tracked(
            ([plate], [parked, leaving], 0), ([], [], 133 * MS), [parked_here], 33 * MS,
            0.5, 2.0, SHAPE, [parked_here], None, unsure, [], None, by_object)
        assert bool(unsure) == by_object, unsure
        assert bool(again) == by_object
