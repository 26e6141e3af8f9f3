"""Small plates in a frame without guidance: at which scale to look at an edge band.

The full-frame plan proposes plates by bands of dense vertical edges (``guided.edge_lines``)
and runs PP-OCRv4's DB text detector on crops around them. The detector needs glyphs of ~12
px: a plate 40 px wide has glyphs of 5-7 px, so at the frame's own scale its band is cut out
and searched in vain (real 40 px plates pasted into real streets: 19 of 54 found). A whole
frame at x2.5 finds them, at ~3x the plate time of the plan. Here only the bands that look
like a row of glyphs are upscaled, each to the scale that makes it ``small_line_px`` tall:
their crops are a few thousand pixels, the frame is a million.

What looks like a row of glyphs, cheaply (no network): one of the band's three middle rows
crosses the band's Otsu threshold at least ``min_transitions`` times (two per glyph stroke
pair; a plate's 5-8 glyphs cross it 10-20 times). Real 40 px plates: 44 of 45 bands pass at
8; of the real street images' bands 28 % (facade edges, poles, foliage cross it 4-7 times).
The reading (``plateread.py``) still decides what is a plate: this only decides where the
detector looks closer.
"""

from __future__ import annotations

import cv2
import numpy as np

Band = tuple[float, float, float, float]


def glyph_transitions(gray: np.ndarray, band: Band) -> int:
    """The most crossings of the band's Otsu threshold along one of its three middle rows
    (``gray``: the frame in grey levels, ``band``: x0, y0, x1, y1 px)."""
    h, w = gray.shape[:2]
    x0, y0 = max(0, int(band[0])), max(0, int(band[1]))
    x1, y1 = min(w, int(np.ceil(band[2]))), min(h, int(np.ceil(band[3])))
    core = gray[y0:y1, x0:x1]
    if core.shape[0] < 1 or core.shape[1] < 2:
        return 0
    t, _ = cv2.threshold(np.ascontiguousarray(core), 0, 255,
                         cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    mid = core.shape[0] // 2
    rows = core[max(0, mid - 1) : mid + 2] > t
    return int(np.abs(np.diff(rows.astype(np.int8), axis=1)).sum(axis=1).max())


def band_scale(band: Band, gray: np.ndarray, base: float, line_px: float, max_scale: float,
               min_transitions: int) -> float:
    """The scale to search an edge band at: ``base`` (the plate scan's), or, for a band lower
    than ``line_px`` that holds a row of glyphs (``glyph_transitions``), the scale that makes
    it ``line_px`` tall, at most ``max_scale`` (``line_px`` 0: always ``base``)."""
    bh = band[3] - band[1]
    if line_px <= 0 or bh * base >= line_px:
        return base
    s = float(min(max_scale, line_px / max(bh, 1.0)))
    if s <= base or glyph_transitions(gray, band) < min_transitions:
        return base
    return s


def edge_bands(gx: np.ndarray, threshold: float, h_range: tuple[float, float],
               w_range: tuple[float, float], aspect: tuple[float, float], fill: float
               ) -> list[Band]:
    """Bands of dense vertical edges in ``gx`` (|Sobel x|, grey levels) at ``threshold``:
    edges closed horizontally (3 x 9) and opened (3 x 3), components of a text line's
    height, width, aspect (px) and ``fill`` of their box."""
    m0 = (gx >= threshold).astype(np.uint8)
    m1 = cv2.morphologyEx(m0, cv2.MORPH_CLOSE, np.ones((3, 9), np.uint8))
    m2 = cv2.morphologyEx(m1, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    _n, _lab, stats, _c = cv2.connectedComponentsWithStats(m2, connectivity=8)
    (hlo, hhi), (wlo, whi), (alo, ahi) = h_range, w_range, aspect
    return [(float(x), float(y), float(x + bw), float(y + bh))
            for x, y, bw, bh, area in stats[1:].tolist()
            if hlo <= bh <= hhi and wlo <= bw <= whi and alo <= bw / bh <= ahi
            and area >= fill * bw * bh]
