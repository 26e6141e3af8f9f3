"""Small plates in a frame without guidance: at which scale to look at an edge band.

The full-frame plan proposes plates by bands of dense vertical edges (``guided.edge_lines``)
and runs PP-OCRv4's DB text detector on crops around them. The detector needs glyphs of ~12
px: a plate 40 px wide has glyphs of 5-7 px, so at the frame's own scale its band is cut out
and searched in vain (real 40 px plates pasted into real streets: 19 of 54 found). A whole
frame at x2.5 finds them, at ~3x the plate time of the plan. Here only the bands that look
like a row of glyphs are upscaled, each to the scale that makes it ``small_line_px`` tall:
their crops are a few thousand pixels, the frame is a million.

What looks like a row of glyphs, cheaply (no network): one row of the band's middle 60 %
alternates dark / bright about its own running mean at least ``min_transitions`` times (two
per glyph stroke; a plate's 5-8 glyphs give 10-24): ``glyph_transitions``. The measure before
(crossings of one Otsu threshold for the band along its three middle rows, at 8) missed a
plate beside its car's dark body or grille, whose thin grey glyphs stayed on the plate's side
of the threshold, and one whose glyphs sat off the band's middle. A glyph row split in two
bands (at its hyphen or emblem) is one band again (``join_bands``); a band over only part
of the glyph row is grown to a plate's text width (``plate_band``). Bands over half
``line_px`` tall (large plates, legible at the scan's scale) keep the Otsu test. The reading
(``plateread.py``) still decides what is a plate: this only decides where the detector looks
closer.
"""

from __future__ import annotations

import cv2
import numpy as np
from numba import njit

from v2xlake.tasks.geometry import merge_until_stable

Band = tuple[float, float, float, float]


def band_pixels(gray: np.ndarray, band: Band) -> np.ndarray:
    """The frame's pixels under a band (x0, y0, x1, y1 px, widened to whole pixels and clipped
    to the frame): what the row tests read."""
    h, w = gray.shape[:2]
    x0, y0 = max(0, int(band[0])), max(0, int(band[1]))
    x1, y1 = min(w, int(np.ceil(band[2]))), min(h, int(np.ceil(band[3])))
    return gray[y0:y1, x0:x1]


def percentiles(a: np.ndarray, qs: tuple[float, ...]) -> list[float]:
    """``np.percentile(a, qs)`` (linear interpolation, numpy's arithmetic: the same values)
    from a partial sort: 8 instead of 160 us on a band, half the cost of ``row_transitions``,
    which runs on every band of every frame (three band passes)."""
    flat = a.ravel()
    n = flat.size
    pos = [q / 100.0 * (n - 1) for q in qs]
    part = np.partition(flat, sorted({min(int(v) + d, n - 1) for v in pos for d in (0, 1)}))
    out = []
    for v in pos:
        lo = int(v)
        t = v - lo
        x, y = float(part[lo]), float(part[min(lo + 1, n - 1)])
        d = y - x
        out.append(y - d * (1 - t) if t >= 0.5 else x + d * t)
    return out


def row_transitions(gray: np.ndarray, band: Band, contrast: float = 0.1) -> np.ndarray:
    """Dark / bright alternations along each row of the band (``gray``: the frame in grey
    levels, ``band``: x0, y0, x1, y1 px): a pixel is dark or bright when it differs from the
    row's running mean over one band height by more than ``contrast`` of the band's grey
    range (5-95 %) plus 2 grey levels; pixels in between keep the last state (hysteresis),
    so noise on a plain patch counts nothing.

    Why a local mean and not one threshold for the band (Otsu, before): a small plate's band
    also holds its car's dark body or grille, and one threshold then splits car from plate
    while the plate's thin, grey-blurred glyphs stay on the bright side (real 40 px plates:
    2-6 crossings where 14 glyph edges are)."""
    core = band_pixels(gray, band).astype(np.float32)
    if core.shape[0] < 1 or core.shape[1] < 2:
        return np.zeros(0, int)
    lo, hi = percentiles(core, (5.0, 95.0))
    dead = contrast * float(hi - lo) + 2.0
    k = max(3, core.shape[0] | 1)
    local = core - cv2.blur(core, (k, 1), borderType=cv2.BORDER_REPLICATE)
    # per row: the sign of each pixel beyond the dead zone, a pixel within it keeping the
    # last one (forward fill along the row); a change between two set states is one
    # alternation (one array operation for the band, not one per row: every band of the
    # frame is tested)
    state = np.where(np.abs(local) > dead, np.sign(local), 0.0)
    cols = np.arange(state.shape[1])
    last = np.maximum.accumulate(np.where(state != 0, cols, 0), axis=1)
    filled = np.take_along_axis(state, last, axis=1)
    return np.count_nonzero((filled[:, 1:] != filled[:, :-1]) & (filled[:, :-1] != 0), axis=1)


