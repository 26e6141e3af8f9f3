"""Plate candidates verified by reading them (plateread.py): plates are plates.

* the judgement is a pure function of a reading: plates pass (EU, Czech / Slovak plates whose
  emblem reads as ':'), words, dates, times, repeated strokes and punctuation do not;
* rendered on an image: a simulator-style plate is read and kept; lettering, a timestamp
  watermark, a striped barrier and a lattice facade drawn the same way are dropped; a
  vanity plate without a digit is kept by its plate look, the same word as lettering not;
* real photos: the labelled plates of ``plates_eu`` are kept natively (>= 0.95), and shrunk to
  40 px wide with the x2.5 full-frame fine pass (>= 0.95, 0.85 at x2); the real street and
  x2.5 pass finds 5.7 false plates per image on the real street images without reading; keep
  at most 0.5 per image and none over 1 % of the frame.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.fixtures.real import requires_real_data
from v2xlake.tasks.anonymize.plateread import (
    PlateReadConfig,
    PlateReader,
    Reading,
    line_crop,
    plate_reading_ok,
    read_text,
    rec_onnx_path,
)
from v2xlake.tasks.anonymize.textplate import TextPlateConfig, TextPlateDetector

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"
CFG = PlateReadConfig()


def _ok(text: str, aspect: float = 4.0, conf: float = 0.95) -> bool:
    return plate_reading_ok(Reading(text, (conf,) * len(text)), aspect, CFG)[0]


def test_ctc_decode_drops_blanks_and_repeats() -> None:
    charset = ["<blank>", "A", "1", " "]
    seq = [1, 1, 0, 1, 2, 2, 0, 0, 3, 2]
    probs = np.full((len(seq), 4), 0.01, np.float32)
    probs[np.arange(len(seq)), seq] = 0.97
    r = read_text(probs, charset)
    assert r.text == "AA1 1" and len(r.confs) == 5 and min(r.confs) > 0.9


@pytest.mark.parametrize("text", ["RK-755AJ", "1B1:9839", "BZM 22-27", "OY09 FEU", "4B4：0262",
                                  "BA3020Z", "W·053011"])
def test_plates_pass(text: str) -> None:
    assert _ok(text), plate_reading_ok(Reading(text, (0.95,) * len(text)), 4.0, CFG)


@pytest.mark.parametrize(("text", "aspect"), [
    ("CITROEN", 4.0), ("histogram of grey values", 7.6), ("Berlingo7", 3.6),
    ("2023-05-12", 5.0), ("12:30:45", 4.0), ("12.05.2023", 5.0), ("IIIIIII", 4.0),
    ("1111111", 4.0), ("瑞批厂", 4.4), ("", 4.0), ("RK", 2.5), ("RK-755AJ", 1.3),
    ("AB12CD34EF56", 6.0), ("#,;|||-.", 4.0)])
def test_non_plates_fail(text: str, aspect: float) -> None:
    assert not _ok(text, aspect)


def test_low_confidence_fails() -> None:
    assert not _ok("RK-755AJ", conf=0.35) and _ok("RK-755AJ", conf=0.6)


def test_a_line_low_in_the_frame_is_judged_on_a_guess() -> None:
    """A line lower than ``small_h`` px in the frame (a ~30 px plate) keeps symbols from
    ``small_char_conf`` and needs no mean confidence (real 30 px plates: '14981' at 0.44,
    '8AT' at 0.25 were rejected); the rules that tell words, dates and stripes from plates
    still hold there, and a line as low in the view but larger in the frame is read as
    before."""
    guess = Reading("14981", (0.5, 0.5, 0.27, 0.3, 0.46))
    faint = Reading("8AT", (0.22, 0.25, 0.27))
    letters = Reading("POKE", (0.39, 0.73, 0.3, 0.32))  # a guess without a digit
    assert CFG.small_h > 8.0
    for r in (guess, faint, letters):
        assert not plate_reading_ok(r, 3.6, CFG)[0]
        assert not plate_reading_ok(r, 3.6, CFG, frame_h=CFG.small_h + 1)[0]
        assert plate_reading_ok(r, 3.6, CFG, frame_h=8.0)[0]
    for text in ("CITROEN", "NORTH", "EXIT", "12:30:45", "1111111", "", "Berlingo7"):
        r = Reading(text, (0.9,) * len(text))
        assert not plate_reading_ok(r, 4.0, CFG, frame_h=8.0)[0], text
    assert not plate_reading_ok(Reading("8AT", (0.05, 0.05, 0.05)), 3.6, CFG, frame_h=8.0)[0]


@pytest.fixture(scope="module")
def reader() -> PlateReader:
    return PlateReader()


def test_model_ships_in_the_package(reader: PlateReader) -> None:
    assert rec_onnx_path().name == "ch_PP-OCRv4_rec_infer.onnx"
    assert "rapidocr_onnxruntime-1.4.4" in reader.version and "onnx-sha256:" in reader.version
    assert len(reader.charset) > 6000 and "A" in reader.charset and "7" in reader.charset


def _line(img: np.ndarray, text: str, org: tuple[int, int], scale: float = 1.6,
          colour: tuple[int, int, int] = (20, 20, 20)) -> tuple[float, ...]:
    """Draw ``text`` and return its line as (cx, cy, long, short, tilt)."""
    font, thick = cv2.FONT_HERSHEY_SIMPLEX, 4
    (tw, th), base = cv2.getTextSize(text, font, scale, thick)
    cv2.putText(img, text, org, font, scale, colour, thick, cv2.LINE_AA)
    return (org[0] + tw / 2, org[1] - th / 2 + base / 4, tw + 0.6 * th, 1.6 * th, 0.0)


def test_rendered_plate_kept_lettering_and_watermark_dropped(reader: PlateReader) -> None:
    img = np.full((400, 900, 3), 235, np.uint8)
    cv2.rectangle(img, (40, 30), (420, 120), (30, 30, 30), 4)
    lines = {"plate": _line(img, "KA 47301", (70, 98)),
             "lettering": _line(img, "Logistics", (480, 98)),
             "watermark": _line(img, "2024-05-12 14:33:02", (40, 220), 1.3),
             "brand": _line(img, "CITROEN", (40, 330))}
    judged = dict(zip(lines, reader.judge(img, list(lines.values())), strict=True))
    assert judged["plate"][0], judged["plate"]
    for k in ("lettering", "watermark", "brand"):
        assert not judged[k][0], (k, judged[k])


def test_vanity_plate_kept_by_its_look_lettering_not(reader: PlateReader) -> None:
    """A reading without a digit (GWAGEN) is a plate when its line looks like one: dark
    glyphs on a white plate that ends with them, on a dark body (kept; dropped with
    ``no_digit_look`` off, as before). The same word as lettering is dropped: white on a
    green sign, dark on a white van that runs on around it, blue on a white sticker."""
    from dataclasses import replace

    img = np.full((560, 700, 3), 60, np.uint8)
    lines = {}
    cv2.rectangle(img, (30, 20), (330, 90), (235, 235, 235), -1)  # the plate
    lines["plate"] = _line(img, "GWAGEN", (45, 75))
    img[140:260, 0:380] = (40, 110, 20)  # a green road sign
    lines["sign"] = _line(img, "GWAGEN", (45, 220), colour=(240, 240, 240))
    img[280:420, :] = 235  # a white van's side
    lines["van"] = _line(img, "GWAGEN", (45, 370))
    cv2.rectangle(img, (30, 450), (330, 520), (235, 235, 235), -1)  # a sticker
    lines["sticker"] = _line(img, "GWAGEN", (45, 505), colour=(160, 60, 20))
    judged = dict(zip(lines, reader.judge(img, list(lines.values())), strict=True))
    assert judged["plate"][0], judged["plate"]
    for k in ("sign", "van", "sticker"):
        assert not judged[k][0] and judged[k][2] is not None, (k, judged[k])
    reader.config = replace(reader.config, no_digit_look=False)
    try:
        assert reader.judge(img, [lines["plate"]])[0][1] == "no digit"
    finally:
        reader.config = replace(reader.config, no_digit_look=True)


def test_stripes_and_lattice_dropped(reader: PlateReader) -> None:
    """A red-white striped barrier and a lattice facade, read as text lines of plate shape."""
    barrier = np.full((60, 260, 3), 240, np.uint8)
    for x in range(0, 260, 26):
        cv2.fillConvexPoly(barrier, np.array([[x, 0], [x + 13, 0], [x + 1, 60], [x - 12, 60]]),
                           (30, 30, 200))
    lattice = np.full((60, 260, 3), 200, np.uint8)
    lattice[:, ::14] = 40
    lattice[::12] = 40
    for img in (barrier, lattice):
        ok, why, r = reader.judge(img, [(130.0, 30.0, 250.0, 50.0, 0.0)])[0]
        assert not ok, (why, r)


def test_line_crop_derotates() -> None:
    """A line drawn at 20 deg comes out level: its rows' ink is concentrated in the middle."""
    img = np.full((300, 400, 3), 255, np.uint8)
    box = cv2.boxPoints(((200.0, 150.0), (200.0, 20.0), 20.0)).astype(np.int32)
    cv2.fillPoly(img, [box], (0, 0, 0))
    crop = line_crop(img, (200.0, 150.0, 200.0, 40.0, 20.0))
    assert crop.shape[0] == 48 and 190 < crop.shape[1] < 280
    ink = (crop[:, 20:-20, 0] < 128).mean(1)
    assert ink[20:28].min() > 0.9 and ink[:6].max() < 0.1 and ink[-6:].max() < 0.1


