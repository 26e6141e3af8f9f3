"""A small raster plotter for the register stage's two PNGs (the BEV and the timeline).

Why not matplotlib: the stage renders both pictures for every clip, and matplotlib spent
0.3-0.45 s of one core on the BEV (scatter of 120k points) and 0.4-1.2 s on the timeline
(ten axes' ticks, grid lines and labels), a fixed cost as large as registering a whole 3 s
clip. Here a picture is a NumPy RGB array: points are counted into pixels (``splat``, one
compiled counting pass per layer), lines, markers and bands are drawn anti-aliased by
OpenCV into views of the array (a view clips to its panel), text is drawn last by Pillow with
FreeType (DejaVu Sans, matplotlib's font, when matplotlib's data is installed) and the PNG is
written by ``pngcodec`` (rows filtered with UP, ISA-L deflate).

Coordinates: pixels, x to the right, y down; a ``Panel`` maps data coordinates into its box.
"""

from __future__ import annotations

import importlib.util
import math
from dataclasses import dataclass, field
from functools import cache, lru_cache
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numba import njit

from v2xlake.tasks.pngcodec import encode_png

Color = tuple[int, int, int]
_SHIFT = 4  # OpenCV's fractional bits: coordinates are drawn to 1/16 px
_ONE = 1 << _SHIFT
MINUS = "\u2212"


def rgb(hex_colour: str) -> Color:
    """``#rrggbb`` as an (r, g, b) tuple."""
    h = hex_colour.lstrip("#")
    return int(h[0:2], 16), int(h[2:4], 16), int(h[4:6], 16)


@cache
def _font_path() -> str | None:
    """matplotlib's DejaVu Sans (the font the pictures had) found without importing
    matplotlib (0.6 s); None: Pillow's own font."""
    spec = importlib.util.find_spec("matplotlib")
    if spec is None or spec.origin is None:
        return None
    p = Path(spec.origin).parent / "mpl-data" / "fonts" / "ttf" / "DejaVuSans.ttf"
    return str(p) if p.exists() else None


@cache
def font(px: int) -> Any:
    """A FreeType font ``px`` pixels high (em size)."""
    from PIL import ImageFont

    path = _font_path()
    if path is not None:
        return ImageFont.truetype(path, px)
    return ImageFont.load_default(size=px)


def text_width(s: str, px: int) -> float:
    """Advance width of ``s`` in pixels at ``px``."""
    return float(font(px).getlength(s))


def nice_ticks(lo: float, hi: float, max_ticks: int = 8) -> np.ndarray:
    """Round tick values inside [lo, hi]: the smallest step of 1, 2, 2.5 or 5 x 10^k giving
    at most ``max_ticks`` ticks (matplotlib's default locator picks from the same steps)."""
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
        return np.array([lo]) if math.isfinite(lo) else np.zeros(0)
    raw = (hi - lo) / max(max_ticks - 1, 1)
    mag = 10.0 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1.0, 2.0, 2.5, 5.0, 10.0) if m * mag >= raw * (1 - 1e-9))
    first = math.ceil(lo / step - 1e-9)
    last = math.floor(hi / step + 1e-9)
    return np.arange(first, last + 1) * step


def tick_labels(ticks: np.ndarray) -> list[str]:
    """Labels with as many decimals as the step needs (0.25 steps: two), minus signs as
    U+2212 and no "-0"."""
    if len(ticks) < 2:
        dec = 0 if len(ticks) == 0 or float(ticks[0]).is_integer() else 2
    else:
        step = abs(float(ticks[1] - ticks[0]))
        dec = 0
        while dec < 6 and abs(step * 10**dec - round(step * 10**dec)) > 1e-6 * 10**dec:
            dec += 1
    out = []
    for v in ticks:
        s = f"{float(v):.{dec}f}"
        if float(s) == 0.0:
            s = s.lstrip("-")
        out.append(s.replace("-", MINUS))
    return out


def limits(values: list[np.ndarray], margin: float = 0.05) -> tuple[float, float]:
    """Data limits of the finite values with ``margin`` of the range on each side
    (matplotlib's default view margins); a flat or empty range gets +-1 or +-5 %."""
    v = np.concatenate([np.ravel(np.asarray(x, dtype=np.float64)) for x in values]) \
        if values else np.zeros(0)
    v = v[np.isfinite(v)]
    if not len(v):
        return -1.0, 1.0
    lo, hi = float(v.min()), float(v.max())
    if hi - lo <= 1e-12 * max(abs(lo), abs(hi), 1e-300):
        d = abs(lo) * 0.05 if lo else 1.0
        return lo - d, hi + d
    d = (hi - lo) * margin
    return lo - d, hi + d


