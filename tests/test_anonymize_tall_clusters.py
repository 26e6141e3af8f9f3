"""A LiDAR cluster taller than a car or a van carries plates only on faces as wide as a truck
or a bus (``clusters.tall_face_min_m``); annotated boxes, low clusters and the windows of
tall ones are searched as before."""

from __future__ import annotations

import numpy as np

from v2xlake.tasks.anonymize.config import AnonymizeConfig
from v2xlake.tasks.anonymize.guide import GuideConfig, WorldBoxes, part_boxes


def _boxes(*sizes: tuple[float, float, float]) -> WorldBoxes:
    n = len(sizes)
    return WorldBoxes(np.zeros(n, np.int64), np.zeros((n, 3)), np.array(sizes, float),
                      np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)), np.zeros((n, 3)),
                      np.array(["Car"] * n), np.array([f"b{i}" for i in range(n)]))


def _plated(parts: list, kind: str = "plate") -> set[int]:
    return {p[2] for p in parts if p[0] == kind}


def test_tall_narrow_cluster_faces_hold_no_plate() -> None:
    cfg = GuideConfig.of(AnonymizeConfig())
    assert cfg.cluster_tall_face_min_m == 1.5
    # (w, l, h): a facade piece's end, its end-on reading, a truck's rear, a car side-on
    boxes = _boxes((0.4, 2.8, 3.8), (2.8, 0.4, 3.8), (2.5, 0.5, 3.6), (0.6, 2.5, 1.5))
    parts = part_boxes(boxes, cfg, clusters=True)
    assert _plated(parts) == {1, 2, 3}
    assert _plated(parts, "face") == {0, 1, 2, 3}  # windows of every vehicle box
    # annotated boxes, and the rule off: every vehicle face
    assert _plated(part_boxes(boxes, cfg)) == {0, 1, 2, 3}
    off = GuideConfig.of(AnonymizeConfig(clusters={"tall_face_min_m": 0}))
    assert _plated(part_boxes(boxes, off, clusters=True)) == {0, 1, 2, 3}