# ----------------------------------------------------------------------------- real photos
def _scaled_recall(det: TextPlateDetector, width_px: float, fine: float | None) -> float:
    from v2xlake.tasks.anonymize.detectors import ScanConfig
    from v2xlake.tasks.anonymize.evaluate import match, plates_eu

    scan = ScanConfig(max_side=None, fine_scale=fine, tile=2048, tile_overlap=160,
                      upscale_min_side=0)
    found = n = 0
    for item in plates_eu(REAL / "plates_eu"):
        img = cv2.imread(item.path, cv2.IMREAD_COLOR)
        kind, box = item.truth[0]
        s = width_px / (box[2] - box[0]) if width_px else 1.0
        small = cv2.resize(img, None, fx=s, fy=s, interpolation=cv2.INTER_AREA) if s != 1 \
            else img
        hit, _ = match([(kind, tuple(v * s for v in box))], det.detect_scan(small, scan), 0.3)
        found += int(hit.sum())
        n += 1
    return found / n


@requires_real_data("plates_eu")
def test_real_plates_40px_found_with_the_fine_pass() -> None:
    """Real plates shrunk to 40 px wide, the full-frame x2.5 fine pass, read: >= 0.95 (103/108
    measured; the misses: vanity plates without a digit, one misread)."""
    r = _scaled_recall(TextPlateDetector(), 40, 2.5)
    print(f"plates_eu at 40 px, x2.5, read: {r:.3f}")
    assert r >= 0.95, r