def splat(img: np.ndarray, col: np.ndarray, row: np.ndarray, color: Color,
          alpha: float) -> None:
    """Points at pixel (``col``, ``row``) (floats, truncated to their pixel) composited onto
    ``img`` (H, W, 3 uint8) in place: a pixel hit by n points of this colour gets opacity
    1 - (1 - alpha)^n, as n overlapping markers of opacity ``alpha`` would. Points outside
    the image are dropped."""
    # the opacity of n points, by table (beyond 255 points a pixel is opaque anyway)
    opacity = (1.0 - (1.0 - alpha) ** np.arange(256)).astype(np.float32)
    _splat_kernel(img, np.asarray(col, np.float64).reshape(-1),
                  np.asarray(row, np.float64).reshape(-1), np.asarray(color, np.float32),
                  opacity)


@njit(cache=True, nogil=True)
def _splat_kernel(img: np.ndarray, col: np.ndarray, row: np.ndarray, color: np.ndarray,
                  opacity: np.ndarray) -> None:
    """:func:`splat`'s counting and compositing in one compiled pass each, with the
    operations its NumPy form took (a pixel's float32 value moved toward the colour by the
    opacity of its count, rounded half to even, clipped): the same pixels. WHY: the
    ``bincount`` over every pixel of the panel, its ``flatnonzero`` and the fancy-indexed
    gathers took ~1 ms a layer, eight layers a BEV."""
    h, w = img.shape[0], img.shape[1]
    n = np.zeros(h * w, dtype=np.int64)
    hit = np.empty(len(col), dtype=np.int64)  # the pixels hit, each once
    m = 0
    for i in range(len(col)):
        c, r = col[i], row[i]
        if c >= 0 and c < w and r >= 0 and r < h:
            k = int(r) * w + int(c)
            if n[k] == 0:
                hit[m] = k
                m += 1
            n[k] += 1
    for e in range(m):
        k = hit[e]
        a = opacity[min(n[k], 255)]
        rr, cc = k // w, k % w
        for ch in range(3):
            px = np.float32(img[rr, cc, ch])
            px += (color[ch] - px) * a
            img[rr, cc, ch] = np.uint8(min(max(np.rint(px), np.float32(0.0)), np.float32(255.0)))


def _fixed(pts: np.ndarray) -> np.ndarray:
    """Pixel points as OpenCV's fixed-point (N, 1, 2) int32 at ``_SHIFT`` fractional bits."""
    return np.rint(np.asarray(pts, np.float64) * _ONE).astype(np.int32).reshape(-1, 1, 2)


@dataclass
class _Text:
    x: float
    y: float
    s: str
    px: int
    color: Color
    anchor: str
    rotate: bool


@dataclass
class Canvas:
    """A white RGB picture of ``width`` x ``height`` pixels; ``png`` draws the queued text
    and encodes it."""

    width: int
    height: int
    img: np.ndarray = field(init=False)
    texts: list[_Text] = field(default_factory=list, init=False)

    def __post_init__(self) -> None:
        self.img = np.full((self.height, self.width, 3), 255, np.uint8)

    def text(self, x: float, y: float, s: str, px: int, *, color: Color = (0, 0, 0),
             anchor: str = "mm", rotate: bool = False) -> None:
        """Queue ``s`` at (x, y) with Pillow's ``anchor`` (e.g. "mm" centre, "rm" right
        middle, "mt" middle top); ``rotate``: turned 90 degrees counter-clockwise, anchored
        at its centre."""
        if s:
            self.texts.append(_Text(x, y, s, px, color, anchor, rotate))

    def rect(self, x0: float, y0: float, x1: float, y1: float, color: Color, *,
             fill: Color | None = None, width: int = 1) -> None:
        """An axis-aligned rectangle's outline (and its fill)."""
        a, b = round(x0), round(y0)
        c, d = round(x1), round(y1)
        if fill is not None:
            self.img[max(b, 0):max(d, 0), max(a, 0):max(c, 0)] = fill
        cv2.rectangle(self.img, (a, b), (c, d), color, width, cv2.LINE_8)

    def png(self, path: str | Path | None = None) -> bytes:
        """The picture with its text as PNG bytes (also written to ``path`` if given)."""
        for t in self.texts:
            mask, x0, y0 = _text_mask(t)
            _ink(self.img, mask, x0, y0, t.color)
        data = encode_png(cv2.cvtColor(self.img, cv2.COLOR_RGB2BGR))
        if path is not None:
            Path(path).write_bytes(data)
        return data


