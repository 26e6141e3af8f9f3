"""Small plates in frames without guidance (``plateprop.py``): an edge band that looks like a
row of glyphs is searched at the scale that makes it legible to the text detector.

* ``glyph_transitions`` counts a row of glyphs, not an edge, a gradient or a flat patch;
* ``band_scale`` upscales only low bands that hold glyphs, to ``line_px`` tall, capped;
* on real data: real plates (plates_eu photos shrunk to 40 px wide) pasted into a real
  street frame are found by the full-frame plan with the closer look, and fewer without it.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from tests.fixtures.real import requires_real_data
from v2xlake.tasks.anonymize.plateprop import band_scale, glyph_transitions

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"


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


def test_band_scale_upscales_only_low_bands_of_glyphs() -> None:
    img, band = _glyph_row()
    gray = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    # a 10 px band of glyphs: brought to 28 px, at most 3x (capped) and never below base
    assert abs(band_scale(band, gray, 1.0, 28.0, 3.0, 8) - 2.8) < 1e-9
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
    from v2xlake.tasks.anonymize.evaluate import match, plates_eu

    base = cv2.imread(str(REAL / "images" / "street_pjlab_sensorx2car_0.png"))
    eu = plates_eu(REAL / "plates_eu")[4::18][:6]
    on = build_detector(AnonymizeConfig())
    off = build_detector(AnonymizeConfig(plates={"small_line_px": 0}))
    assert not on._plates_proposed(base)
    found = {"on": 0, "off": 0}
    for k, item in enumerate(eu):
        photo = cv2.imread(item.path)
        (kind, (x0, y0, x1, y1)), = item.truth
        s = 40.0 / (x1 - x0)
        small = cv2.resize(photo, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
        img = base.copy()
        sh, sw = small.shape[:2]
        ox, oy = 100 + 190 * k, base.shape[0] - sh - 10
        img[oy : oy + sh, ox : ox + sw] = small
        truth = [(kind, (x0 * s + ox, y0 * s + oy, x1 * s + ox, y1 * s + oy))]
        for name, det in (("on", on), ("off", off)):
            hit, _ = match(truth, det._plates_proposed(img), 0.3)
            found[name] += int(hit[0])
    print(f"40 px real plates in a real street: {found}")
    assert found["on"] >= 5 and found["off"] < found["on"], found
