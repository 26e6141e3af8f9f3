"""The plate-blob tests' faster statistics give what the slower ones gave: the far band's
sized 4-connected components as ``cv2.connectedComponentsWithStats`` lists them, and the
body colour's median as ``np.median`` computes it."""

from __future__ import annotations

import cv2
import numpy as np

from v2xlake.tasks.anonymize.guided import (
    _components_sized,
    component_area,
    component_boxes,
    median_u8,
)


def _reference(mask: np.ndarray, wlo: float, whi: float, hmin: float, alo: float,
               ahi: float, fill: float) -> list[tuple[int, int, int, int, int]]:
    n, _lab, st, _c = cv2.connectedComponentsWithStats(mask, connectivity=4)
    out = []
    for i in range(1, n):
        x, y, w, h, area = (int(v) for v in st[i])
        if wlo <= w <= whi and alo <= w / h <= ahi and h >= hmin and area >= fill * w * h:
            out.append((i, x, y, w, h))
    return out


def test_sized_components_are_those_of_opencv_stats() -> None:
    rng = np.random.default_rng(0)
    for k in range(20):
        # blobs of many sizes: a smoothed noise field cut at a level
        noise = cv2.GaussianBlur(rng.random((240, 640)).astype(np.float32), (0, 0), 1 + k % 4)
        mask = (noise > np.quantile(noise, 0.7 + 0.01 * k)).astype(np.uint8)
        args = (3.0, 60.0, 2.0, 1.2, 8.0, 0.5)
        got = [(i, x, y, w, h) for i, x, y, w, h, _lab in _components_sized(mask, *args)]
        assert got == _reference(mask, *args)
        if k == 0:
            assert got  # the case is not empty
    # the label image returned is the one the boxes index
    mask = np.zeros((20, 40), np.uint8)
    mask[5:9, 10:30] = 1
    ((i, x, y, w, h, lab),) = _components_sized(mask, 10, 30, 2, 2, 8, 0.6)
    assert (x, y, w, h) == (10, 5, 20, 4) and (lab[y : y + h, x : x + w] == i).all()


def test_component_boxes_are_opencv_stats() -> None:
    rng = np.random.default_rng(2)
    for conn in (4, 8):
        for k in range(6):
            noise = cv2.GaussianBlur(rng.random((200, 300)).astype(np.float32), (0, 0), 1 + k)
            mask = (noise > np.quantile(noise, 0.6)).astype(np.uint8)
            n, _l, st, _c = cv2.connectedComponentsWithStats(mask, connectivity=conn)
            lab, boxes = component_boxes(mask, conn)
            assert len(boxes) == n - 1 > 0
            for i, x, y, w, h in boxes:
                assert (x, y, w, h, component_area(lab, i, x, y, w, h)) == tuple(st[i])


def test_median_u8_is_numpy_median() -> None:
    rng = np.random.default_rng(1)
    for n in (1, 2, 3, 10, 11, 1000, 1001):
        a = rng.integers(0, 256, (n, 3), dtype=np.uint8)
        if n > 10:
            a[: n // 2, 1] = 7  # ties around the middle
        ref = np.median(a.astype(np.float32), axis=0)
        got = median_u8(a)
        assert got.dtype == ref.dtype and np.array_equal(got, ref), (n, got, ref)
