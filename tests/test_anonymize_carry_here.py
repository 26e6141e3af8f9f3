"""A frame between key frames of a LiDAR-only clip judged by its own regions
(``clusters.carry_in_view_here``, ``carry.between_tracked``'s ``in_view_here``): a find of
one key frame without a partner in the other is not a reason to call the frame unsure where
the frame's own region of its track holds it in view; pure functions, no detector."""

from __future__ import annotations

import dataclasses

import numpy as np

from v2xlake.tasks.anonymize.carry import between_tracked
from v2xlake.tasks.anonymize.detectors import Detection
from v2xlake.tasks.anonymize.guide import Region

MS = 1_000_000
SHAPE = (1080, 1920, 3)
Box = tuple[float, float, float, float]


def _head(track: str, box: Box, expected: float = 20.0) -> Region:
    """A walker's head region of one LiDAR track."""
    return Region("face", box, expected, f"lidar:a:L:{track}", None, None, "head", None)


def _plate(track: str, box: Box) -> Region:
    return Region("plate", box, box[2] - box[0], f"lidar:a:L:{track}", None, None, "rear",
                  None)


def _covers(r: Region, box: Box) -> bool:
    return r.box[0] <= box[0] and r.box[1] <= box[1] and box[2] <= r.box[2] and box[3] <= r.box[3]


def test_a_walker_crossing_whose_region_is_here_is_searched_where_it_went() -> None:
    """A pedestrian crossing the front camera at 30 px a frame (90 px per key interval), its
    face found on the first key frame only (its LiDAR track has no region on the next: a far
    walker gets returns in some sweeps only). Without a velocity nothing on the key frames
    says where it went: unsure. This frame's own region of its track (the scan nearest this
    frame) is whole and moves the face 60 px on, inside the frame: with
    ``in_view_here`` the frame is sure, and its window search covers the face where it is
    now (not only where it was)."""
    face = Detection("face", (1000.0, 500.0, 1020.0, 520.0), 0.8, "centerface")
    r0 = _head("t2", (990.0, 490.0, 1030.0, 530.0))
    here = _head("t2", (1050.0, 490.0, 1090.0, 530.0))
    truth_now: Box = (1060.0, 500.0, 1080.0, 520.0)
    for on, expect_unsure in ((False, True), (True, False)):
        unsure: list[str] = []
        zones: list = []
        _found, again, _fb = between_tracked(([face], [r0], 0), ([], [], 100 * MS), [here],
                                             67 * MS, 0.5, 2.0, SHAPE, (), None, unsure,
                                             zones, None, (on, on))
        assert bool(unsure) == expect_unsure, unsure
        assert any(_covers(r, truth_now) for r in again)


def test_a_region_here_that_cannot_vouch_leaves_the_frame_unsure() -> None:
    """The frame's own region does not vouch where it is cut by the frame edge (a vehicle
    turning out of the view: its clipped box no longer follows it, though its anchor would
    keep the find's window inside the frame), where moving the find with it puts the find's
    window past the edge, where the frame's regions come from the key frame's own scan
    (its region is the key frame's: moving the find with it says nothing of where it went),
    or where the find is not of the region's scale (a small face in a close car's window
    region: the region's motion is not the face's)."""
    plate = Detection("plate", (1700.0, 700.0, 1750.0, 712.0), 0.9, "text")
    r0 = _plate("t3", (1650.0, 650.0, 1800.0, 760.0))
    anchored = dataclasses.replace(r0, anchor=(1725.0, 705.0))
    cut = dataclasses.replace(r0, box=(1660.0, 650.0, 1920.0, 760.0), anchor=(1735.0, 705.0))
    cases = (
        (anchored, cut, (True, True)),  # turning out: cut by the edge
        (r0, _plate("t3", (1720.0, 650.0, 1870.0, 760.0)), (True, True)),  # window past edge
        (r0, r0, (False, True)),  # the key frame's own scan: its region says nothing here
    )
    for key, here, new in cases:
        unsure: list[str] = []
        between_tracked(([plate], [key], 0), ([], [], 100 * MS), [here], 33 * MS, 0.5, 2.0,
                        SHAPE, (), None, unsure, [], None, new)
        assert unsure, here
    # the control: a region from a later scan that moved little vouches
    unsure = []
    between_tracked(([plate], [anchored], 0), ([], [], 100 * MS),
                    [dataclasses.replace(anchored, anchor=(1735.0, 705.0))], 33 * MS, 0.5, 2.0,
                    SHAPE, (), None, unsure, [], None, (True, True))
    assert not unsure
    small = Detection("face", (900.0, 500.0, 910.0, 510.0), 0.6, "centerface")
    window = _head("t4", (700.0, 400.0, 1100.0, 700.0), expected=80.0)  # 8x the face
    unsure = []
    between_tracked(([small], [window], 0), ([], [], 100 * MS), [window], 33 * MS, 0.5, 2.0,
                    SHAPE, (), None, unsure, [], None, (True, True))
    assert unsure