def _text_mask(t: _Text) -> tuple[np.ndarray, int, int]:
    """The text's coverage (uint8, FreeType anti-aliased) and where its top left goes. Each
    string is drawn into its own small image: converting the whole picture to Pillow and
    back cost more than the text (20 ms of a 2200 x 1200 timeline)."""
    m, left, top = _glyphs(t.s, t.px, t.anchor, t.rotate)
    if t.rotate:
        return m, round(t.x - m.shape[1] / 2), round(t.y - m.shape[0] / 2)
    return m, round(t.x) + left, round(t.y) + top


@lru_cache(maxsize=1024)
def _glyphs(s: str, px: int, anchor: str, rotate: bool) -> tuple[np.ndarray, int, int]:
    """A string's coverage (read-only) and its top left relative to the anchor point (0, 0
    when ``rotate``: centred there). WHY: the two pictures of a clip draw about a hundred
    labels, most of them (tick values, legends, axis names) the same from clip to clip, and
    FreeType drew each again: about 1 % of a 3 s clip's register stage."""
    from PIL import Image, ImageDraw

    f = font(px)
    if rotate:
        box = f.getbbox(s, anchor="lt")
        tile = Image.new("L", (int(box[2]) + 2, int(box[3]) + 2), 0)
        ImageDraw.Draw(tile).text((1, 1), s, fill=255, font=f, anchor="lt")
        m = np.ascontiguousarray(np.rot90(np.asarray(tile)))  # counter-clockwise, upwards
        left = top = 0
    else:
        left, top, right, bottom = (int(v) for v in f.getbbox(s, anchor=anchor))
        tile = Image.new("L", (right - left + 1, bottom - top + 1), 0)
        ImageDraw.Draw(tile).text((-left, -top), s, fill=255, font=f, anchor=anchor)
        m = np.array(tile)
    m.flags.writeable = False
    return m, left, top


def _ink(img: np.ndarray, mask: np.ndarray, x0: int, y0: int, color: Color) -> None:
    """``color`` laid onto ``img`` with coverage ``mask`` (uint8) at (x0, y0), clipped."""
    h, w = img.shape[:2]
    a0, b0 = max(x0, 0), max(y0, 0)
    a1, b1 = min(x0 + mask.shape[1], w), min(y0 + mask.shape[0], h)
    if a1 <= a0 or b1 <= b0:
        return
    _blend(img[b0:b1, a0:a1], mask[b0 - y0:b1 - y0, a0 - x0:a1 - x0], 1.0, color)


def _blend(v: np.ndarray, mask: np.ndarray, alpha: float, color: Color) -> None:
    """``color`` composited onto the pixels ``v`` (a view, in place) with opacity ``alpha``
    times the coverage ``mask`` (uint8, 255 full): v (1 - w) + colour w, rounded."""
    wgt = mask.astype(np.float32) * np.float32(alpha / 255.0)
    ink = np.empty_like(v)
    ink[:] = color
    v[...] = cv2.blendLinear(v, ink, 1.0 - wgt, wgt)


