"""Real-photo faces and rendered licence plates, the things the anonymizer must find.

Faces are crops of real photographs that ship inside installed packages (no downloads):
``skimage.data.astronaut()`` (Eileen Collins, public domain) and matplotlib's
``mpl-data/sample_data/grace_hopper.jpg``. Plates are drawn as real plates look: a white or
yellow 520 x 110 mm plate with a dark border and black alphanumeric text (``cv2.putText``),
rendered at 0.8 px/mm so that a close plate in a 4K image still has crisp characters.
"""

from __future__ import annotations

from functools import cache
from pathlib import Path

import cv2
import matplotlib
import numpy as np

PLATE_MM = (520.0, 110.0)
FACE_M = (0.18, 0.24)  # width, height of the face sprite in metres


@cache
def face_textures() -> tuple[np.ndarray, ...]:
    """BGR face crops, index 0 = astronaut, 1 = Grace Hopper."""
    from skimage import data

    astro = np.ascontiguousarray(data.astronaut()[20:190, 155:300, ::-1])
    hop_path = Path(matplotlib.get_data_path()) / "sample_data" / "grace_hopper.jpg"
    hop = cv2.imread(str(hop_path), cv2.IMREAD_COLOR)
    if hop is None:
        raise FileNotFoundError(f"matplotlib sample image missing: {hop_path}")
    hop = np.ascontiguousarray(hop[110:350, 160:360])
    return astro, hop


@cache
def plate_texture(text: str, style: int) -> np.ndarray:
    """A 416 x 88 px BGR plate: white (style 0) or yellow (style 1), dark border, black text."""
    w, h = round(PLATE_MM[0] * 0.8), round(PLATE_MM[1] * 0.8)
    bg = (255, 255, 255) if style == 0 else (40, 210, 250)
    img = np.full((h, w, 3), bg, np.uint8)
    cv2.rectangle(img, (3, 3), (w - 4, h - 4), (30, 30, 30), 5)
    font, scale, thick = cv2.FONT_HERSHEY_SIMPLEX, 2.2, 6
    (tw, th), _ = cv2.getTextSize(text, font, scale, thick)
    scale *= min(1.0, (w - 30) / tw)
    (tw, th), _ = cv2.getTextSize(text, font, scale, thick)
    cv2.putText(img, text, ((w - tw) // 2, (h + th) // 2), font, scale, (0, 0, 0), thick,
                cv2.LINE_AA)
    return img
