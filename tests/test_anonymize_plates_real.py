"""The learned plate detector (PP-OCRv4 DB text lines + plate geometry) on real photos.

* ``plates_eu/``: 108 real photos of European cars, one labelled plate each (openalpr's
  benchmark, AGPL test data read in place: skipped when the folder is absent). Recall at IoU
  >= 0.3 must be >= 0.95 (the issue's target; 104/108 measured with reading, plateread.py:
  three vanity plates without a digit are read as lettering; 107/108 without reading).
* the real street images of ``images/labels.json``: at most 0.5 false blurs per image
  and 0.5 % of the image area (the classic detector made 82 on one of them).
* the DB post-processing (probability map -> text lines) is a pure function, tested on a map
  with known lines; the model comes from the installed wheel, identified by its hash.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tests.fixtures.real import requires_real_data
from v2xlake.tasks.anonymize.evaluate import plates_eu, score_real, street_images
from v2xlake.tasks.anonymize.textplate import TextPlateDetector, db_lines, text_det_onnx_path

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"
EU = REAL / "plates_eu"
STREETS = REAL / "images"


@pytest.fixture(scope="module")
def detector() -> TextPlateDetector:
    return TextPlateDetector()


def test_model_ships_in_the_wheel(detector: TextPlateDetector) -> None:
    p = text_det_onnx_path()
    assert p.name == "ch_PP-OCRv4_det_infer.onnx" and "rapidocr_onnxruntime" in str(p)
    assert "onnx-sha256:" in detector.version and "rapidocr_onnxruntime-1.4.4" in detector.version


def test_db_lines_recovers_rectangles() -> None:
    """A 200 x 40 band and a tilted 120 x 24 band of probability 0.9: two lines, unclipped
    by d = area x 1.6 / perimeter on every side, the tilt recovered, nothing else."""
    import cv2

    prob = np.zeros((300, 400), np.float32)
    prob[50:90, 100:300] = 0.9
    box = cv2.boxPoints(((200.0, 200.0), (120.0, 24.0), 20.0)).astype(np.int32)
    cv2.fillPoly(prob, [box], 0.9)
    prob[250:252, 10:12] = 0.9  # 2 px speck: too thin for a line
    lines = sorted(db_lines(prob, 0.3, 0.5, 1.6), key=lambda r: r[1])
    assert len(lines) == 2
    cx, cy, a, b, ang, score = lines[0]
    d = 200 * 40 * 1.6 / (2 * 240)
    assert abs(cx - 199.5) < 1.5 and abs(cy - 69.5) < 1.5 and abs(ang) < 1
    assert abs(a - (200 + 2 * d)) < 3 and abs(b - (40 + 2 * d)) < 3 and score > 0.85
    assert abs(abs(lines[1][4]) - 20.0) < 2.0


@requires_real_data("plates_eu")
def test_plates_eu_recall(detector: TextPlateDetector) -> None:
    images = plates_eu(EU)
    assert len(images) >= 100
    s = score_real(images, detector.detect, kinds=("plate",))
    assert s.recall >= 0.95, (s.recall, s.missed)


@requires_real_data("images")
def test_few_false_plates_on_real_streets(detector: TextPlateDetector) -> None:
    s = score_real(street_images(STREETS), detector.detect, kinds=("plate",))
    assert s.n_images >= 3
    assert s.false_per_image <= 0.5, s
    assert max(s.false_area) <= 0.005, s


@requires_real_data("images")
def test_default_detector_few_false_blurs_on_real_streets() -> None:
    """Faces and plates together, with the plan a frame without pose or LiDAR gets (the
    full-frame plan: faces in a coarse and an x2 pass at a score of 0.5, plates natively)."""
    from v2xlake.tasks.anonymize.build import build_detector
    from v2xlake.tasks.anonymize.config import AnonymizeConfig

    s = score_real(street_images(STREETS), build_detector(AnonymizeConfig()).detect)
    assert s.false_per_image <= 0.5, s
    assert max(s.false_area) <= 0.005, s


def _scaled_recall(images: list, width_px: float,
                   detect: object) -> float:
    """Recall at IoU >= 0.3 with each photo shrunk so its labelled plate is ``width_px``."""
    import cv2

    from v2xlake.tasks.anonymize.evaluate import match

    found = 0
    for item in images:
        img = cv2.imread(item.path, cv2.IMREAD_COLOR)
        kind, box = item.truth[0]
        s = width_px / (box[2] - box[0])
        small = cv2.resize(img, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
        dets = [d for d in detect(small) if d.kind == "plate"]  # type: ignore[operator]
        hit, _ = match([(kind, tuple(v * s for v in box))], dets, 0.3)
        found += int(hit.sum())
    return found / len(images)


@requires_real_data("plates_eu")
def test_small_real_plates_and_the_full_frame_fine_pass() -> None:
    """Without LiDAR guidance the text detector needs a plate ~80 px wide in its input: real
    plates shrunk to 44 px are mostly missed natively; ``full_plate_fine_scale=2`` (a user
    setting for recordings without pose whose plates are small) finds most of them."""
    from v2xlake.tasks.anonymize.build import build_detector
    from v2xlake.tasks.anonymize.config import AnonymizeConfig

    images = plates_eu(EU)[::9]  # 12 photos
    native = _scaled_recall(images, 44, build_detector(AnonymizeConfig()).detect)
    fine = _scaled_recall(images, 44, build_detector(AnonymizeConfig(
        plates={"full_fine_scale": 2.0})).detect)
    print(f"44 px real plates: native {native:.2f}, x2 {fine:.2f}")
    assert fine >= 0.7 and fine >= native + 0.3, (native, fine)


@requires_real_data("images")
def test_small_real_faces_in_real_streets_full_frame_plan() -> None:
    """Real faces (astronaut, Grace Hopper) pasted at 16 and 20 px tall into the real street
    images, the plan a frame without pose gets: at the default full-frame score (0.4) they
    are found, and the unpasted street images still carry no false face."""
    import cv2

    from v2xlake.tasks.anonymize.build import build_detector
    from v2xlake.tasks.anonymize.config import AnonymizeConfig
    from v2xlake.tasks.anonymize.evaluate import match, paste_face, real_faces

    detect = build_detector(AnonymizeConfig()).detect
    faces = real_faces()
    found = total = 0
    for k, item in enumerate(street_images(STREETS)):
        img = cv2.imread(item.path, cv2.IMREAD_COLOR)
        assert not [d for d in detect(img) if d.kind == "face"], item.path
        H, W = img.shape[:2]
        truth = []
        for j, (name, h) in enumerate([(n, h) for n in sorted(faces) for h in (16, 20)]):
            photo, box = faces[name]
            x = int((0.1 + 0.2 * j + 0.05 * k) * W)
            y = int((0.25 + 0.15 * ((j + k) % 3)) * H)
            truth.append(("face", paste_face(img, photo, box, h, x, y, body_max=40)))
        hit, _ = match(truth, [d for d in detect(img) if d.kind == "face"], 0.3)
        found += int(hit.sum())
        total += len(truth)
    print(f"real faces 16-20 px in real streets: {found}/{total}")
    assert found >= 0.9 * total, (found, total)