def _middle(n: int, share: float) -> slice:
    """The middle ``share`` of ``n`` rows (at least one)."""
    m = round(n * (1 - share) / 2)
    return slice(m, n - m) if n - 2 * m >= 1 else slice(0, n)


def glyph_transitions(gray: np.ndarray, band: Band, contrast: float = 0.1,
                      rows: float = 0.6) -> int:
    """The most alternations (``row_transitions``) along one row of the band's middle
    ``rows`` share: a band of edges is rarely centred on its glyphs (it also holds the
    plate's frame or the grille below), so not only its middle row. A plate's 5-8 glyphs
    give 10-20, a facade edge, a pole or foliage 2-7."""
    t = row_transitions(gray, band, contrast)
    return int(t[_middle(len(t), rows)].max()) if len(t) else 0


def otsu_transitions(gray: np.ndarray, band: Band) -> int:
    """The most crossings of the band's Otsu threshold along one of its three middle rows
    (``gray``: the frame in grey levels, ``band``: x0, y0, x1, y1 px): the test of a band of
    a large plate (``band_scale``), as before ``glyph_transitions``."""
    core = band_pixels(gray, band)
    if core.shape[0] < 1 or core.shape[1] < 2:
        return 0
    t, _ = cv2.threshold(np.ascontiguousarray(core), 0, 255,
                         cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    mid = core.shape[0] // 2
    rows = core[max(0, mid - 1) : mid + 2] > t
    return int(np.abs(np.diff(rows.astype(np.int8), axis=1)).sum(axis=1).max())


def glyph_rows(t: np.ndarray, rows: float = 0.6) -> int:
    """How many rows a band's glyph row spans: the run of rows around the busiest row of the
    middle ``rows`` share whose alternations (``t``: ``row_transitions``) reach half its
    count. A band of edges is often taller than its glyphs (a 40 px plate's 6 px glyphs in
    a 13-15 px band with the plate's frame and the grille below)."""
    if not len(t):
        return 0
    mid = _middle(len(t), rows)
    peak = mid.start + int(np.argmax(t[mid]))
    keep = t >= 0.5 * t[peak]
    lo, hi = peak, peak + 1
    while lo > 0 and keep[lo - 1]:
        lo -= 1
    while hi < len(t) and keep[hi]:
        hi += 1
    return hi - lo


def band_scale(band: Band, gray: np.ndarray, base: float, line_px: float, max_scale: float,
               min_transitions: int, large_min_transitions: int = 8) -> float:
    """The scale to search an edge band at: ``base`` (the plate scan's), or, for a band lower
    than ``line_px`` that holds a row of glyphs, a closer one, at most ``max_scale``
    (``line_px`` 0: always ``base``). A small plate's band (at most half ``line_px`` tall):
    ``glyph_transitions`` at least ``min_transitions``, and the scale that makes its glyph
    row (``glyph_rows`` + 2 px, at least 60 % of the band: the crop costs the square of its
    scale) ``line_px`` tall; real 40 px plates in 13-14 px bands were looked at x2 and
    missed. A taller band (a large plate's, legible already): the test and scale of before,
    ``otsu_transitions`` at least ``large_min_transitions`` and the band ``line_px`` tall
    (plates_eu through the plan lost 2 of 108 when their crops changed), unless its glyph
    row (+2 px) is at most half of it: then the scale that makes the glyph row ``line_px``
    tall (its floor 0.3 ``line_px``), if larger (real 40 px plates in 21-22 px bands with
    the car's lamp or trim were looked at 1-1.3x and missed)."""
    bh = band[3] - band[1]
    if line_px <= 0 or bh * base >= line_px or base >= max_scale:
        return base
    t = row_transitions(gray, band)
    glyphs = bool(len(t)) and int(t[_middle(len(t), 0.6)].max()) >= min_transitions
    if 2 * bh > line_px:
        s = float(min(max_scale, line_px / max(bh, 1.0)))
        if s <= base or otsu_transitions(gray, band) < large_min_transitions:
            s = base
        if not glyphs:
            return s
        # a tall band whose glyph row is a few of its rows (a 40 px plate's 6 px glyphs in a
        # 21-22 px band with the car's lamp or trim): scaled for its glyph row, not the band
        gr = glyph_rows(t) + 2.0
        if gr > 0.5 * bh:
            return s
        return float(max(s, min(max_scale, line_px / max(gr, 0.3 * line_px))))
    if not glyphs:
        return base
    gh = min(bh, max(glyph_rows(t) + 2.0, 0.6 * bh))
    s = float(min(max_scale, line_px / max(gh, 1.0)))
    return s if s > base else base


def plate_band(band: Band, gray: np.ndarray, text_aspect: float, below: float = np.inf) -> Band:
    """A band of a glyph row grown, both sides evenly, to the width of a plate's text
    (``text_aspect`` x its glyph height, ``glyph_rows`` + 1 px) when it is narrower: a small
    plate's band is often only part of its glyph row (the rest touches the bumper's chrome or
    is under the edge threshold), and the crop around that part cuts the plate's other
    glyphs off (read as no plate, or not found). Only bands narrower than ``below`` (px;
    the caller's floor for a line: a band that narrow was dropped, so no crop that found a
    plate changes; growing every upscaled band added a third to the upscaled crops' pixels
    of a street frame, over the plan's budget). ``text_aspect`` 0: the band as it is."""
    if text_aspect <= 0 or band[2] - band[0] >= below:
        return band
    t = row_transitions(gray, band)
    want = text_aspect * (glyph_rows(t) + 1.0)
    w = band[2] - band[0]
    if not len(t) or w >= want:
        return band
    g = 0.5 * (want - w)
    return (max(0.0, band[0] - g), band[1], min(float(gray.shape[1]), band[2] + g), band[3])


def join_bands(bands: list[Band], gap: float = 1.5, max_h: float = 14.0,
               max_w: float = np.inf, max_aspect: float = np.inf) -> list[Band]:
    """The bands of one small glyph row joined: two at most ``max_h`` tall whose union is at
    most 1.5x as tall as the lower one (one row, not a row beside a taller object) and that
    lie at most ``gap`` of that height apart side by side become their union (when it is at
    most ``max_w`` wide and ``max_aspect`` as wide as tall). Why: a small plate's glyph row
    is often two bands, split at its hyphen or emblem, and half a plate cut out is half a
    line (read as no plate, or not found). Larger plates' rows are one band already (60 px
    plates: bands of 13-20 px), and joining them to a neighbour on their row only changes a
    crop that was found (``max_h``)."""

    def union(a: Band, b: Band) -> Band | None:
        hmin = min(a[3] - a[1], b[3] - b[1])
        if max(a[3] - a[1], b[3] - b[1]) > max_h:
            return None
        if max(a[0], b[0]) - min(a[2], b[2]) > gap * hmin:
            return None
        u = (min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3]))
        if (u[3] - u[1] > 1.5 * hmin or u[2] - u[0] > max_w
                or u[2] - u[0] > max_aspect * (u[3] - u[1])):
            return None
        return u

    out = merge_until_stable([(b[0], b[1], b[2], b[3]) for b in bands], union)
    return [(float(b[0]), float(b[1]), float(b[2]), float(b[3])) for b in out]


