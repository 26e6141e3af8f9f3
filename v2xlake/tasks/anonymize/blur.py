"""Irreversible blurring of detected regions, at the image's full resolution.

Why so strong: a mild Gaussian can be partly inverted (deconvolution) and a small mosaic can be
re-identified; the region is therefore first pixelated to a handful of cells across its longest
side (information actually discarded) and then Gaussian-smoothed so that the cell edges do not
leave a pattern. The box is grown by a margin first because detectors' boxes are tight (a face
box often cuts hair and chin, a plate box its frame).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from v2xlake.tasks.anonymize.detectors import Box
from v2xlake.tasks.anonymize.params import FromParams, param


@dataclass(frozen=True)
class BlurConfig(FromParams):
    """How a box is blurred; the fields made with ``param`` are user parameters (params.py:
    ``BlurConfig.of``)."""

    method: str = param("blur.method")  # "pixelate+gaussian" or "gaussian"
    margin: float = param("blur.plate_margin")  # fraction of the box size added on each side
    # faces: a detector's box runs brow/hairline to chin, and the whole face (hairline to
    # chin, ear to ear) sticks out of it by up to 0.18 of the box width at the sides, 0.17 of
    # its height at the top and 0.09 at the bottom (two real faces pasted at 24-160 px, tilted
    # +-20 deg, into the real street images, full-frame plan and 480 px safety pass); these
    # margins hold that plus a head turned or bent (None: ``margin``)
    face_margin_x: float | None = param("blur.face_margin_x")
    face_margin_top: float | None = param("blur.face_margin_top")
    face_margin_bottom: float | None = param("blur.face_margin_bottom")
    min_margin_px: int = 2
    cells: int = 6  # pixelation cells across the longest side of the grown box
    sigma_frac: float = 0.25  # Gaussian sigma as a fraction of the grown box's longest side


def grow_box(box: Box, shape: tuple[int, ...], cfg: BlurConfig,
             kind: str | None = None) -> tuple[int, int, int, int]:
    """The box grown by the margin (a face's by the face margins), rounded outwards and
    clipped to the image."""
    h, w = shape[:2]
    x0, y0, x1, y1 = box
    fx = cfg.margin if kind != "face" or cfg.face_margin_x is None else cfg.face_margin_x
    ft = cfg.margin if kind != "face" or cfg.face_margin_top is None else cfg.face_margin_top
    fb = cfg.margin if kind != "face" or cfg.face_margin_bottom is None else cfg.face_margin_bottom
    mx = max(fx * (x1 - x0), cfg.min_margin_px)
    mt = max(ft * (y1 - y0), cfg.min_margin_px)
    mb = max(fb * (y1 - y0), cfg.min_margin_px)
    return (
        max(0, int(np.floor(x0 - mx))),
        max(0, int(np.floor(y0 - mt))),
        min(w, int(np.ceil(x1 + mx))),
        min(h, int(np.ceil(y1 + mb))),
    )


def blur_region(img: np.ndarray, box: tuple[int, int, int, int], cfg: BlurConfig) -> None:
    """Blur ``img[y0:y1, x0:x1]`` in place."""
    x0, y0, x1, y1 = box
    if x1 - x0 < 1 or y1 - y0 < 1:
        return
    roi = img[y0:y1, x0:x1]
    rh, rw = roi.shape[:2]
    side = max(rh, rw)
    sigma = max(1.0, cfg.sigma_frac * side)
    if cfg.method.startswith("pixelate"):
        cw = max(1, round(cfg.cells * rw / side))
        ch = max(1, round(cfg.cells * rh / side))
        small = cv2.resize(roi, (cw, ch), interpolation=cv2.INTER_AREA)
        if small.ndim == 2:
            small = small[:, :, None]
        # the Gaussian of the cells shown at full size (nearest), as two small matrices:
        # rows (rh x ch) and columns (rw x cw)
        a_y, a_x = _cells_gauss(rh, ch, sigma), _cells_gauss(rw, cw, sigma)
        out = np.einsum("ic,cdz,jd->ijz", a_y, small.astype(np.float32), a_x, optimize=True)
        img[y0:y1, x0:x1] = np.clip(np.rint(out), 0, 255).astype(img.dtype).reshape(roi.shape)
        return
    out = cv2.GaussianBlur(roi, (0, 0), sigmaX=sigma, sigmaY=sigma,
                           borderType=cv2.BORDER_REPLICATE)
    img[y0:y1, x0:x1] = out.reshape(roi.shape)


def _cells_gauss(n: int, cells: int, sigma: float) -> np.ndarray:
    """(n x cells) float32: pixel i of a line of ``n`` pixels, after ``cells`` values are
    shown at full size (``cv2.INTER_NEAREST``) and smoothed by OpenCV's 8-bit Gaussian of
    ``sigma`` (its kernel size, replicated border), is row i of this matrix times the cells.

    Why: the pixelated box is piecewise constant, so its Gaussian is a weighted sum of a
    handful of cells, the weights differences of the kernel's cumulative sum over each
    cell's run of pixels. ``cv2.GaussianBlur`` paid ~6 sigma taps per pixel instead: three
    160 px faces (boxes ~260 px, sigma 64) took 366 ms per image to blur, more than finding
    them; this gives the same pixels (within 2 grey levels: OpenCV rounds in fixed point) in
    a few milliseconds (8 ms for one such face, 110 ms with OpenCV)."""
    ks = round(sigma * 6 + 1) | 1  # OpenCV's kernel size for 8-bit images
    r = ks // 2
    k = cv2.getGaussianKernel(ks, sigma, cv2.CV_64F).ravel()
    cdf = np.concatenate([[0.0], np.cumsum(k)])
    # each pixel's cell, as INTER_NEAREST picks it; a cell's run of pixels [lo, hi), the
    # first and last runs open towards the replicated border
    cell = np.minimum((np.arange(n) * (cells / n)).astype(np.int64), cells - 1)
    lo = np.searchsorted(cell, np.arange(cells), side="left").astype(np.int64)
    hi = np.searchsorted(cell, np.arange(cells), side="right").astype(np.int64)
    lo[0], hi[-1] = -(ks + n), ks + n
    i = np.arange(n)[:, None]
    w = (cdf[np.clip(hi[None, :] - i + r, 0, ks)] - cdf[np.clip(lo[None, :] - i + r, 0, ks)])
    return w.astype(np.float32)


def blur_boxes(
    img: np.ndarray, boxes: Iterable[Box], cfg: BlurConfig | None = None,
    kinds: Sequence[str] | None = None,
) -> list[tuple[int, int, int, int]]:
    """Blur every box (grown by the margin of its kind: ``kinds`` None, all by ``margin``) in
    place; returns the pixel regions changed."""
    cfg = cfg or BlurConfig()
    done = []
    for i, b in enumerate(boxes):
        g = grow_box(b, img.shape, cfg, kinds[i] if kinds is not None else None)
        blur_region(img, g, cfg)
        done.append(g)
    return done
