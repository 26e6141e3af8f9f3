"""A learned licence-plate detector: PaddleOCR's DB text detector plus plate geometry.

Why a text detector: a plate is a short line of large, high-contrast characters on a plain
rectangle, and a text detector trained on millions of scene-text lines finds exactly the
character line, in any script, colour and tilt, where hand-written edge/MSER rules (the
classic detector) both miss plates and fire on facades. The network is PP-OCRv4's DB
("Differentiable Binarization", Liao et al. 2020) text detector, ``ch_PP-OCRv4_det_infer.onnx``
(4.7 MB, Apache-2.0), copied out of the ``rapidocr_onnxruntime`` 1.4.4 wheel into this package's
``models/`` folder (never downloaded; rapidocr itself is not installed: it wants the
non-headless OpenCV) and run by onnxruntime (measured ~3x faster than
``cv2.dnn`` on this network at 960 x 544 on one core; ``backend="cv2"`` gives the same map).

What makes a text line a plate (``TextPlateConfig``): the de-rotated line is 1.3-8 times as
wide as tall (EU plate text ~ 4.5, US ~ 2.5, two-row plates ~ 1.5), tilted at most
``max_tilt_deg``, not wider than a fraction of the frame, and sits on a plate: the patch
around the line (the plate's margin) is plain, i.e. one of the two Otsu classes of the
de-rotated patch holds most of its border pixels. Shop signs and road signs pass the first
tests but are usually far larger than plates in the frame or sit on textured backgrounds.
The box reported is the plate estimated from the text line: the line grown by
``plate_grow_x`` / ``plate_grow_y`` of its own size (a plate's margin and frame).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np

from v2xlake.tasks.anonymize.detectors import (
    Detection,
    ScanConfig,
    _file_sha256,
    _unmap,
    bundled_model,
    iter_views,
    model_source,
    nms,
    ort_session,
)
from v2xlake.tasks.anonymize.params import FromParams, derived, param
from v2xlake.tasks.anonymize.plateread import PlateReadConfig, PlateReader

MODEL_SOURCE = "rapidocr_onnxruntime-1.4.4"
MODEL_FILE = "ch_PP-OCRv4_det_infer.onnx"


def text_det_onnx_path() -> Path:
    """The DB text detector shipped with the package (``models/<MODEL_SOURCE>/``)."""
    return bundled_model(MODEL_SOURCE, MODEL_FILE)


@dataclass(frozen=True)
class TextPlateConfig(FromParams):
    """Text-line detection (DB) settings and the geometry a plate's text line must have; the
    fields made with ``param`` / ``derived`` are user parameters (params.py:
    ``TextPlateConfig.of``)."""

    # DB: pixels above ``pixel_threshold`` form text regions; a region is a line when its
    # mean probability is at least ``box_threshold``; ``unclip_ratio`` grows the shrunk
    # kernel back to the text line (PaddleOCR's defaults: 0.3, 0.5 / 0.6, 1.5-2.0)
    pixel_threshold: float = 0.3
    box_threshold: float = param("plates.box_threshold")
    unclip_ratio: float = 1.6
    # plate geometry of the (de-rotated) text line
    min_h: float = 3.0  # px in the original frame
    min_w: float = 8.0
    min_aspect: float = param("plates.min_aspect")
    max_aspect: float = param("plates.max_aspect")
    max_tilt_deg: float = param("plates.max_tilt_deg")
    # a line reaching the frame's left or right edge (within ``edge_cut_px``) may be a plate
    # cut by it: its aspect need only reach ``edge_cut_min_aspect``
    edge_cut_min_aspect: float = param("plates.edge_cut_min_aspect")
    edge_cut_px: float = 2.0
    max_w_frac: float = 1.0
    # the plate estimated from its text line
    plate_grow_x: float = 0.0
    plate_grow_y: float = 0.0
    scan: ScanConfig = field(
        default_factory=lambda: ScanConfig(max_side=None, fine_scale=None, tile=0)
    )
    nms_iou: float = 0.3
    backend: Literal["onnxruntime", "cv2"] = "onnxruntime"
    # read each candidate line with PP-OCRv4's recogniser and keep it only when the reading
    # looks like a plate (plateread.py); None: geometry only
    read: PlateReadConfig | None = derived(
        lambda c: PlateReadConfig.of(c) if c.plates.read else None)


def _rect_of(contour: np.ndarray) -> tuple[float, float, float, float, float]:
    """(cx, cy, long side, short side, tilt deg in (-90, 90]) of a contour's min-area rect."""
    (cx, cy), (a, b), ang = cv2.minAreaRect(contour)
    if a < b:
        a, b, ang = b, a, ang + 90.0
    ang = (ang + 90.0) % 180.0 - 90.0
    return float(cx), float(cy), float(a), float(b), float(ang)


