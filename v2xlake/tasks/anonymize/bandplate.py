"""A small learned scorer for plates too small for text (the far band's 18-32 px plates).

Why: a real 20 px plate is about 20 x 4 px; its glyphs blur into the plate, the text detector
barely responds to it, and the band's plate-blob test (``guided.band_plate_blobs``) needs it
brighter than its car, which a plate on a white or silver car is not (there it is a grey,
textured rectangle with a dark rim), nor one whose light area joins a chrome bumper. A linear
classifier on oriented-gradient and local-contrast cells of a window around a plate sees both
the rim and the texture, whatever the body's colour.

The classifier is trained only on synthetic plates (EU-style 520 x 112 mm plates with random
characters in DejaVu Sans, on rendered car rears) and on negatives from photos that ship with
scikit-image and matplotlib (``scripts/train_band_plates.py`` makes ``bandplate.npz`` beside
this module, deterministically); real plate photos are never its training data.

Scoring is dense and linear: the band is rescaled so a plate of one width in the pyramid is
``PLATE_PX`` wide, cell features are computed once on a grid of ``STRIDE`` px, and the
window score at every grid point is a sum of correlations, one per feature channel (no
window is cut out). A second stage (``second_score``, the same file's ``w2``, ``b2``) rates
a window's row and column profiles, for a window whose glyphs the texture test cannot see.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Sequence
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np
from numba import njit

from v2xlake.tasks.anonymize.plateprop import row_texture
from v2xlake.tasks.geometry import greedy_boxes

CELL = 4  # px at the canonical scale
STRIDE = 2  # grid step (px at the canonical scale)
WIN_CELLS = (5, 12)  # rows, columns of cells in a window
PLATE_PX = 32.0  # the plate's width in a window (canonical px)
PLATE_ASPECT = 520.0 / 112.0
BINS = 9
CHANNELS = BINS + 1  # orientation bins + local contrast
WIDTHS = (20.0, 26.5)  # plate widths scored (frame px), each +-15 % in training
WEIGHTS = Path(__file__).with_name("bandplate.npz")


def window_px() -> tuple[int, int]:
    """A window's height and width in canonical px."""
    return WIN_CELLS[0] * CELL, WIN_CELLS[1] * CELL


def plate_in_window() -> tuple[float, float, float, float]:
    """Where a plate sits in a window (x0, y0, x1, y1 canonical px): centred."""
    wh, ww = window_px()
    ph = PLATE_PX / PLATE_ASPECT
    return ((ww - PLATE_PX) / 2, (wh - ph) / 2, (ww + PLATE_PX) / 2, (wh + ph) / 2)


def cell_features(gray: np.ndarray) -> np.ndarray:
    """Cell features of a grey image (canonical scale) on a grid of ``STRIDE`` px: for the
    ``CELL`` x ``CELL`` cell whose corner is at each grid point, the square roots of its
    gradient magnitudes per unsigned orientation bin (soft-binned), each pixel's magnitude
    divided by the gradient energy of the 12 x 12 px around it (so a plate on a dim car
    scores as one on a bright car), and its mean grey level against the 24 x 24 px around it
    in that area's standard deviations. Shape (rows, cols, ``CHANNELS``), float32."""
    g = gray.astype(np.float32)
    h, w = g.shape
    rows, cols = (h - CELL) // STRIDE + 1, (w - CELL) // STRIDE + 1
    out = np.empty((max(rows, 0), max(cols, 0), CHANNELS), np.float32)
    if rows <= 0 or cols <= 0:
        return out
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=1)
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=1)
    mag, ang = cv2.cartToPolar(gx, gy, angleInDegrees=True)
    energy = cv2.boxFilter(mag * mag, -1, (12, 12))
    _orientation_cells(mag, ang, energy, out)
    a = 0  # boxFilter's anchor: the cell [p, p + CELL) lands at p
    mean = cv2.boxFilter(g, -1, (24, 24))
    sq = cv2.boxFilter(g * g, -1, (24, 24))
    zc = cv2.boxFilter(_local_z(g, mean, sq), -1, (CELL, CELL), anchor=(a, a),
                       borderType=cv2.BORDER_REPLICATE)
    out[..., BINS] = np.clip(zc[: rows * STRIDE : STRIDE, : cols * STRIDE : STRIDE], -3, 3)
    return out


