"""Small plates in frames without guidance (``plateprop.py``): an edge band that looks like a
row of glyphs is searched at the scale that makes it legible to the text detector.

* ``glyph_transitions`` counts a row of glyphs, not an edge, a gradient or a flat patch, also
  beside a dark car body and off the band's middle row (where one Otsu threshold for the
  band, the measure before, counted a handful);
* ``join_bands`` / ``edge_bands`` join the halves of one glyph row, not bands of two rows;
* ``band_scale`` upscales only low bands that hold glyphs, to ``line_px`` tall, capped;
* ``edge_bands`` with ``max_stroke`` finds a glyph row that a lamp's long edge beside it
  joins into a component too large for a line;
* on real data: real plates (plates_eu photos shrunk to 40 px wide) pasted into a real
  street frame are found by the full-frame plan with the closer look, and fewer without it;
* ``is_dark`` / ``lift_dark``: a dark frame's plate pass sees it lifted locally (bright places
  kept, no edges added), which finds real plates in a real street frame at a third of its
  light; the real street frames at their own light are not dark;
* ``plates.edge_cut_min_aspect``: a text line reaching the frame's edge may be a plate cut by
  it, held to a lower aspect: real plates cut in half by a real frame's edge are found more.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np

from tests.fixtures.real import requires_real_data
from v2xlake.tasks.anonymize.plateprop import (
    band_scale,
    edge_bands,
    glyph_transitions,
    is_dark,
    join_bands,
    keep_within,
    lift_dark,
    percentiles,
    plate_band,
    row_transitions,
    short_strokes,
)

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"


def _found_by(dets: dict[str, Any], cases: list[tuple[np.ndarray, list[Any]]]) -> dict[str, int]:
    """Per detector (the full-frame plan's plate pass), how many of the cases' one pasted
    plate each it finds (IoU >= 0.3)."""
    from v2xlake.tasks.anonymize.evaluate import match

    return {name: sum(int(match(truth, det._plates_proposed(img), 0.3)[0][0])
                      for img, truth in cases) for name, det in dets.items()}


def _glyph_row() -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """A 200 x 60 grey image with a white 52 x 12 px plate of 7 dark glyphs drawn 3x larger
    and shrunk (as a far plate is), and the band of its glyphs."""
    big = np.full((180, 600, 3), 110, np.uint8)
    cv2.rectangle(big, (222, 72), (378, 108), (235, 235, 235), -1)
    cv2.putText(big, "AB1234K", (226, 102), cv2.FONT_HERSHEY_SIMPLEX, 0.8, (20, 20, 20), 2)
    img = cv2.resize(big, (200, 60), interpolation=cv2.INTER_AREA)
    return img, (75.0, 25.0, 126.0, 35.0)


def test_glyph_transitions_count_a_row_of_glyphs_not_an_edge() -> None:
    img, band = _glyph_row()
    gray = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    assert glyph_transitions(gray, band) >= 8
    flat = np.full((60, 200), 120, np.uint8)
    assert glyph_transitions(flat, band) == 0
    step = flat.copy()
    step[:, 100:] = 230  # one strong vertical edge: one crossing
    assert glyph_transitions(step, band) <= 2
    ramp = np.tile(np.linspace(0, 255, 200).astype(np.uint8), (60, 1))
    assert glyph_transitions(ramp, band) <= 2
    assert glyph_transitions(gray, (0.0, 0.0, 0.0, 0.0)) == 0  # an empty band


def _small_plate_on_dark_car(glyph_rows: tuple[int, int] = (5, 11)) -> np.ndarray:
    """A 14 x 60 px band as a 40 px plate gives it: the car's near-black body left and right,
    a bright plate between with 7 grey, 1 px glyph strokes pairs (blurred, as a shrunk plate's
    glyphs are: lighter than the body), in ``glyph_rows``."""
    band = np.full((14, 60), 25, np.uint8)
    band[3:13, 8:52] = 215
    r0, r1 = glyph_rows
    for i in range(7):
        x = 11 + 6 * i
        band[r0:r1, x] = 120
        band[r0:r1, x + 2] = 120
    return band


def test_glyph_transitions_beside_a_dark_body_and_off_the_middle_row() -> None:
    """One Otsu threshold for the band splits the dark body from the bright plate and leaves
    the grey strokes on the bright side (2 crossings: the body's edges): the running mean
    sees all 28 stroke edges. Glyphs in the band's upper half (a band that also holds the
    grille below) are still counted."""
    band = _small_plate_on_dark_car()
    box = (0.0, 0.0, 60.0, 14.0)
    t_otsu, _ = cv2.threshold(band, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    otsu = int(np.abs(np.diff((band[6:9] > t_otsu).astype(np.int8), axis=1)).sum(1).max())
    assert otsu <= 4  # the measure before: not a row of glyphs
    assert glyph_transitions(band, box) >= 20
    high = _small_plate_on_dark_car((3, 8))
    assert glyph_transitions(high, box) >= 20
    t = row_transitions(high, box)
    assert len(t) == 14 and t[-2:].max() <= 2  # the body below: no glyphs
    # the closer look's scale follows the 5 glyph rows, not the 14 px band (that gave x2)
    assert band_scale(box, high, 1.0, 28.0, 3.0, 10) == 3.0
    # a band over half of line_px tall (a large plate's) whose glyphs fill over half of it
    # keeps the Otsu test: not upscaled; one whose glyph row is at most half of it is scaled
    # for the glyph row (+2 px: 7 px to 20 px)
    assert band_scale(box, band, 1.0, 20.0, 3.0, 10) == 1.0
    assert abs(band_scale(box, high, 1.0, 20.0, 3.0, 10) - 20.0 / 7.0) < 1e-6


def test_a_tall_band_is_scaled_for_its_glyph_row() -> None:
    """A 22 px band (over half ``line_px``) whose glyphs are 6 of its rows (a 40 px plate's
    band with the car's lamp or trim above): scaled so that its glyph row, not the band, is
    ``line_px`` tall (before: 28 / 22 = 1.27x at most, and real 40 px plates in such bands
    were missed); a tall band without a glyph row keeps the band's scale."""
    band = np.full((22, 60), 60, np.uint8)
    band[:9] = 200  # the lamp / trim: plain
    band[10:21, 6:54] = 215
    for i in range(7):
        band[13:19, 9 + 6 * i] = 40
        band[13:19, 11 + 6 * i] = 40
    box = (0.0, 0.0, 60.0, 22.0)
    assert band_scale(box, band, 1.0, 28.0, 3.0, 10) == 3.0
    plain = band.copy()
    plain[13:19] = 215
    assert band_scale(box, plain, 1.0, 28.0, 3.0, 10) <= 28.0 / 22.0


def test_plate_band_grows_part_of_a_glyph_row_to_a_plate_s_text() -> None:
    """A band over the first glyphs of a row (the rest touched the bumper) is grown evenly
    to ``text_aspect`` glyph heights, so that its crop holds the whole plate; a band as wide
    already, one not narrower than ``below`` and ``text_aspect`` 0 are left as they are."""
    gray = np.full((30, 120), 200, np.uint8)
    for x in range(20, 72, 4):
        gray[10:17, x : x + 2] = 30
    part = (20.0, 9.0, 40.0, 18.0)
    grown = plate_band(part, gray, 5.6)
    assert grown[1:4:2] == part[1:4:2]
    assert abs((grown[0] + grown[2]) / 2 - 30.0) < 1e-6  # both sides evenly
    assert 38.0 <= grown[2] - grown[0] <= 50.0  # 5.6 x (7 glyph rows + 1)
    assert plate_band(part, gray, 0.0) == part
    assert plate_band(part, gray, 5.6, below=20.0) == part
    whole = (20.0, 9.0, 72.0, 18.0)
    assert plate_band(whole, gray, 5.6) == whole
    edge = plate_band((0.0, 9.0, 10.0, 18.0), gray, 5.6)
    assert edge[0] == 0.0  # clipped to the frame


def test_keep_within_keeps_scan_scale_looks_then_the_most_glyph_like() -> None:
    """Over budget: every look at the scan's scale (rank inf), then the closer looks by
    glyph alternations, most first, while the total fits; one that does not fit is skipped,
    a smaller one after it still taken."""
    area = [40.0, 30.0, 20.0, 25.0, 10.0]
    rank = [np.inf, 12.0, 20.0, 16.0, 10.0]
    assert keep_within(area, rank, 100.0) == [True, False, True, True, True]
    assert keep_within(area, rank, 40.0) == [True, False, False, False, False]
    assert keep_within(area, rank, 1000.0) == [True] * 5


def test_join_bands_joins_one_line_not_two() -> None:
    left, right = (100.0, 50.0, 126.0, 59.0), (135.0, 50.0, 153.0, 58.0)
    assert join_bands([left, right]) == [(100.0, 50.0, 153.0, 59.0)]  # 9 px apart, 8-9 tall
    assert len(join_bands([left, right], gap=0.5)) == 2
    assert len(join_bands([left, (170.0, 50.0, 190.0, 58.0)])) == 2  # 44 px apart
    assert len(join_bands([left, (128.0, 62.0, 150.0, 70.0)])) == 2  # the row below
    assert len(join_bands([left, right], max_w=40.0)) == 2  # the union too wide
    assert len(join_bands([left, right], max_h=8.0)) == 2  # not small bands
    assert len(join_bands([left, (130.0, 44.0, 150.0, 58.0)])) == 2  # a taller object
    three = join_bands([left, right, (156.0, 51.0, 170.0, 58.0)])
    assert three == [(100.0, 50.0, 170.0, 59.0)]


def test_edge_bands_join_a_glyph_row_split_at_its_hyphen() -> None:
    """A row of strokes with a 15 px gap (a plate's hyphen or emblem): one band, the
    whole row (``join_gap`` 0: the two halves, as before)."""
    img = np.zeros((40, 200), np.uint8)
    for x in list(range(40, 70, 4)) + list(range(86, 116, 4)):
        img[15:24, x : x + 2] = 255
    gx = cv2.convertScaleAbs(cv2.Sobel(img, cv2.CV_16S, 1, 0, ksize=3))
    geom = ((5.0, 60.0), (12.0, 300.0), (1.3, 12.0), 0.35)
    halves = edge_bands(gx, 90.0, *geom, join_gap=0)
    assert len(halves) == 2
    whole = edge_bands(gx, 90.0, *geom)
    assert len(whole) == 1 and whole[0][0] <= 40 and whole[0][2] >= 116


def test_percentiles_are_numpy_s() -> None:
    """The partial-sort percentiles of ``row_transitions`` give ``np.percentile``'s values."""
    rng = np.random.default_rng(0)
    for _ in range(300):
        a = rng.integers(0, 256, (int(rng.integers(1, 16)), int(rng.integers(1, 90))))
        a = a.astype(np.float32) if rng.random() < 0.7 else np.round(a / 64.0) * 64.0
        assert percentiles(a, (5.0, 95.0)) == list(np.percentile(a, (5, 95)))


def test_a_glyph_row_beside_a_long_edge_is_a_band_without_the_long_edge() -> None:
    """A row of 6 px strokes 6 px beside a slanted 30 px edge (a lamp's outline) and a 20 px
    upright one (the plate holder's side): closed horizontally, all one component, too
    large for a line, so no band of the row (as before); without the vertical edges longer
    than 10 px, the glyph row's band. A stroke 10 px tall is kept at 11, one 20 px tall not."""
    img = np.zeros((60, 200), np.uint8)
    for x in range(60, 100, 4):
        img[25:31, x : x + 2] = 255
    for y in range(10, 40):  # slanted, one pixel every 4 rows
        img[y, 50 - (y - 10) // 4 : 52 - (y - 10) // 4] = 255
    img[18:38, 104:106] = 255
    gx = cv2.convertScaleAbs(cv2.Sobel(img, cv2.CV_16S, 1, 0, ksize=3))
    geom = ((5.0, 60.0), (12.0, 300.0), (1.3, 12.0), 0.35)
    assert not any(b[0] >= 50 and b[2] <= 104 and b[3] - b[1] <= 12
                   for b in edge_bands(gx, 90.0, *geom))
    bands = edge_bands(gx, 90.0, *geom, max_stroke=10)
    assert any(55 <= b[0] <= 62 and 97 <= b[2] <= 104 and b[1] >= 20 and b[3] <= 36
               for b in bands), bands
    upright = np.zeros((30, 20), np.uint8)
    upright[5:15, 9] = 1
    upright[5:25, 4] = 1
    kept = short_strokes(upright, 11)
    assert kept[5:15, 9].all() and not kept[:, 4].any()
    assert (short_strokes(upright, 0) == upright).all()


def test_band_scale_upscales_only_low_bands_of_glyphs() -> None:
    img, band = _glyph_row()
    gray = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    # a 10 px band of glyphs: its glyph row (+2 px, at least 6 px) brought to 28 px, at
    # most 3x (capped) and never below base
    assert band_scale(band, gray, 1.0, 28.0, 3.0, 8) == 3.0
    assert 2.8 < band_scale(band, gray, 1.0, 28.0, 9.0, 8) <= 28.0 / 6.0
    assert band_scale(band, gray, 1.0, 28.0, 2.0, 8) == 2.0
    assert band_scale(band, gray, 1.0, 0.0, 3.0, 8) == 1.0  # off
    assert band_scale(band, gray, 3.0, 28.0, 3.0, 8) == 3.0  # the scan's scale suffices
    tall = (75.0, 10.0, 126.0, 50.0)  # 40 px tall: legible as it is
    assert band_scale(tall, gray, 1.0, 28.0, 3.0, 8) == 1.0
    flat = np.full((60, 200), 120, np.uint8)  # a low band without glyphs: not worth it
    assert band_scale(band, flat, 1.0, 28.0, 3.0, 8) == 1.0


@requires_real_data("plates_eu", "images/street_pjlab_sensorx2car_0.png")
def test_small_real_plates_found_by_the_closer_look() -> None:
    """Six real plates shrunk to 40 px wide, pasted into the lower half of a real 1392 x 512
    street frame: the default full-frame plan finds at least 5, and with the closer look off
    (``small_line_px`` 0, the plan before: 19 of 54 such plates over the three street
    frames) fewer. The street frame alone gets no plate."""
    from v2xlake.tasks.anonymize.build import build_detector
    from v2xlake.tasks.anonymize.config import AnonymizeConfig
    from v2xlake.tasks.anonymize.evaluate import paste_plate_photo, plates_eu

    base = cv2.imread(str(REAL / "images" / "street_pjlab_sensorx2car_0.png"))
    eu = plates_eu(REAL / "plates_eu")[4::18][:6]
    on = build_detector(AnonymizeConfig())
    off = build_detector(AnonymizeConfig(plates={"small_line_px": 0}))
    assert not on._plates_proposed(base)
    cases = []
    for k, item in enumerate(eu):
        img = base.copy()
        cases.append((img, [paste_plate_photo(img, item, 40.0, x=100 + 190 * k)]))
    found = _found_by({"on": on, "off": off}, cases)
    print(f"40 px real plates in a real street: {found}")
    assert found["on"] >= 5 and found["off"] < found["on"], found


@requires_real_data("plates_eu", "images/street_pjlab_sensorx2car_0.png")
def test_three_cars_small_plates_in_one_real_frame() -> None:
    """Three real cars' photos (plates 40 px wide) side by side along the lower edge of one
    real 1392 x 512 street frame: their fronts make so many bands that the closer looks'
    crops are over the plan's budget. All three plates found: the looks with the most glyph
    alternations are kept within the budget (``keep_within``) beside the whole frame at its
    own scale; before, only the whole frame was searched and 1 of 3 was found (each car
    alone: found)."""
    from v2xlake.tasks.anonymize.build import build_detector
    from v2xlake.tasks.anonymize.config import AnonymizeConfig
    from v2xlake.tasks.anonymize.evaluate import match, paste_plate_photo, plates_eu

    img = cv2.imread(str(REAL / "images" / "street_pjlab_sensorx2car_0.png"))
    truth = []
    for k, item in enumerate(plates_eu(REAL / "plates_eu")[1::9][:3]):
        truth.append(paste_plate_photo(img, item, 40.0, x=10 + 270 * k))
    hit, _ = match(truth, build_detector(AnonymizeConfig())._plates_proposed(img), 0.3)
    assert hit.all(), hit


def test_lift_dark_lifts_dark_places_keeps_bright_ones_and_adds_no_edges() -> None:
    img = np.full((120, 240, 3), 200, np.uint8)
    img[:, :120] = 24  # a dark half beside a bright one
    out = lift_dark(img, 96.0, 4.0)
    assert (out[:, 150:] == 200).all()  # bright: as it was
    assert abs(int(out[60, 20, 0]) - 96) <= 1  # dark: brought to the reference, 4x
    assert (lift_dark(np.full((50, 50), 8, np.uint8), 96.0, 4.0) == 32).all()  # capped
    ramp = np.tile(np.linspace(10, 60, 240).astype(np.uint8), (120, 1))
    gx = np.abs(cv2.Sobel(lift_dark(ramp, 96.0, 4.0), cv2.CV_16S, 1, 0, ksize=3))
    assert gx[:, 20:-20].max() < 40  # a smooth ramp stays smooth (no edge of the gain's own)
    assert not is_dark(img, 0.0) and is_dark(img // 8, 48.0) and not is_dark(img, 48.0)


@requires_real_data("plates_eu", "images/street_pjlab_sensorx2car_0.png")
def test_real_plates_in_a_dark_real_frame_found_when_lifted() -> None:
    """Four real plates 60 px wide pasted into a real 1392 x 512 street frame, the whole frame
    then darkened to 0.3 of its light (night, an underexposed camera): the default plan
    (``plates.dark_frame_median`` 48) finds all, without the lift fewer. The three real
    street frames at their own light are not dark (their plate pass is unchanged)."""
    from v2xlake.tasks.anonymize.build import build_detector
    from v2xlake.tasks.anonymize.config import AnonymizeConfig
    from v2xlake.tasks.anonymize.evaluate import paste_plate_photo, plates_eu

    for name in ("street_pjlab_sensorx2car_0.png", "street_pjlab_sensorx2car_1.png",
                 "street_plate_small_pjlab_0.png"):
        frame = cv2.imread(str(REAL / "images" / name))
        assert frame is not None and not is_dark(frame, 48.0), name
    base = cv2.imread(str(REAL / "images" / "street_pjlab_sensorx2car_0.png"))
    on = build_detector(AnonymizeConfig())
    off = build_detector(AnonymizeConfig(plates={"dark_frame_median": 0}))
    cases = []
    for k, item in enumerate(plates_eu(REAL / "plates_eu")[2::18][:4]):
        img = base.copy()
        truth = [paste_plate_photo(img, item, 60.0, x=100 + 190 * k)]
        cases.append(((img.astype(np.float32) * 0.3).astype(np.uint8), truth))
    found = _found_by({"on": on, "off": off}, cases)
    print(f"60 px real plates in a real street at 0.3 of its light: {found}")
    assert found["on"] == 4 and found["off"] < found["on"], found


def test_a_line_at_the_frame_edge_may_be_a_cut_plate() -> None:
    from v2xlake.tasks.anonymize.config import AnonymizeConfig
    from v2xlake.tasks.anonymize.textplate import TextPlateConfig, TextPlateDetector

    det = TextPlateDetector(TextPlateConfig.of(AnonymizeConfig()))
    half = (24.0, 14.0, 0.0)  # long, short, tilt: half an EU plate's text line
    assert not det.plate_ok((700.0, 100.0, *half), 1392)  # inside the frame: too short
    assert det.plate_ok((1381.0, 100.0, *half), 1392) and det.plate_ok((11.0, 100.0, *half), 1392)
    assert not det.plate_ok((1381.0, 100.0, 12.0, 14.0, 0.0), 1392)  # under 1: a glyph or two
    off = TextPlateDetector(TextPlateConfig.of(AnonymizeConfig(plates={"edge_cut_min_aspect": 2})))
    assert not off.plate_ok((1381.0, 100.0, *half), 1392)


@requires_real_data("plates_eu", "images/street_pjlab_sensorx2car_0.png")
def test_real_plates_cut_by_the_frame_edge() -> None:
    """Real plates 60 px wide pasted so the frame's right or left edge cuts them in half (a
    car leaving the view), in a real 1392 x 512 street frame: the default plan finds more
    of them than with the cut-plate aspect off (the reading decides either way)."""
    from v2xlake.tasks.anonymize.build import build_detector
    from v2xlake.tasks.anonymize.config import AnonymizeConfig
    from v2xlake.tasks.anonymize.evaluate import paste_plate_photo, plates_eu

    base = cv2.imread(str(REAL / "images" / "street_pjlab_sensorx2car_0.png"))
    on = build_detector(AnonymizeConfig())
    off = build_detector(AnonymizeConfig(plates={"edge_cut_min_aspect": 2.0}))
    cases = []
    for k, item in enumerate(plates_eu(REAL / "plates_eu")[::6][:8]):
        (_kind, (x0, _y0, x1, _y1)), = item.truth
        s = 60.0 / (x1 - x0)
        mid = 0.5 * (x0 + x1) * s  # the plate's middle, px from the shrunk photo's left edge
        img = base.copy()
        x = base.shape[1] - int(mid) if k % 2 == 0 else -int(mid)
        cases.append((img, [paste_plate_photo(img, item, 60.0, x=x)]))
    found = _found_by({"on": on, "off": off}, cases)
    print(f"60 px real plates cut in half by a real frame's edge: {found}")
    assert found["on"] > found["off"], found
