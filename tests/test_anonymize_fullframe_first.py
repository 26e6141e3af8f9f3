"""The full-frame plan's first face pass on the shrunk frame (``faces.first_scale``).

The proposing int8 pass runs on the frame shrunk by ``first_scale`` and its boxes are read
back in frame pixels (``detectors.peak_boxes``): one candidate per local maximum of the heat
map, scaled by the view's size. What must hold: a peak's box lands where the face is in the
frame (centre and size scaled), cells beside a peak and cells under the threshold propose
nothing, and the native view (scale 1) is the frame itself.
"""

from __future__ import annotations

import numpy as np

from v2xlake.tasks.anonymize.detectors import peak_boxes, shrunk


def _maps(hh: int, hw: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    heat = np.zeros((hh, hw), np.float32)
    scale = np.zeros((2, hh, hw), np.float32)
    offset = np.zeros((2, hh, hw), np.float32)
    return heat, scale, offset


def test_peak_boxes_map_local_maxima_to_frame_pixels() -> None:
    heat, scale, offset = _maps(8, 16)  # a 64 x 32 view (stride 4) of a 128 x 64 frame
    heat[2, 5], heat[2, 6] = 0.5, 0.3  # a peak and its weaker neighbour (not a maximum)
    scale[:, 2, 5] = np.log(12 / 4)  # a 12 px box in the view (CenterFace: exp(s) * 4)
    heat[6, 12] = 0.03  # a maximum under the threshold
    boxes, scores = peak_boxes((heat, scale, offset), 64, 32, 128, 64, 0.04)
    assert scores.tolist() == [np.float32(0.5)]
    cx, cy = (5 + 0.5) * 4 * 2, (2 + 0.5) * 4 * 2  # the cell's centre, x2 into the frame
    assert np.allclose(boxes[0], [cx - 12, cy - 12, cx + 12, cy + 12])
    # at scale 1 the boxes are the view's own, clipped to it
    native, _ = peak_boxes((heat, scale, offset), 64, 32, 64, 32, 0.04)
    assert np.allclose(native[0], boxes[0] / 2)
    # a box reaching beyond the view is clipped to the frame
    scale[:, 2, 5] = np.log(80 / 4)
    wide, _ = peak_boxes((heat, scale, offset), 64, 32, 128, 64, 0.04)
    assert wide[0].min() >= 0 and wide[0][2] <= 128 and wide[0][3] <= 64


def test_shrunk_keeps_the_frame_at_scale_one() -> None:
    img = np.random.default_rng(0).integers(0, 255, (512, 1392, 3), np.uint8)
    assert shrunk(img, 1.0) is img
    assert shrunk(img, 0.75).shape == (384, 1044, 3)
    assert shrunk(img[:20, :20], 0.5).shape == (32, 32, 3)  # never under the net's 32 px