@njit(cache=True)
def _orientation_cells(mag: np.ndarray, ang: np.ndarray, energy: np.ndarray,
                       out: np.ndarray) -> None:
    """``cell_features``' orientation channels into ``out[..., :BINS]``, from the gradient
    magnitudes and angles (degrees) and the 12 x 12 px gradient energy (float32): each
    pixel's magnitude divided by ``sqrt(energy + 16)``, soft-binned into the two nearest of
    ``BINS`` unsigned orientations, summed over 2 x 2 px blocks in float64, and each 4 x 4
    cell at a 2 px step the square root of the sum of its four blocks (float32).

    One pass where NumPy took a dozen (an int64 modulo, index arrays, two ``np.bincount``
    over float64 copies of the weights): every value is rounded as NumPy rounded it (float32
    steps, the blocks' sums in float64 in the pixels' raster order, as ``np.bincount``
    added them), so the features are bit for bit the same."""
    rows, cols = out.shape[0], out.shape[1]
    h2, w2 = rows + 1, cols + 1
    half = np.float32(180.0)
    per = np.float32(BINS / 180.0)
    shift = np.float32(0.5)
    one = np.float32(1.0)
    sixteen = np.float32(16.0)
    # two rows of blocks at a time: a row of cells is read off the block row above it and
    # the one being summed
    above = np.zeros((w2, BINS), np.float32)
    blk = np.zeros((w2, BINS), np.float32)
    lo_sum = np.zeros(BINS, np.float64)
    hi_sum = np.zeros(BINS, np.float64)
    for bi in range(h2):
        for bj in range(w2):
            lo_sum[:] = 0.0
            hi_sum[:] = 0.0
            for y in range(2 * bi, 2 * bi + 2):
                for x in range(2 * bj, 2 * bj + 2):
                    m = mag[y, x] / np.sqrt(energy[y, x] + sixteen)
                    a = ang[y, x]
                    if a >= half:
                        a = a - half
                    a = a * per - shift
                    lo = np.floor(a)
                    f = a - lo
                    # the bin modulo ``BINS`` as NumPy's (floor) modulo: ``a`` is in
                    # [-0.5, 8.5], ``lo`` -1 to 8 (no integer division in the loop)
                    k = int(lo)
                    if k < 0:
                        k += BINS
                    elif k >= BINS:
                        k -= BINS
                    kh = k + 1 if k + 1 < BINS else 0
                    lo_sum[k] += np.float64(m * (one - f))
                    hi_sum[kh] += np.float64(m * f)
            for b in range(BINS):
                blk[bj, b] = np.float32(lo_sum[b] + hi_sum[b])
        if bi > 0:
            i = bi - 1
            for j in range(cols):
                for b in range(BINS):
                    out[i, j, b] = np.sqrt(above[j, b] + blk[j, b] + above[j + 1, b]
                                           + blk[j + 1, b])
        above, blk = blk, above


@njit(cache=True)
def _local_z(g: np.ndarray, mean: np.ndarray, sq: np.ndarray) -> np.ndarray:
    """Each pixel's grey level against the 24 x 24 px around it (``mean``, ``sq``: the box
    means of ``g`` and ``g * g``), in that area's standard deviations (+8): float32, rounded
    step by step as NumPy's float32 expression did."""
    out = np.empty_like(g)
    zero = np.float32(0.0)
    eight = np.float32(8.0)
    for y in range(g.shape[0]):
        for x in range(g.shape[1]):
            mu = mean[y, x]
            v = sq[y, x] - mu * mu
            out[y, x] = (g[y, x] - mu) / (np.sqrt(max(v, zero)) + eight)
    return out


def window_at(feats: np.ndarray, i: int = 0, j: int = 0) -> np.ndarray:
    """The feature vector of the window whose top-left corner is grid point (``i``, ``j``) of
    ``feats`` (``cell_features``): its cells, one every ``CELL`` px, flattened (rows,
    columns, channels). What ``score_map`` scores there, and what training fits."""
    step = CELL // STRIDE
    r, c = WIN_CELLS
    return feats[i : i + r * step : step, j : j + c * step : step].reshape(-1)