def _half_extents(a: float, b: float, ang: float) -> tuple[float, float]:
    """Half the width and height of the axis-aligned box around a rectangle ``a`` x ``b``
    tilted ``ang`` degrees: where a text line reaches in the frame."""
    t = np.deg2rad(ang)
    return (0.5 * (a * abs(np.cos(t)) + b * abs(np.sin(t))),
            0.5 * (a * abs(np.sin(t)) + b * abs(np.cos(t))))


def db_lines(
    prob: np.ndarray, pixel_threshold: float, box_threshold: float, unclip_ratio: float
) -> list[tuple[float, float, float, float, float, float]]:
    """Text lines of a DB probability map: (cx, cy, long, short, tilt deg, score) per line,
    in map pixels. Pure function of the map (PaddleOCR's DBPostProcess, 'fast' score, with
    the polygon offset done on the rectangle: a rectangle grown by d on every side, d =
    area x ratio / perimeter, which is what pyclipper's offset gives a rectangle)."""
    mask = cv2.dilate((prob > pixel_threshold).astype(np.uint8), np.ones((2, 2), np.uint8))
    contours, _ = cv2.findContours(mask, cv2.RETR_LIST, cv2.CHAIN_APPROX_SIMPLE)
    out = []
    for cnt in contours:
        cx, cy, a, b, ang = _rect_of(cnt)
        if b < 3:
            continue
        x, y, bw, bh = cv2.boundingRect(cnt)
        sub = np.zeros((bh, bw), np.uint8)
        cv2.drawContours(sub, [cnt - np.array([x, y])], -1, 1, -1)
        score = float(cv2.mean(prob[y : y + bh, x : x + bw], sub)[0])
        if score < box_threshold:
            continue
        d = a * b * unclip_ratio / (2 * (a + b))
        out.append((cx, cy, a + 2 * d, b + 2 * d, ang, score))
    return out


NET_MULTIPLE = 32  # the DB network's stride: its input sides are multiples of this