def short_strokes(mask: np.ndarray, max_px: int) -> np.ndarray:
    """``mask`` (edge pixels, uint8 0 / 1) without its long vertical edges: runs of
    ``max_px`` rows or more, upright or slanted by up to one pixel per row, and the pixels
    beside them. A glyph's strokes are at most a glyph tall; a lamp's outline, a pole, the
    body's or the plate holder's side runs on. Closed horizontally, such an edge a few
    pixels beside a small plate's glyph row joins it into a component far too large for a
    line (a low-contrast plate's glyph row is not among the strongest edges around either,
    so the stricter pass breaks it apart: real 40 px plates pasted into real streets, 4 of
    53 held-out ones had no band). ``max_px`` 0: the mask as it is."""
    if max_px <= 0:
        return mask
    row = np.ones((1, 3), np.uint8)
    thick = cv2.dilate(mask, row)  # a slanted edge keeps an upright run of pixels
    long_ = cv2.dilate(cv2.morphologyEx(thick, cv2.MORPH_OPEN,
                                        np.ones((int(max_px), 1), np.uint8)), row)
    return mask & (1 - long_)


def component_stats(mask: np.ndarray) -> np.ndarray:
    """The components of a binary mask (8-connected) as ``cv2.connectedComponentsWithStats``
    labels them: a row (x, y, w, h, area) per component in label order, the background's
    row left out (int32). Labelled in 16 bits, and in 32 only when a mask has more than
    65,535 components (OpenCV raises then): the label image is most of OpenCV's work at 16
    bits (8 instead of 21 ms per 1920 x 1200 pass at 32), and its statistics most of the
    rest (3.3 ms against 1.0 ms for the labels alone on a 1920 x 1080 frame's edge mask,
    the background's row the costliest), so the components' rows are read off the label
    image in one pass (``label_stats``): the same rows as OpenCV's."""
    try:
        n, lab = cv2.connectedComponents(mask, connectivity=8, ltype=cv2.CV_16U)
    except cv2.error:
        n, lab = cv2.connectedComponents(mask, connectivity=8)
    return label_stats(lab, n)