def score_map(feats: np.ndarray, w: np.ndarray, bias: float) -> np.ndarray:
    """The linear score of the window whose top-left corner is at each grid point of
    ``feats`` (``cell_features``); ``w`` shaped (rows, cols, ``CHANNELS``) of cells."""
    step = CELL // STRIDE
    r, c = WIN_CELLS
    hs, ws = feats.shape[0] - (r - 1) * step, feats.shape[1] - (c - 1) * step
    if hs <= 0 or ws <= 0:
        return np.zeros((0, 0), np.float32)
    # the cells of a window are ``step`` grid points apart, so the windows whose corners
    # share a row and column phase (i % step, j % step) read one sub-grid only: per phase
    # and channel one correlation of that sub-grid with the window's dense weights (r x c
    # taps), anchored at the kernel's corner. The same sums as one correlation of the full
    # grid with the weights spread out ``step`` apart, at a quarter of the multiplications
    # (the scorer's dense part: 0.087 -> ~0.03 CPU s per narrow-camera band)
    # (each phase's sub-grid copied once, channels first, and its sums kept contiguous: the
    # same correlations and the same additions in the same order)
    out = np.full((hs, ws), bias, np.float32)
    taps = [np.ascontiguousarray(w[..., ch]) for ch in range(feats.shape[2])]
    for pi in range(step):
        for pj in range(step):
            ni, nj = len(range(pi, hs, step)), len(range(pj, ws, step))
            if ni <= 0 or nj <= 0:
                continue
            sub = np.ascontiguousarray(feats[pi::step, pj::step].transpose(2, 0, 1))
            acc = np.full((ni, nj), bias, np.float32)
            for ch in range(feats.shape[2]):
                full = cv2.filter2D(sub[ch], -1, taps[ch], anchor=(0, 0),
                                    borderType=cv2.BORDER_CONSTANT)
                acc += full[:ni, :nj]
            out[pi::step, pj::step] = acc
    return out


@lru_cache(maxsize=4)
def weights_version(path: str = str(WEIGHTS)) -> str:
    """``bandplate-sha256:<12 hex>`` of the weights file: a retrained scorer blurs different
    boxes at the same settings, so the stage's provenance string names the weights too."""
    return f"bandplate-sha256:{hashlib.sha256(Path(path).read_bytes()).hexdigest()[:12]}"


@lru_cache(maxsize=4)
def load_weights(path: str = str(WEIGHTS)) -> tuple[np.ndarray, float]:
    """The shipped classifier: cell weights (rows, cols, ``CHANNELS``) and bias."""
    with np.load(path) as z:
        return z["w"].astype(np.float32).reshape(*WIN_CELLS, CHANNELS), float(z["b"])


@lru_cache(maxsize=4)
def load_second(path: str = str(WEIGHTS)) -> tuple[np.ndarray, float] | None:
    """The shipped second stage (``second_score``): weights over ``second_features`` and
    bias; None where the weights file holds none."""
    with np.load(path) as z:
        if "w2" not in z:
            return None
        return z["w2"].astype(np.float32), float(z["b2"])


SECOND_GRID = (24, 64)  # rows, columns: the box's context resampled (``second_features``)


