"""The far band's plate-blob test (``guided.band_plate_blobs``, issue #22): real 20-25 px
plates, too small for the text detector (their glyphs blur into the plate), are found as
light, textured rectangles of a plate's shape; plain lamps, wide signs and the real street
frames' band rows are not.
"""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np

from tests.fixtures.real import SHARED_REAL, requires_real_data
from tests.test_anonymize_lidar_band import paste_band_plates
from v2xlake.tasks.anonymize.guided import GuidedConfig, band_plate_blobs


def _plate(img: np.ndarray, x: int, y: int, w: int, h: int, glyphs: bool) -> None:
    """A light ``w`` x ``h`` rectangle on the darker body; ``glyphs``: dark strokes every
    2 px in its middle rows (a 20 px plate's glyphs as the band sees them)."""
    img[y : y + h, x : x + w] = 200
    if glyphs:
        img[y + 1 : y + h - 1, x + 2 : x + w - 2 : 2] = 90


def test_small_textured_plates_in_the_band_only() -> None:
    """In a flat band: a 20 x 5 px light rectangle with glyph strokes is a plate (its box
    within a pixel); the same rectangle without strokes (a lamp), one 120 px wide (legible
    to the text detector) and one under the band are not; ``band_blob_max_px`` 0: off."""
    img = np.full((1080, 1920, 3), 60, np.uint8)
    _plate(img, 500, 480, 20, 5, True)
    _plate(img, 800, 480, 20, 5, False)
    _plate(img, 1200, 470, 120, 26, True)
    _plate(img, 1500, 800, 20, 5, True)
    cfg = GuidedConfig()
    found = band_plate_blobs(img, (0, 400, 1920, 600), 20.0, cfg)
    assert len(found) == 1, found
    (box, score), = found
    assert np.allclose(box, (500, 480, 520, 485), atol=1.0) and 0 < score <= 0.5
    assert band_plate_blobs(img, (0, 400, 1920, 600), 20.0,
                            replace(cfg, band_blob_max_px=0.0)) == []


@requires_real_data("plates_eu", "images/street_pjlab_sensorx2car_0.png")
def test_real_20_px_plates_in_a_real_streets_band() -> None:
    """Real plates_eu plates (the bench's half) shrunk to 20 and 25 px, 8 of each, pasted
    across the band rows of a real 1392 x 512 street frame without plates: the street alone
    gives nothing; with the plates, 20 px 3 and 25 px 6 of 8 are found at IoU >= 0.3
    (measured), and 3 boxes lie off them, on the pasted car photos (stickers, a lamp). The text
    detector's band pass and closer look found 7 of 32 such 20 px plates in the band of
    simulated clips."""
    from v2xlake.tasks.anonymize.evaluate import plates_eu
    from v2xlake.tasks.geometry import iou_xyxy

    eu = plates_eu(SHARED_REAL / "plates_eu")[::2]
    base = cv2.imread(str(SHARED_REAL / "images" / "street_pjlab_sensorx2car_0.png"))
    assert base is not None
    box = (0, 200, base.shape[1], 310)
    cfg = GuidedConfig()
    assert band_plate_blobs(base, box, 20.0, cfg) == []
    hits, off = {}, {}
    for wd, k0 in ((20, 0), (25, 8)):
        img = base.copy()
        truth = paste_band_plates(img, box, eu, wd, 8, k0)
        found = [b for b, _sc in band_plate_blobs(img, box, 20.0, cfg)]
        m = iou_xyxy(np.array(truth), np.array(found)) if found else np.zeros((8, 1))
        hits[wd] = int((m >= 0.3).any(axis=1).sum())
        off[wd] = int((m.max(axis=0) < 0.1).sum()) if found else 0
    assert hits[20] >= 3 and hits[25] >= 5 and sum(off.values()) <= 3, (hits, off)