@njit(cache=True)
def label_stats(lab: np.ndarray, n: int) -> np.ndarray:
    """(x, y, w, h, area) of labels 1 to ``n`` - 1 of a label image (each has a pixel),
    int32."""
    h, w = lab.shape
    x0 = np.full(n, w, np.int64)
    y0 = np.full(n, h, np.int64)
    x1 = np.zeros(n, np.int64)
    y1 = np.zeros(n, np.int64)
    area = np.zeros(n, np.int64)
    for y in range(h):
        for x in range(w):
            k = lab[y, x]
            if k == 0:
                continue
            area[k] += 1
            if x < x0[k]:
                x0[k] = x
            if x > x1[k]:
                x1[k] = x
            if y < y0[k]:
                y0[k] = y
            y1[k] = y
    out = np.empty((max(n - 1, 0), 5), np.int32)
    for k in range(1, n):
        out[k - 1, 0] = x0[k]
        out[k - 1, 1] = y0[k]
        out[k - 1, 2] = x1[k] - x0[k] + 1
        out[k - 1, 3] = y1[k] - y0[k] + 1
        out[k - 1, 4] = area[k]
    return out


def edge_bands(gx: np.ndarray, threshold: float, h_range: tuple[float, float],
               w_range: tuple[float, float], aspect: tuple[float, float], fill: float,
               join_gap: float = 1.5, max_stroke: int = 0) -> list[Band]:
    """Bands of dense vertical edges in ``gx`` (|Sobel x|, grey levels) at ``threshold``:
    edges closed horizontally (3 x 9) and opened (3 x 3), components of a text line's
    height, width, aspect (px) and ``fill`` of their box, those of one line joined
    (``join_bands``, ``join_gap`` of their height apart at most; 0: not joined).
    ``max_stroke`` > 0: vertical edges of that many rows or more dropped first
    (``short_strokes``), and only bands at most 2 px taller kept: what is left are strokes
    lower than that, and a band taller than its glyphs and the closing's row each side is
    rows of them stacked (foliage, gravel, a grille: on the real street frames 2 in 3 of
    the bands this pass added, each a closer look, over the plan's crop budget)."""
    m0 = short_strokes((gx >= threshold).astype(np.uint8), max_stroke)
    if max_stroke > 0:
        h_range = (h_range[0], min(h_range[1], max_stroke + 2.0))
    m1 = cv2.morphologyEx(m0, cv2.MORPH_CLOSE, np.ones((3, 9), np.uint8))
    m2 = cv2.morphologyEx(m1, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    stats = component_stats(m2)
    (hlo, hhi), (wlo, whi), (alo, ahi) = h_range, w_range, aspect
    bands = [(float(x), float(y), float(x + bw), float(y + bh))
             for x, y, bw, bh, area in stats.tolist()
             if hlo <= bh <= hhi and wlo <= bw <= whi and alo <= bw / bh <= ahi
             and area >= fill * bw * bh]
    if join_gap <= 0:
        return bands
    return join_bands(bands, join_gap, max_w=whi, max_aspect=ahi)


def keep_within(area: list[float], rank: list[float], budget: float) -> list[bool]:
    """Which crops to keep when their pixels (``area``) are over ``budget``: every crop of
    infinite ``rank``, then the others by ``rank`` (a band's glyph alternations), most
    first, while the total stays within ``budget``. Why: over budget the plan searched only
    the whole frame at its own scale, which finds no plate under ~60 px: a real street frame
    with three or five cars' fronts pasted in (their grilles and lettering make bands) kept
    1 of their 40 px plates (each car alone: found); with the closer looks of the most
    glyph-like bands kept too, 3 of 3 and 4 of 5."""
    keep = [bool(np.isinf(r)) for r in rank]
    total = float(sum(a for a, k in zip(area, keep, strict=True) if k))
    for i in sorted((i for i, k in enumerate(keep) if not k), key=lambda i: -rank[i]):
        if total + area[i] <= budget:
            keep[i] = True
            total += area[i]
    return keep


def to_gray(image: np.ndarray) -> np.ndarray:
    """The frame in grey levels (BGR or already grey)."""
    return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image


def is_dark(image: np.ndarray, median_below: float) -> bool:
    """Is the frame dark: its median grey level (every 4th pixel, each way) under
    ``median_below`` (0: never)? Why the median: a night frame's street lights and lit
    plates are bright, but few; the mean follows them, the median follows the street."""
    if median_below <= 0:
        return False
    return float(np.median(to_gray(np.ascontiguousarray(image[::4, ::4])))) < median_below


def lift_dark(image: np.ndarray, ref: float, gain_max: float, window: int = 31) -> np.ndarray:
    """The frame lifted locally: each pixel (all channels) scaled by ``ref`` / the mean grey
    level of the ``window`` x ``window`` px around it, clipped to [1, ``gain_max``]. Why local
    and not a global gamma: in a night frame the plate under a street light is bright and the
    one in the shadow is dark; one gain for both either saturates the first or leaves the
    second under the edge threshold. Bright places (a mean at ``ref`` or above) keep their
    pixels; the gain varies with the blurred mean, so it adds no edges of its own."""
    mean = cv2.blur(to_gray(image), (window, window)).astype(np.float32)
    gain = np.clip(ref / np.maximum(mean, 1.0), 1.0, gain_max)
    if image.ndim == 3:
        gain = gain[..., None]
    return np.clip(image.astype(np.float32) * gain, 0, 255).astype(np.uint8)


def row_texture(along: np.ndarray, x: int, y: int, w: int, h: int) -> tuple[float, float | None]:
    """Of a small plate box (x, y, w, h px) on ``along`` (|grey level change| along the rows
    of an upscaled band): the mean change over its middle half of rows and middle 80 % of
    columns (its glyphs, even blurred), and over the rows as tall as it above and below (the
    body around it; None where there are none). A plate's glyphs change more than its
    car's body; a curb's edge or a bumper's highlight does not."""
    mid = along[y + h // 4 : y + h - h // 4, x + w // 10 : x + w - w // 10 - 1]
    near = np.concatenate([along[max(0, y - h) : y, x : x + w - 1].ravel(),
                           along[y + h : y + 2 * h, x : x + w - 1].ravel()])
    return (float(mid.mean()) if mid.size else 0.0), (float(near.mean()) if near.size else None)
