"""The far band's strip searched by the text detector only around its glyph lines
(``clusters.band_text_near_lines``, issue #22: LiDAR-only clips at fleet speed).

* the strip's pieces cover each proposed line's columns with the band's largest plate of
  context on both sides, overlapping spans as one piece, at the band's own scale and its full
  height; no line, no piece;
* small text lines in the band are found by the region search with the option on as with the
  whole strip; a blank band costs no text-detector call on its strip.
"""

from __future__ import annotations

import numpy as np
import pytest

from v2xlake.tasks.anonymize.guide import Region
from v2xlake.tasks.anonymize.guided import GuidedConfig, band_strip_pieces, plan_pieces


def _band(x1: float = 1920.0, y0: float = 400.0, y1: float = 600.0) -> Region:
    return Region("plate", (0.0, y0, x1, y1), 20.0, "band", part="band", expected_max_px=62.0)


def test_strip_pieces_cover_the_lines_columns_with_context() -> None:
    cfg = GuidedConfig()
    band = _band()
    s = cfg.band_plate_px / 20.0
    lines = [(500.0, 480.0, 530.0, 486.0), (560.0, 470.0, 600.0, 480.0),
             (1500.0, 450.0, 1620.0, 470.0)]
    pieces = band_strip_pieces(band, lines, 1920, 1080, cfg)
    crops = sorted(p.crop for p in pieces if p.crop is not None)
    assert len(crops) == 2  # the two near lines' spans joined
    (a0, ay0, a1, ay1, sa), (b0, by0, b1, by1, sb) = crops
    assert (ay0, ay1, by0, by1) == (400, 600, 400, 600)  # the band's full height
    assert sa == pytest.approx(s) and sb == pytest.approx(s)
    assert a0 <= 500 - 62 and a1 >= 600 + 62  # the largest plate of context each side
    assert b0 <= 1500 - 120 and b1 >= 1620 + 120  # a wide line: its own width each side
    assert all(p.expected == (20.0, 62.0) for p in pieces)
    whole = plan_pieces([band], (1080, 1920), cfg)
    assert sum(p.out_w * p.out_h for p in pieces) < 0.5 * whole[0].out_w * whole[0].out_h
    assert band_strip_pieces(band, [], 1920, 1080, cfg) == []
    # spans reaching the frame's edges are clipped to it
    (edge,) = band_strip_pieces(band, [(10.0, 480.0, 40.0, 486.0)], 1920, 1080, cfg)
    assert edge.crop is not None and edge.crop[0] == 0


def test_the_region_search_with_lines_only_finds_what_the_whole_strip_finds() -> None:
    """Three small plate-like text lines on a noisy band: the band's plates with the option
    on are those of the whole strip (boxes within 1.5 px); a blank band gives no text-detector
    call on its strip."""
    import cv2

    from v2xlake.tasks.anonymize.build import build_detector
    from v2xlake.tasks.anonymize.config import AnonymizeConfig

    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur(rng.integers(70, 110, (1080, 1920, 3)).astype(np.uint8), (0, 0), 2)
    for x, text in ((300, "AB 123"), (1100, "KX 4071"), (1500, "M 88 ZT")):
        cv2.rectangle(img, (x - 4, 490), (x + 60, 510), (235, 235, 235), -1)
        cv2.putText(img, text, (x - 2, 506), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (20, 20, 20), 1,
                    cv2.LINE_AA)
    band = _band()
    whole = build_detector(AnonymizeConfig(clusters={"band_blob_max_px": 0,
                                                     "band_learned_score": 0,
                                                     "band_look_px": 0,
                                                     "band_text_near_lines": False}))
    near = build_detector(AnonymizeConfig(clusters={"band_blob_max_px": 0,
                                                    "band_learned_score": 0,
                                                    "band_look_px": 0,
                                                    "band_text_near_lines": True}))
    a = sorted(d.box for d in whole.in_regions(img, [band]) if d.kind == "plate")
    b = sorted(d.box for d in near.in_regions(img, [band]) if d.kind == "plate")
    assert len(a) == 3 and len(b) == 3, (a, b)
    assert np.allclose(np.asarray(a), np.asarray(b), atol=1.5)
    blank = np.full((1080, 1920, 3), 90, np.uint8)
    calls: list[tuple[int, ...]] = []
    for det in (whole, near):
        plate = det.plate
        assert plate is not None
        orig = plate.lines_view

        def spy(view: np.ndarray, orig=orig):  # type: ignore[no-untyped-def]
            calls.append(view.shape)
            return orig(view)

        object.__setattr__(plate, "lines_view", spy)
    assert whole.in_regions(blank, [band]) == [] and len(calls) == 1  # the whole strip
    assert near.in_regions(blank, [band]) == [] and len(calls) == 1  # no line, no call


def test_a_low_contrast_plate_is_why_the_lines_only_search_is_off_by_default() -> None:
    """Far plates of low contrast (light grey 115 on 95, dark grey glyphs) hold no glyph-edge
    line the closer look proposes: the default (the whole strip, with every other far-band
    path on) finds all three, lines only misses some. If this stops failing for lines only,
    the option may be worth measuring again as a default."""
    import cv2

    from v2xlake.tasks.anonymize.build import build_detector
    from v2xlake.tasks.anonymize.config import AnonymizeConfig
    from v2xlake.tasks.geometry import iou_xyxy

    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur(rng.integers(70, 110, (1080, 1920, 3)).astype(np.uint8), (0, 0), 2)
    truth = []
    for x, text in ((300, "AB 123"), (1100, "KX 4071"), (1500, "M 88 ZT")):
        cv2.rectangle(img, (x - 4, 490), (x + 60, 510), (115, 115, 115), -1)
        cv2.putText(img, text, (x - 2, 506), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (95, 95, 95), 1,
                    cv2.LINE_AA)
        truth.append((x - 4, 490, x + 60, 510))
    assert not AnonymizeConfig().clusters.band_text_near_lines

    def found(cfg: AnonymizeConfig) -> int:
        boxes = [d.box for d in build_detector(cfg).in_regions(img, [_band()])
                 if d.kind == "plate"]
        if not boxes:
            return 0
        return int((iou_xyxy(np.asarray(truth, float), np.asarray(boxes)) >= 0.3)
                   .any(axis=1).sum())

    assert found(AnonymizeConfig()) == 3
    assert found(AnonymizeConfig(clusters={"band_text_near_lines": True})) < 3