def _runs(ok: np.ndarray) -> list[tuple[int, int]]:
    """[start, stop) of each run of at least two consecutive True values: the pieces a line
    or band is drawn in (a non-finite value splits it, as in matplotlib)."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], ok.astype(np.int8), [0]])))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2], strict=True) if b - a >= 2]


def _polyline(img: np.ndarray, origin: tuple[float, float], pts: np.ndarray, color: Color,
              width: float) -> None:
    """Segments between consecutive finite points, drawn into ``img`` (a view: clipped)."""
    if len(pts) < 2:
        return
    p = pts - np.asarray(origin)[None, :]
    runs = [_fixed(p[a:b]) for a, b in _runs(np.isfinite(pts).all(axis=1))]
    if runs:
        cv2.polylines(img, runs, False, color, max(round(width), 1), cv2.LINE_AA, _SHIFT)


def _marker(img: np.ndarray, x: float, y: float, kind: str, size: float,
            color: Color) -> None:
    """One filled, anti-aliased marker of ``size`` pixels centred at (x, y) in ``img``: "o"
    disc, "^" triangle, "|" vertical bar (the timeline's decision strip)."""
    if not (math.isfinite(x) and math.isfinite(y)):
        return
    if kind == "o":
        cv2.circle(img, (round(x * _ONE), round(y * _ONE)),
                   round(size / 2 * _ONE), color, -1, cv2.LINE_AA, _SHIFT)
    elif kind == "^":
        r = size / 2
        tri = np.array([[x, y - r], [x + r * 0.866, y + r / 2], [x - r * 0.866, y + r / 2]])
        cv2.fillPoly(img, [_fixed(tri)], color, cv2.LINE_AA, _SHIFT)
    elif kind == "|":
        cv2.line(img, (round(x * _ONE), round((y - size / 2) * _ONE)),
                 (round(x * _ONE), round((y + size / 2) * _ONE)), color, 2,
                 cv2.LINE_AA, _SHIFT)
    else:
        raise ValueError(f"unknown marker {kind!r}")


@dataclass
class Panel:
    """An axes box (pixels, right / bottom exclusive) showing ``xlim`` x ``ylim``."""

    canvas: Canvas
    x0: int
    y0: int
    x1: int
    y1: int
    xlim: tuple[float, float]
    ylim: tuple[float, float]
    # (x ticks, y ticks, x labels shown, y labels shown, label size), set by ``axes``
    ticks: tuple[np.ndarray, np.ndarray, bool, bool, int] | None = None

    @property
    def view(self) -> np.ndarray:
        """The panel's pixels (a view of the canvas): drawing into it clips to the box."""
        return self.canvas.img[self.y0:self.y1, self.x0:self.x1]

    def px(self, x: Any, y: Any) -> tuple[np.ndarray, np.ndarray]:
        """Canvas pixel coordinates of data points."""
        x = np.asarray(x, np.float64)
        y = np.asarray(y, np.float64)
        sx = (self.x1 - self.x0) / (self.xlim[1] - self.xlim[0])
        sy = (self.y1 - self.y0) / (self.ylim[1] - self.ylim[0])
        return self.x0 + (x - self.xlim[0]) * sx, self.y1 - (y - self.ylim[0]) * sy

    def points(self, x: np.ndarray, y: np.ndarray, color: Color, alpha: float) -> None:
        """Many small points counted into pixels (``splat``)."""
        cx, cy = self.px(x, y)
        splat(self.view, cx - self.x0, cy - self.y0, color, alpha)

    def line(self, x: Any, y: Any, color: Color, width: float = 1.0) -> None:
        cx, cy = self.px(x, y)
        _polyline(self.view, (self.x0, self.y0), np.stack([cx, cy], axis=1), color, width)

    def hline(self, y: float, color: Color, width: float = 1.0) -> None:
        self.line(self.xlim, (y, y), color, width)

    def markers(self, x: Any, y: Any, kind: str, size: float, color: Color) -> None:
        cx, cy = self.px(x, y)
        for a, b in zip(np.atleast_1d(cx).tolist(), np.atleast_1d(cy).tolist(), strict=True):
            _marker(self.view, a - self.x0, b - self.y0, kind, size, color)

    def band(self, x: np.ndarray, lo: np.ndarray, hi: np.ndarray, color: Color,
             alpha: float) -> None:
        """The area between ``lo`` and ``hi`` over ``x`` (fill_between), anti-aliased edges,
        composited with opacity ``alpha``; columns with non-finite bounds split the band."""
        ok = np.isfinite(x) & np.isfinite(lo) & np.isfinite(hi)
        mask = np.zeros(self.view.shape[:2], np.uint8)
        for a, b in _runs(ok):
            xs = np.concatenate([x[a:b], x[a:b][::-1]])
            ys = np.concatenate([hi[a:b], lo[a:b][::-1]])
            cx, cy = self.px(xs, ys)
            poly = np.stack([cx - self.x0, cy - self.y0], axis=1)
            cv2.fillPoly(mask, [_fixed(poly)], 255, cv2.LINE_AA, _SHIFT)
        rows = np.flatnonzero(mask.any(axis=1))
        if not len(rows):
            return
        cols = np.flatnonzero(mask.any(axis=0))
        sl = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))
        _blend(self.view[sl], mask[sl], alpha, color)

    def axes(self, *, xticks: np.ndarray | None = None, yticks: np.ndarray | None = None,
             xlabels: bool = True, ylabels: bool = True, grid: bool = False,
             tick_px: int = 14) -> None:
        """Grid (under the data: call first), then call ``frame`` after the data."""
        xt = nice_ticks(*self.xlim) if xticks is None else xticks
        yt = nice_ticks(*self.ylim, max_ticks=6) if yticks is None else yticks
        self.ticks = (xt, yt, xlabels, ylabels, tick_px)
        if grid:
            g = (235, 235, 235)
            for v in xt:
                cx = self._col(v)
                cv2.line(self.canvas.img, (cx, self.y0), (cx, self.y1 - 1), g, 1)
            for v in yt:
                cy = self._row(v)
                cv2.line(self.canvas.img, (self.x0, cy), (self.x1 - 1, cy), g, 1)

    def _col(self, x: float) -> int:
        return round(float(self.px(x, 0.0)[0]))

    def _row(self, y: float) -> int:
        return round(float(self.px(0.0, y)[1]))

    def frame(self) -> None:
        """The box, its outward ticks and their labels (as set by ``axes``)."""
        if self.ticks is None:
            self.axes()
        assert self.ticks is not None
        xt, yt, xlabels, ylabels, tick_px = self.ticks
        c = self.canvas
        k = (0, 0, 0)
        cv2.rectangle(c.img, (self.x0 - 1, self.y0 - 1), (self.x1, self.y1), k, 1)
        for v, s in zip(xt, tick_labels(xt), strict=True):
            cx = self._col(v)
            cv2.line(c.img, (cx, self.y1), (cx, self.y1 + 4), k, 1)
            if xlabels:
                c.text(cx, self.y1 + 6, s, tick_px, anchor="mt")
        for v, s in zip(yt, tick_labels(yt), strict=True):
            cy = self._row(v)
            cv2.line(c.img, (self.x0 - 5, cy), (self.x0 - 1, cy), k, 1)
            if ylabels:
                c.text(self.x0 - 8, cy, s, tick_px, anchor="rm")

    def ylabel(self, s: str, px: int) -> None:
        """``s`` turned upright, left of the y tick labels."""
        if self.ticks is None:
            self.axes()
        assert self.ticks is not None
        _, yt, _, shown, tick_px = self.ticks
        w = max((text_width(x, tick_px) for x in tick_labels(yt)), default=0.0) if shown else 0
        self.canvas.text(self.x0 - 8 - w - 4 - px * 0.6, (self.y0 + self.y1) / 2, s, px,
                         rotate=True)

    def legend(self, entries: list[tuple[str, str, Color]], px: int, *,
               where: str = "upper right", ncol: int = 1,
               at: tuple[float, float] | None = None) -> None:
        """A framed legend of (kind, label, colour) entries, kind "line", "dot", "patch"
        (a light square) or "|"; ``where`` "upper right" inside the panel, or ``at`` a canvas
        point (the legend's top centre)."""
        if not entries:
            return
        c = self.canvas
        ncol = max(min(ncol, len(entries)), 1)
        pad, sw, gap, row = px * 0.5, px * 2.0, px * 0.6, px * 1.45
        widths = [sw + gap + text_width(s, px) for _, s, _ in entries]
        nrow = math.ceil(len(entries) / ncol)
        colw = [max(widths[i::ncol]) for i in range(ncol)]
        w = sum(colw) + pad * (ncol + 1)
        h = nrow * row + pad
        if at is not None:
            x0, y0 = at[0] - w / 2, at[1]
        else:
            x0, y0 = self.x1 - w - px * 0.5, self.y0 + px * 0.5
        c.rect(x0, y0, x0 + w, y0 + h, (204, 204, 204), fill=(255, 255, 255))
        for i, (kind, label, col) in enumerate(entries):
            r, j = divmod(i, ncol)
            ex = x0 + pad + sum(colw[:j]) + pad * j
            ey = y0 + pad / 2 + r * row + row / 2
            if kind == "line":
                _polyline(c.img, (0.0, 0.0), np.array([[ex, ey], [ex + sw, ey]]), col, 1.5)
            elif kind == "hline":
                _polyline(c.img, (0.0, 0.0), np.array([[ex, ey], [ex + sw, ey]]), col, 1.0)
            elif kind == "dot":
                _marker(c.img, ex + sw / 2, ey, "o", px * 0.45, col)
            elif kind == "patch":
                c.rect(ex, ey - px * 0.35, ex + sw, ey + px * 0.35, col, fill=col)
            elif kind == "|":
                _marker(c.img, ex + sw / 2, ey, "|", row * 0.9, col)
            c.text(ex + sw + gap, ey, label, px, anchor="lm")
