"""PNG overlay of the three alignment methods and the true boxes on one camera image.

The picture a reviewer needs to trust Tab. 4: the true 2D boxes (white) and the annotated
3D boxes projected by the stamp (red), frame (yellow) and target (green) methods. Each
method's boxes are drawn only on the image that method associated (a box drawn on another
image would show a misalignment the method does not make): when the stamp method chose a
different image than the frame method, the PNG has two panels side by side, each with the
true boxes of its own image.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

COLOURS_BGR = {
    "truth": (255, 255, 255),
    "stamp": (40, 40, 230),
    "frame": (0, 215, 255),
    "target": (60, 200, 60),
}


@dataclass(frozen=True)
class OverlayBoxes:
    truth: np.ndarray  # (T, 4) x0 y0 x1 y1
    stamp: np.ndarray  # (M, 4), NaN rows skipped
    frame: np.ndarray
    target: np.ndarray


def _draw(img: np.ndarray, boxes: np.ndarray, colour: tuple[int, int, int], thick: int) -> int:
    n = 0
    for b in np.asarray(boxes, dtype=np.float64).reshape(-1, 4):
        if not np.all(np.isfinite(b)):
            continue
        p0 = (round(b[0]), round(b[1]))
        p1 = (round(b[2]), round(b[3]))
        cv2.rectangle(img, p0, p1, colour, thick, lineType=cv2.LINE_AA)
        n += 1
    return n


def _draw_points(img: np.ndarray, pts: np.ndarray, max_depth: float = 60.0) -> None:
    """Points as single pixels coloured by depth (near red, far blue), like Fig. 10."""
    u = np.round(pts[:, 0]).astype(np.int64)
    v = np.round(pts[:, 1]).astype(np.int64)
    ok = (u >= 0) & (u < img.shape[1]) & (v >= 0) & (v < img.shape[0])
    d = np.clip(pts[ok, 2] / max_depth, 0, 1)
    lut = cv2.applyColorMap(np.arange(256, dtype=np.uint8).reshape(-1, 1), cv2.COLORMAP_JET)
    colours = lut[(255 - np.round(d * 255)).astype(np.int64), 0]
    img[v[ok], u[ok]] = colours


@dataclass(frozen=True)
class Panel:
    image_png: bytes | None
    width: int
    height: int
    boxes: OverlayBoxes
    title: str = ""
    points: np.ndarray | None = None  # (K, 3) u, v, depth: LiDAR points drawn under the boxes


def _render_panel(p: Panel) -> np.ndarray:
    img = None
    if p.image_png:
        img = cv2.imdecode(np.frombuffer(p.image_png, np.uint8), cv2.IMREAD_COLOR)
    if img is None:
        img = np.full((p.height, p.width, 3), 90, np.uint8)
    elif img.shape[0] != p.height or img.shape[1] != p.width:
        img = cv2.resize(img, (p.width, p.height))
    thick = max(1, round(max(p.width, p.height) / 640))
    if p.points is not None and len(p.points):
        _draw_points(img, p.points)
    counts = {
        "truth": _draw(img, p.boxes.truth, COLOURS_BGR["truth"], thick + 1),
        "stamp": _draw(img, p.boxes.stamp, COLOURS_BGR["stamp"], thick),
        "frame": _draw(img, p.boxes.frame, COLOURS_BGR["frame"], thick),
        "target": _draw(img, p.boxes.target, COLOURS_BGR["target"], thick),
    }
    scale = max(0.4, max(p.width, p.height) / 1600)
    step = round(22 * scale * 1.4)
    lines = [(p.title, (255, 255, 255))] if p.title else []
    lines += [(f"{k} ({n})", COLOURS_BGR[k]) for k, n in counts.items() if n]
    for i, (text, colour) in enumerate(lines):
        y = step * (i + 1)
        cv2.putText(img, text, (8, y), cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 3)
        cv2.putText(img, text, (8, y), cv2.FONT_HERSHEY_SIMPLEX, scale, colour, 1)
    return img


def render_overlay(panels: list[Panel], max_panel_width: int = 1280) -> bytes:
    """PNG bytes: the panels side by side (each downscaled to ``max_panel_width``)."""
    imgs = []
    for p in panels:
        img = _render_panel(p)
        if img.shape[1] > max_panel_width:
            f = max_panel_width / img.shape[1]
            img = cv2.resize(img, (max_panel_width, round(img.shape[0] * f)),
                             interpolation=cv2.INTER_AREA)
        imgs.append(img)
    h = max(i.shape[0] for i in imgs)
    imgs = [np.pad(i, ((0, h - i.shape[0]), (0, 0), (0, 0))) for i in imgs]
    ok, buf = cv2.imencode(".png", np.concatenate(imgs, axis=1))
    if not ok:
        raise RuntimeError("PNG encoding of the alignment overlay failed")
    return bytes(buf.tobytes())
