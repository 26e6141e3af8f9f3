"""A plate box that is a part of a larger plate box (``guided.nms_plate_parts``, issue #22):
the text detector reads one group of a plate's characters as a line of its own, scoring
above the whole plate's line; the merge keeps the whole plate's extent, not the part alone.
"""

from __future__ import annotations

from v2xlake.tasks.anonymize.config import AnonymizeConfig
from v2xlake.tasks.anonymize.detectors import Detection, nms
from v2xlake.tasks.anonymize.evaluate import blurred_share
from v2xlake.tasks.anonymize.guided import GuidedConfig, GuidedDetector, nms_plate_parts

PLATE = (220.0, 489.0, 260.0, 498.0)  # a 40 px plate
HALF = Detection("plate", (237.0, 490.0, 260.0, 498.0), 0.91, "text-plate")
WHOLE = Detection("plate", (220.0, 489.0, 261.0, 499.0), 0.89, "text-plate")
LOOSE = Detection("plate", (218.0, 488.0, 262.0, 501.0), 0.84, "text-plate")


def test_a_part_scoring_above_its_plate_is_grown_to_the_plate() -> None:
    """Plain ``nms`` keeps the half-plate box (its score is the highest) and drops the
    whole; the merge keeps one box, the union of the boxes that hold the part."""
    plain = nms([HALF, WHOLE, LOOSE], 0.3)
    assert [d.box for d in plain] == [HALF.box]
    assert blurred_share(PLATE, [tuple(map(int, HALF.box))], (1080, 1920)) < 0.6
    (d,) = nms_plate_parts([HALF, WHOLE, LOOSE], 0.3)
    assert d.box == (218.0, 488.0, 262.0, 501.0)
    assert (d.score, d.detector) == (HALF.score, HALF.detector)
    assert blurred_share(PLATE, [(218, 488, 262, 501)], (1080, 1920)) == 1.0


def test_boxes_that_do_not_hold_the_kept_one_change_nothing() -> None:
    """A box inside the kept one, or overlapping it without holding it (shifted half a
    plate), is dropped as ``nms`` drops it; a plate elsewhere and the faces stay as they are."""
    inside = Detection("plate", (225.0, 490.0, 250.0, 497.0), 0.5, "band-plate-learned")
    shifted = Detection("plate", (235.0, 489.0, 275.0, 498.0), 0.6, "text-plate")
    other = Detection("plate", (600.0, 500.0, 640.0, 509.0), 0.7, "text-plate")
    faces = [Detection("face", (10.0, 10.0, 30.0, 34.0), 0.9, "centerface"),
             Detection("face", (12.0, 11.0, 31.0, 35.0), 0.8, "centerface")]
    dets = [WHOLE, inside, shifted, other, *faces]
    assert sorted(nms_plate_parts(dets, 0.3), key=lambda d: d.box) == sorted(
        nms(dets, 0.3), key=lambda d: d.box)


def test_the_setting_reaches_the_detector_and_the_provenance() -> None:
    on, off = AnonymizeConfig(), AnonymizeConfig(regions={"plate_parts_whole": False})
    assert GuidedConfig.of(on).plate_parts_whole and not GuidedConfig.of(off).plate_parts_whole
    assert "regions.plate_parts_whole=True" in on.provenance("v")
    assert on.provenance("v") != off.provenance("v")
    assert ":plate-parts-whole" in GuidedDetector(None, None, GuidedConfig.of(on)).version
    assert ":plate-parts-whole" not in GuidedDetector(None, None, GuidedConfig.of(off)).version


class _Fixed:
    """A full-frame detector (``GuidedDetector``'s ``extra``) that returns fixed boxes."""

    name, version = "fixed", "1"

    def __init__(self, dets: list[Detection]) -> None:
        self.dets = dets

    def detect(self, image: object) -> list[Detection]:
        return list(self.dets)


def test_the_full_frame_plan_keeps_the_whole_plate_too() -> None:
    """A frame without guidance (and a LiDAR-only frame's safety pass) ends with the same
    merge: the part is grown to the whole plate; off, the part alone, as before."""
    import numpy as np

    img = np.zeros((1080, 1920, 3), np.uint8)
    on, off = AnonymizeConfig(), AnonymizeConfig(regions={"plate_parts_whole": False})
    extra = [_Fixed([HALF, WHOLE, LOOSE])]
    (d,) = GuidedDetector(None, None, GuidedConfig.of(on), extra).full_frame(img)
    assert d.box == LOOSE.box and d.score == HALF.score
    (d,) = GuidedDetector(None, None, GuidedConfig.of(off), extra).full_frame(img)
    assert d.box == HALF.box