def test_a_new_find_whose_region_is_here_has_not_just_entered() -> None:
    """The ego vehicle braking hard: a plate ahead grows and is found on the key frame after
    only (not before: it was smaller than the detector's reach), near the side of the frame.
    Its track's region was not in view before, so it may have entered the view between the
    key frames (unsure); with ``in_view_here`` this frame's own region, whole and holding it
    inside the frame, says it is in view here (its window is searched), so the frame is
    sure."""
    plate = Detection("plate", (1790.0, 700.0, 1840.0, 712.0), 0.9, "text")
    r1 = _plate("t6", (1740.0, 650.0, 1890.0, 760.0))
    here = _plate("t6", (1700.0, 660.0, 1820.0, 748.0))  # 33 ms earlier: farther, smaller
    for on in (False, True):
        unsure: list[str] = []
        _f, again, _fb = between_tracked(([], [], 0), ([plate], [r1], 100 * MS), [here],
                                         67 * MS, 0.5, 2.0, SHAPE, (), None, unsure, [],
                                         None, (on, on))
        assert bool(unsure) != on, unsure
        assert any(_covers(r, plate.box) for r in again)
    # the frame's regions from the key frame after's own scan: its region is that key
    # frame's, so it cannot tell whether the plate was in view before it
    unsure = []
    between_tracked(([], [], 0), ([plate], [r1], 100 * MS), [r1], 67 * MS, 0.5, 2.0, SHAPE,
                    (), None, unsure, [], None, (True, False))
    assert unsure


def test_a_frame_knows_which_scans_its_regions_come_from() -> None:
    """``ClipGuide.scans``: each agent's scan nearest the image (LiDAR clusters), the same
    for two images nearest one scan, () for annotated boxes (moved to each image's time)."""
    from v2xlake.tasks.anonymize.context import ClipGuide
    from v2xlake.tasks.anonymize.guide import GuideConfig
    from v2xlake.tasks.anonymize.timespace import T0_OFFSET_NS

    class _Boxes:
        def __init__(self, t: list[int]) -> None:
            self.t_ns = np.asarray(t, np.int64)

        def __len__(self) -> int:
            return len(self.t_ns)

    g = ClipGuide(GuideConfig(), source="lidar clusters")
    g.boxes = {"b": _Boxes([0, 0, 100 * MS]), "a": _Boxes([5 * MS, 105 * MS])}  # type: ignore[dict-item]
    at = [g.scans(t * MS - T0_OFFSET_NS) for t in (0, 33, 67, 100)]
    assert at[0] == at[1] == (5 * MS, 0)
    assert at[2] == at[3] == (105 * MS, 100 * MS)
    g.source = "annotations"
    assert g.scans(33 * MS - T0_OFFSET_NS) == ()
