"""The anonymize stage's compiled kernels give the bits of the NumPy / OpenCV code they
replace (the far band's learned scorer's cell features and score map, connected-component
boxes and statistics): the references below are that code, kept here as the oracle."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy import ndimage

from v2xlake.tasks.anonymize import bandplate as bp
from v2xlake.tasks.anonymize.guided import component_boxes
from v2xlake.tasks.anonymize.plateprop import component_stats


def _cell_features_ref(gray: np.ndarray) -> np.ndarray:
    g = gray.astype(np.float32)
    h, w = g.shape
    rows, cols = (h - bp.CELL) // bp.STRIDE + 1, (w - bp.CELL) // bp.STRIDE + 1
    out = np.empty((max(rows, 0), max(cols, 0), bp.CHANNELS), np.float32)
    if rows <= 0 or cols <= 0:
        return out
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=1)
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=1)
    mag, ang = cv2.cartToPolar(gx, gy, angleInDegrees=True)
    energy = cv2.boxFilter(mag * mag, -1, (12, 12))
    mag /= np.sqrt(energy + 16.0)
    ang = np.where(ang >= 180.0, ang - 180.0, ang) * (bp.BINS / 180.0) - 0.5
    lo = np.floor(ang)
    frac = ang - lo
    lo_i = lo.astype(np.int64) % bp.BINS
    hi_i = (lo_i + 1) % bp.BINS
    h2, w2 = rows + 1, cols + 1
    sid = ((np.arange(2 * h2) // 2)[:, None] * w2 + (np.arange(2 * w2) // 2)[None, :]) * bp.BINS
    m = mag[: 2 * h2, : 2 * w2]
    f = frac[: 2 * h2, : 2 * w2]
    n = h2 * w2 * bp.BINS
    hist = (np.bincount((sid + lo_i[: 2 * h2, : 2 * w2]).ravel(), (m * (1 - f)).ravel(), n)
            + np.bincount((sid + hi_i[: 2 * h2, : 2 * w2]).ravel(), (m * f).ravel(), n))
    sub = hist.reshape(h2, w2, bp.BINS).astype(np.float32)
    out[..., : bp.BINS] = np.sqrt(sub[:-1, :-1] + sub[1:, :-1] + sub[:-1, 1:] + sub[1:, 1:])
    mean = cv2.boxFilter(g, -1, (24, 24))
    sq = cv2.boxFilter(g * g, -1, (24, 24))
    z = (g - mean) / (np.sqrt(np.maximum(sq - mean * mean, 0)) + 8.0)
    zc = cv2.boxFilter(z, -1, (bp.CELL, bp.CELL), anchor=(0, 0),
                       borderType=cv2.BORDER_REPLICATE)
    out[..., bp.BINS] = np.clip(zc[: rows * bp.STRIDE : bp.STRIDE, : cols * bp.STRIDE : bp.STRIDE],
                                -3, 3)
    return out


def _score_map_ref(feats: np.ndarray, w: np.ndarray, bias: float) -> np.ndarray:
    step = bp.CELL // bp.STRIDE
    r, c = bp.WIN_CELLS
    hs, ws = feats.shape[0] - (r - 1) * step, feats.shape[1] - (c - 1) * step
    if hs <= 0 or ws <= 0:
        return np.zeros((0, 0), np.float32)
    out = np.full((hs, ws), bias, np.float32)
    for pi in range(step):
        for pj in range(step):
            sub = feats[pi::step, pj::step]
            ni, nj = len(range(pi, hs, step)), len(range(pj, ws, step))
            if ni <= 0 or nj <= 0:
                continue
            acc = out[pi::step, pj::step]
            for ch in range(feats.shape[2]):
                full = cv2.filter2D(np.ascontiguousarray(sub[..., ch]), -1,
                                    np.ascontiguousarray(w[..., ch]), anchor=(0, 0),
                                    borderType=cv2.BORDER_CONSTANT)
                acc += full[:ni, :nj]
    return out


def _street(seed: int, h: int, w: int) -> np.ndarray:
    """A grey test image with edges at every orientation and flat areas: smoothed noise,
    rectangles and lines, plus a saturated and a black patch."""
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.integers(0, 256, (h, w)).astype(np.uint8), (0, 0), 1.5)
    for _ in range(12):
        x0, y0 = int(rng.integers(0, w)), int(rng.integers(0, h))
        x1, y1 = int(rng.integers(0, w)), int(rng.integers(0, h))
        v = int(rng.integers(0, 256))
        if rng.random() < 0.5:
            cv2.rectangle(img, (x0, y0), (x1, y1), v, -1)
        else:
            cv2.line(img, (x0, y0), (x1, y1), v, int(rng.integers(1, 4)))
    img[: h // 6, : w // 6] = 255
    img[-h // 6 :, -w // 6 :] = 0
    return img


@pytest.mark.parametrize("shape", [(1, 1), (3, 9), (4, 4), (5, 7), (37, 121), (96, 410)])
def test_cell_features_bits(shape: tuple[int, int]) -> None:
    for seed in range(3):
        g = _street(seed, *shape)
        a, b = _cell_features_ref(g), bp.cell_features(g)
        assert a.shape == b.shape and a.tobytes() == b.tobytes()
    for v in (0, 255):  # flat: every gradient 0
        g = np.full(shape, v, np.uint8)
        assert _cell_features_ref(g).tobytes() == bp.cell_features(g).tobytes()


def test_score_map_bits() -> None:
    w, b = bp.load_weights()
    for seed, shape in ((0, (60, 200)), (1, (61, 333)), (2, (20, 40)), (3, (5, 5))):
        f = bp.cell_features(_street(seed, *shape))
        a, c = _score_map_ref(f, w, b), bp.score_map(f, w, b)
        assert a.shape == c.shape and a.tobytes() == c.tobytes()


def _masks() -> list[np.ndarray]:
    out = []
    for seed in range(3):
        g = _street(seed, 120, 260)
        gx = cv2.convertScaleAbs(cv2.Sobel(g, cv2.CV_16S, 1, 0, ksize=3))
        out += [(gx >= t).astype(np.uint8) for t in (20, 60, 120)]
    out += [np.zeros((7, 9), np.uint8), np.ones((7, 9), np.uint8), np.ones((1, 1), np.uint8)]
    many = np.zeros((520, 1040), np.uint8)
    many[::2, ::2] = 1  # 135,200 components: beyond 16-bit labels
    return [*out, many]


def test_component_stats_rows() -> None:
    for m in _masks():
        try:
            ref = cv2.connectedComponentsWithStats(m, connectivity=8, ltype=cv2.CV_16U)[2]
        except cv2.error:
            ref = cv2.connectedComponentsWithStats(m, connectivity=8)[2]
        got = component_stats(m)
        assert got.dtype == ref.dtype and got.shape == ref[1:].shape and (got == ref[1:]).all()


@pytest.mark.parametrize("connectivity", [4, 8])
def test_component_boxes(connectivity: int) -> None:
    for m in _masks():
        _n, lab = cv2.connectedComponents(m, connectivity=connectivity, ltype=cv2.CV_32S)
        ref = [(i, sl[1].start, sl[0].start, sl[1].stop - sl[1].start, sl[0].stop - sl[0].start)
               for i, sl in enumerate(ndimage.find_objects(lab), start=1) if sl is not None]
        got_lab, got = component_boxes(m, connectivity)
        assert got == ref and (got_lab == lab).all()