def second_features(gray: np.ndarray, box: tuple[float, float, float, float]) -> np.ndarray:
    """Profiles of a small plate box (frame px) and its context, whatever its size: the
    box's rows from 2.5 box heights above its centre to 2.5 below and its columns widened
    by half its width on each side, resampled (linear) to ``SECOND_GRID`` px (the box the
    middle 32 x 4.8 px), then per row of the box's columns the mean grey level (in the
    patch's standard deviations, +8) and the mean change along the row (against the
    patch's, +3), and per eighth of the width the same two over the box's middle rows:
    64 values. Why: at 20 px a plate's glyphs may be gone, but it is still a light field
    between two darker lines (its rim, holder or the body's edge) that ends on either
    side, a shape the row test (``glyph_texture``) does not read."""
    x0, y0, x1, y1 = box
    w, h = x1 - x0, y1 - y0
    gh, gw = SECOND_GRID
    sx, sy = 2.0 * w / gw, 5.0 * h / gh
    # grid pixel (c, r) samples frame point (x0 - w / 2 + (c + 0.5) sx, cy - 2.5 h + ...),
    # read from a crop of the frame that holds every point sampled (and the frame's edge
    # where they pass it: replicated as in the whole frame)
    ox, oy = x0 - 0.5 * w + 0.5 * sx - 0.5, (y0 + y1) / 2 - 2.5 * h + 0.5 * sy - 0.5
    ca = int(np.clip(np.floor(ox) - 1, 0, gray.shape[1] - 1))
    ra = int(np.clip(np.floor(oy) - 1, 0, gray.shape[0] - 1))
    cb = int(np.clip(np.ceil(ox + gw * sx) + 2, ca + 1, gray.shape[1]))
    rb = int(np.clip(np.ceil(oy + gh * sy) + 2, ra + 1, gray.shape[0]))
    m = np.array([[sx, 0, ox - ca], [0, sy, oy - ra]], np.float32)
    g = cv2.warpAffine(gray[ra:rb, ca:cb].astype(np.float32), m, (gw, gh),
                       flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                       borderMode=cv2.BORDER_REPLICATE)
    z = (g - g.mean()) / (g.std() + 8.0)
    along = np.abs(np.diff(g, axis=1))
    along /= along.mean() + 3.0
    q = gw // 4  # the box's columns: the middle half of the grid
    mid = slice(gh // 2 - 2, gh // 2 + 2)  # the box's middle rows
    return np.concatenate([
        z[:, q : 3 * q].mean(1), along[:, q : 3 * q - 1].mean(1),
        z[mid].mean(0).reshape(8, -1).mean(1),
        np.pad(along[mid].mean(0), (0, 1), mode="edge").reshape(8, -1).mean(1),
    ]).astype(np.float32)


def second_score(gray: np.ndarray, box: tuple[float, float, float, float],
                 weights: tuple[np.ndarray, float] | None = None) -> float:
    """The second stage's score (a logistic regression's log-odds, trained on synthetic
    plates against the first stage's windows elsewhere) of a box the first stage found;
    -inf where no second stage ships."""
    wb = weights if weights is not None else load_second()
    if wb is None:
        return float("-inf")
    return float(second_features(gray, box) @ wb[0] + wb[1])


# the grid's other phase re-scored (rows, columns; canonical px): the rows only. Why: a 20 px
# plate is 4-5 px tall, two cells of the window; which rows its rim falls in moves its score
# most (synthetic plates whose best grid window scores under 7 while one at another phase
# scores 7 or more, 1500 drawn: 21 of 31 recovered by the rows' phase, 15 by the columns',
# and on 30 real street band pieces moved 0-3 px, learned boxes on no plate 5 -> 7 with the
# rows against 9 with both)
HALF_SHIFTS: tuple[tuple[int, int], ...] = ((1, 0),)


def half_phase_scores(up: np.ndarray, corners: Sequence[tuple[int, int]], w: np.ndarray,
                      bias: float, shifts: Sequence[tuple[int, int]] = HALF_SHIFTS
                      ) -> list[tuple[float, int, int]]:
    """The scores of the windows half a grid step (1 canonical px, ``STRIDE`` / 2) beside
    each window corner (row, column, canonical px of ``up``, on the ``STRIDE`` grid): for each
    of ``shifts`` (dy, dx) the windows at (y +- dy, x +- dx), from the cell features of a
    patch around them whose grid has that phase (with the context the features' local
    normalisation reads, so the scores equal a dense map's at that phase: ~0.2 ms a patch
    against ~60 ms for a narrow camera's band at one scale). Returns (score, row, column) of
    each window scored; corners too near ``up``'s edge are skipped."""
    # the window at y - dy is cell row k - dy of a patch whose grid starts at y + dy - pad:
    # true only for a half step of one canonical px on a grid of two
    assert STRIDE == 2, "half_phase_scores assumes a grid of 2 canonical px"
    wh, ww = window_px()
    # the features' widest context (12 px, the 24 px box's half) plus the 2 px the two
    # shifted windows span, rounded up to a multiple of STRIDE so the patch's grid keeps
    # the shifted phase
    pad = 16
    flat = w.reshape(-1)
    out: list[tuple[float, int, int]] = []
    for y, x in corners:
        for dy, dx in shifts:
            oy, ox = y + dy - pad, x + dx - pad
            ey, ex = y + dy + wh + pad, x + dx + ww + pad
            if oy < 0 or ox < 0 or ey > up.shape[0] or ex > up.shape[1]:
                continue
            feats = cell_features(up[oy:ey, ox:ex])
            k = pad // STRIDE
            for ki in {k, k - dy}:
                for kj in {k, k - dx}:
                    v = window_at(feats, ki, kj)
                    out.append((float(v @ flat + bias), oy + ki * STRIDE, ox + kj * STRIDE))
    return out


def peaks_over(sc: np.ndarray, floor: float, cap: int) -> list[tuple[int, int]]:
    """Grid points (i, j) of ``sc`` whose window scores ``floor`` or more and no less than
    its 8 neighbours, at most ``cap``, the highest first."""
    if sc.size == 0:
        return []
    peak = sc >= cv2.dilate(sc, np.ones((3, 3), np.uint8))
    ii, jj = np.nonzero(peak & (sc >= floor))
    order = np.argsort(-sc[ii, jj], kind="stable")[:cap]
    return list(zip(ii[order].tolist(), jj[order].tolist(), strict=True))


def band_plate_scores(gray: np.ndarray, box: tuple[int, int, int, int],
                      widths: tuple[float, ...], threshold: float, keep: int,
                      weights: tuple[np.ndarray, float] | None = None,
                      accept: Callable[[tuple[float, float, float, float]], bool] | None = None,
                      refine: float = 0.0, refine_cap: int = 64
                      ) -> list[tuple[tuple[float, float, float, float], float]]:
    """Plates ``widths`` px wide (frame px) whose centre lies in the band ``box`` (x0, y0,
    x1, y1) of the grey frame, by the shipped linear classifier: for each width the band
    (with a window's height of rows above and below) is rescaled so that width is
    ``PLATE_PX``, scored densely, and windows scoring ``threshold`` or more become plate
    boxes (frame px, the window's plate); those ``accept`` takes (all when None), overlaps
    (IoU >= 0.2) keeping the highest, at most ``keep``. ``refine`` > 0: the map's local
    peaks scoring ``threshold - refine`` or more (at most ``refine_cap`` per width) are also
    scored half a grid step beside (``half_phase_scores``), those windows reaching
    ``threshold`` joining the others (a peak over it too: its neighbour's box may be the
    one on the plate's glyph row that ``accept`` takes). Why: the grid is ``STRIDE``
    canonical px (1.25 frame px for a 20 px plate), and a 4-5 px tall plate is found or not
    as it moves by under a pixel against it; scoring the whole map at the other phase
    doubles the scorer's cost, the peaks are a few dozen windows. Returns (box, score)."""
    w, b = weights if weights is not None else load_weights()
    x0, y0, x1, y1 = box
    wh, ww = window_px()
    px0, py0, px1, py1 = plate_in_window()
    found: list[tuple[float, tuple[float, float, float, float]]] = []
    for width in widths:
        s = PLATE_PX / width
        pad_y, pad_x = int(np.ceil(wh / s)), int(np.ceil(ww / (2 * s)))
        ya, yb = max(0, y0 - pad_y), min(gray.shape[0], y1 + pad_y)
        xa, xb = max(0, x0 - pad_x), min(gray.shape[1], x1 + pad_x)
        if yb - ya < 2 or xb - xa < 2:
            continue
        up = cv2.resize(gray[ya:yb, xa:xb], None, fx=s, fy=s, interpolation=cv2.INTER_LINEAR)
        sc = score_map(cell_features(up), w, b)
        ii, jj = np.nonzero(sc >= threshold)
        hits = [(float(sc[i, j]), i * STRIDE, j * STRIDE)
                for i, j in zip(ii.tolist(), jj.tolist(), strict=True)]
        if refine > 0:  # the grid's other phase at its peaks from ``refine`` under
            hits += [h for h in half_phase_scores(
                up, [(i * STRIDE, j * STRIDE) for i, j in peaks_over(sc, threshold - refine,
                                                                       refine_cap)], w, b)
                     if h[0] >= threshold]
        for score, cy, cx in hits:
            fx0, fy0 = (cx + px0) / s + xa, (cy + py0) / s + ya
            fx1, fy1 = (cx + px1) / s + xa, (cy + py1) / s + ya
            if y0 <= (fy0 + fy1) / 2 < y1 and x0 <= (fx0 + fx1) / 2 < x1:
                found.append((score, (fx0, fy0, fx1, fy1)))
    return greedy_boxes(found, keep, accept=accept, candidates=50 * max(keep, 1))


def glyph_texture(gray: np.ndarray, box: tuple[float, float, float, float], scale: float = 2.0
                  ) -> tuple[float, float]:
    """How much the grey level of a small plate box (frame px) changes along its middle
    rows (grey levels per px, the box upscaled ``scale``: its glyphs, even blurred), and
    that against the rows as tall as it above and below (+3 for noise). A plate's glyphs
    change more than the body around it; a curb's edge, a lit wall or a bumper's highlight
    that the classifier takes for a rimmed rectangle do not."""
    x0, y0 = int(np.floor(box[0])), int(np.floor(box[1]))
    x1, y1 = int(np.ceil(box[2])), int(np.ceil(box[3]))
    y0, y1 = max(0, y0), min(gray.shape[0], y1)  # a box over the frame's top or bottom edge
    h = y1 - y0
    ya, yb = max(0, y0 - h), min(gray.shape[0], y1 + h)
    x0, x1 = max(0, x0), min(gray.shape[1], x1)
    if h < 1 or x1 - x0 < 3 or yb <= ya:
        return 0.0, 0.0
    up = cv2.resize(gray[ya:yb, x0:x1], None, fx=scale, fy=scale,
                    interpolation=cv2.INTER_LINEAR).astype(np.float32)
    along = np.abs(np.diff(up, axis=1))
    glyph, near = row_texture(along, 0, int((y0 - ya) * scale), up.shape[1], int(h * scale))
    return glyph, glyph / ((near or 0.0) + 3.0)


def on_face(box: tuple[float, float, float, float],
            faces: Sequence[tuple[float, float, float, float]], grow: float = 0.25) -> bool:
    """Whether the centre of a small plate box (frame px) lies in one of the ``faces`` boxes
    grown by ``grow`` of its width and height on each side. Why: a face photo's mouth, eye
    or hair-line row, seen 25-35 px tall, is to the scorer a dark-rimmed textured rectangle
    of a 20-26 px plate's shape (simulated LiDAR-only clips, seeds 0 / 1: 12 of the 18
    candidates on no plate lay on a face, centres within its box or just below its chin);
    a plate is never on a face, and the face detector has searched that face already."""
    cx, cy = (box[0] + box[2]) / 2, (box[1] + box[3]) / 2
    for fx0, fy0, fx1, fy1 in faces:
        gx, gy = grow * (fx1 - fx0), grow * (fy1 - fy0)
        if fx0 - gx <= cx <= fx1 + gx and fy0 - gy <= cy <= fy1 + gy:
            return True
    return False


def stripe_slope(gray: np.ndarray, box: tuple[float, float, float, float],
                 reach: float = 1.0, scale: float = 4.0) -> float:
    """How much the bright shape at a small plate box (frame px) leans: the larger of
    ``_lean`` over the box's columns and over them widened by ``reach`` x its width on each
    side (a box on a dash's tip or on a curb's edge: the stroke goes on beside it).

    Why: a lane dash lies on the ground along the road; a ground line ``L`` m to the side of
    a camera ``H`` m high appears with slope ``H / L`` wherever it is (1.8 m over a lane 3-12
    m off: 0.15-0.6), a bright parallelogram on asphalt, which the scorer takes for a plate.
    A plate's edges are level lines across a vehicle, as are its lamps' and bumper's beside
    it: at the far band's ranges they lean only by the camera's roll (real 20 / 30 px plates
    pasted in the band: median 0.01 / 0.00 over the box)."""
    x0, y0, x1, y1 = box
    w = x1 - x0
    wide = (max(0.0, x0 - reach * w), y0, min(float(gray.shape[1]), x1 + reach * w), y1)
    return max(_lean(gray, box, scale), _lean(gray, wide, scale) if reach > 0 else 0.0)


def _lean(gray: np.ndarray, box: tuple[float, float, float, float], scale: float) -> float:
    """In the box's columns, from 1.5 box heights above it to 1.5 below (upscaled
    ``scale``), the pixels brighter than halfway from the median to the maximum; per column
    its top and bottom rows; the slopes (rows per column) of lines fitted to both. Their
    smaller magnitude where both lean the same way, else 0 (also 0 where under half the
    columns hold a bright pixel)."""
    x0, y0, x1, y1 = box
    h = y1 - y0
    ya = int(max(0, np.floor(y0 - 1.5 * h)))
    yb = int(min(gray.shape[0], np.ceil(y1 + 1.5 * h)))
    xa, xb = int(max(0, np.floor(x0))), int(min(gray.shape[1], np.ceil(x1)))
    if yb - ya < 2 or xb - xa < 2:
        return 0.0
    g = cv2.resize(gray[ya:yb, xa:xb], None, fx=scale, fy=scale,
                   interpolation=cv2.INTER_LINEAR).astype(np.float32)
    bright = g > (float(g.max()) + float(np.median(g))) / 2
    cols = np.nonzero(bright.any(0))[0]
    if len(cols) < max(0.5 * g.shape[1], 2):
        return 0.0
    top = np.argmax(bright[:, cols], axis=0)
    bottom = bright.shape[0] - 1 - np.argmax(bright[::-1, cols], axis=0)
    st = float(np.polyfit(cols, top, 1)[0])
    sb = float(np.polyfit(cols, bottom, 1)[0])
    return min(abs(st), abs(sb)) if st * sb > 0 else 0.0