def net_size(w: int, h: int) -> tuple[int, int]:
    """The size (w, h) the text detector's network sees a ``w`` x ``h`` view at: each side
    padded up to a multiple of ``NET_MULTIPLE`` (``TextPlateDetector.prob_map``)."""
    return -(-w // NET_MULTIPLE) * NET_MULTIPLE, -(-h // NET_MULTIPLE) * NET_MULTIPLE


class TextPlateDetector:
    """Plates as text lines of plate geometry, found by PP-OCRv4's DB text detector."""

    name = "text-plate"

    def __init__(self, config: TextPlateConfig | None = None, onnx_path: Path | None = None):
        self.config = config or TextPlateConfig()
        self.onnx_path = Path(onnx_path) if onnx_path else text_det_onnx_path()
        c = self.config
        self.version = (
            f"ppocrv4-det@{model_source(self.onnx_path)}+onnx-sha256:"
            f"{_file_sha256(str(self.onnx_path))[:12]}"
            f":p{c.pixel_threshold:g}:b{c.box_threshold:g}:a{c.min_aspect:g}-{c.max_aspect:g}"
        )
        self.reader = PlateReader(c.read) if c.read is not None else None
        if self.reader is not None:
            self.version += f"+{self.reader.version}"
        self._local = threading.local()
        self._session: Any = None
        if c.backend == "onnxruntime":
            self._session = ort_session(str(self.onnx_path))
            self._input = self._session.get_inputs()[0].name

    def _net(self, w: int, h: int) -> cv2.dnn.Net:
        nets: dict[tuple[int, int], cv2.dnn.Net] = self._local.__dict__.setdefault("nets", {})
        if (w, h) not in nets:
            nets[(w, h)] = cv2.dnn.readNetFromONNX(str(self.onnx_path))
        return nets[(w, h)]

    def prob_map(self, view: np.ndarray) -> np.ndarray:
        """DB text probability per pixel of a BGR view (padded to ``net_size``)."""
        h, w = view.shape[:2]
        wn, hn = net_size(w, h)
        if (wn, hn) != (w, h):
            view = cv2.copyMakeBorder(view, 0, hn - h, 0, wn - w, cv2.BORDER_REPLICATE)
        blob = cv2.dnn.blobFromImage(
            view, 1 / 127.5, (wn, hn), (127.5, 127.5, 127.5), swapRB=True, crop=False
        )
        if self._session is not None:
            out = self._session.run(None, {self._input: blob})[0]
        else:
            net = self._net(wn, hn)
            net.setInput(blob)
            out = net.forward()
        return np.asarray(out[0, 0, :h, :w], np.float32)

    def lines_view(self, view: np.ndarray) -> list[tuple[float, float, float, float, float, float]]:
        c = self.config
        return db_lines(self.prob_map(view), c.pixel_threshold, c.box_threshold, c.unclip_ratio)

    def readable_plates(self, view: np.ndarray, lines: list[tuple[float, ...]],
                        frame_h: list[float] | None = None) -> list[bool]:
        """Per text line of ``view`` (view pixels; ``frame_h``: their heights in the frame
        when the view is scaled): does its reading look like a plate? (all True without a
        reader; lines too small to read are not judged)."""
        if self.reader is None or not lines:
            return [True] * len(lines)
        return [ok for ok, _why, _r in self.reader.judge(view, [ln[:5] for ln in lines],
                                                         frame_h)]

    def plate_ok(self, rect: tuple[float, ...], frame_w: int,
                 at_edge: bool | None = None) -> bool:
        """The plate geometry checks on one text line. A line reaching the frame's left or
        right edge is held to ``edge_cut_min_aspect`` instead of ``min_aspect``: a plate cut
        by the edge shows part of its text, as tall as a whole plate's line but shorter (real
        plates cut in half: about 1.6-2, whole EU lines ~4.5). ``at_edge``: whether the
        line reaches the edge, as the caller knows it; None: told by ``rect``, which must then
        be in frame pixels (a canvas's coordinates say nothing of where the frame ends)."""
        c = self.config
        cx, _cy, a, b, ang = rect[:5]
        lo = c.min_aspect
        if c.edge_cut_min_aspect < lo:
            if at_edge is None:
                hw, _hh = _half_extents(a, b, ang)
                at_edge = cx - hw <= c.edge_cut_px or cx + hw >= frame_w - c.edge_cut_px
            if at_edge:
                lo = c.edge_cut_min_aspect
        return (
            b >= c.min_h
            and a >= c.min_w
            and lo <= a / max(b, 1e-6) <= c.max_aspect
            and abs(ang) <= c.max_tilt_deg
            and a <= c.max_w_frac * frame_w
        )

    def plate_box(self, rect: tuple[float, ...]) -> np.ndarray:
        """Axis-aligned box of the plate around a text line (grown by the plate margins)."""
        c = self.config
        cx, cy, a, b, ang = rect[:5]
        hw, hh = _half_extents(a * (1 + 2 * c.plate_grow_x), b * (1 + 2 * c.plate_grow_y), ang)
        return np.array([cx - hw, cy - hh, cx + hw, cy + hh])

    def detect(self, image_bgr: np.ndarray) -> list[Detection]:
        return self.detect_scan(image_bgr, self.config.scan)

    def detect_scan(self, image_bgr: np.ndarray, scan: ScanConfig) -> list[Detection]:
        """Plates found by the views of ``scan`` (e.g. a down-scaled safety pass)."""
        h, w = image_bgr.shape[:2]
        dets: list[Detection] = []
        for view, s, x0, y0 in iter_views(image_bgr, scan):
            cand = []
            for cx, cy, a, b, ang, score in self.lines_view(view):
                rect = ((cx + x0) / s, (cy + y0) / s, a / s, b / s, ang)
                if self.plate_ok(rect, w):
                    cand.append(((cx, cy, a, b, ang), rect, score))
            ok = self.readable_plates(view, [c[0] for c in cand])
            for (_line, rect, score), keep in zip(cand, ok, strict=True):
                if keep:
                    box = _unmap(self.plate_box(rect), 1.0, 0, 0, w, h)
                    dets.append(Detection("plate", box, score, self.name))
        return nms(dets, self.config.nms_iou)