@requires_real_data("images")
def test_false_plates_on_real_streets_read_away() -> None:
    """The x2.5 full-frame pass on the real street images: without reading 5.7 false plates
    per image, up to 6 % of a frame (facades, shop signs, lettering); read: at most 0.5 per
    image and none over 1 % of the frame."""
    from v2xlake.tasks.anonymize.detectors import ScanConfig
    from v2xlake.tasks.anonymize.evaluate import score_real, street_images

    scan = ScanConfig(max_side=None, fine_scale=2.5, tile=2048, tile_overlap=160,
                      upscale_min_side=0)
    items = street_images(REAL / "images")
    stats = {}
    for name, det in (("geometry", TextPlateDetector(TextPlateConfig(read=None))),
                      ("read", TextPlateDetector())):
        stats[name] = score_real(items, lambda im, d=det: d.detect_scan(im, scan),
                                 kinds=("plate",))
    print({k: (s.false_per_image, max(s.false_area)) for k, s in stats.items()})
    assert stats["geometry"].false_per_image >= 2  # the test can fail: there is much to drop
    assert stats["read"].false_per_image <= 0.5, stats["read"]
    assert max(stats["read"].false_area) <= 0.01, stats["read"]


@requires_real_data("plates_eu", "images/street_pjlab_sensorx2car_0.png")
def test_small_real_plates_read_on_a_guess() -> None:
    """Six real plates shrunk to 30 px wide (the photos of the plateprop 40 px test), each
    pasted into the lower middle of a real street frame (its 464 x 256 lower middle third:
    the plan's cost follows the frame's pixels), the full-frame plan: their lines are found
    but their readings are guesses (glyphs of 4-5 px). Judged as guesses (``small_h``) at
    least two more are kept than read as large lines (``small_h`` 0, before): measured 3
    and 0; over the bench's 108 pasted 30 px plates 41 -> 47 with no new false plate."""
    from dataclasses import replace

    from v2xlake.tasks.anonymize.build import build_detector
    from v2xlake.tasks.anonymize.config import AnonymizeConfig
    from v2xlake.tasks.anonymize.evaluate import match, paste_plate_photo, plates_eu

    street = cv2.imread(str(REAL / "images" / "street_pjlab_sensorx2car_0.png"))[256:, 464:928]
    det = build_detector(AnonymizeConfig())
    assert det.plate is not None and det.plate.reader is not None
    reader = det.plate.reader
    guess = reader.config
    found = {"guess": 0, "read": 0}
    for item in plates_eu(REAL / "plates_eu")[4::18][:6]:
        img = street.copy()
        truth = [paste_plate_photo(img, item, 30.0)]
        for name, cfg in (("guess", guess), ("read", replace(guess, small_h=0.0))):
            reader.config = cfg
            hit, _ = match(truth, det._plates_proposed(img), 0.3)
            found[name] += int(hit[0])
    reader.config = guess
    print(f"30 px real plates in a real street: {found}")
    assert found["guess"] >= found["read"] + 2, found
