"""A LiDAR-only key frame's full-frame safety pass without its plate passes
(``clusters.full_frame_plates`` false, off by default; issue #22): its faces are the full-frame
plan's, its plates the shrunk safety pass's; frames without guidance keep the whole plan."""

from __future__ import annotations

import numpy as np

from v2xlake.tasks.anonymize.build import build_detector
from v2xlake.tasks.anonymize.config import AnonymizeConfig
from v2xlake.tasks.anonymize.guide import Region


def _spied(cfg: AnonymizeConfig) -> tuple[object, list[str]]:
    det = build_detector(cfg)
    calls: list[str] = []
    for name in ("_plates_proposed", "_plates_full", "_faces_proposed"):
        orig = getattr(det, name)

        def spy(*a, _orig=orig, _name=name, **k):  # type: ignore[no-untyped-def]
            calls.append(_name)
            return _orig(*a, **k)

        setattr(det, name, spy)
    return det, calls


def test_key_frame_safety_without_plate_passes() -> None:
    img = np.full((360, 640, 3), 100, np.uint8)
    regions = [Region("face", (100.0, 100.0, 140.0, 140.0), 30.0, "p1", part="head")]
    det, calls = _spied(AnonymizeConfig())
    det.detect(img, regions, full_safety=True)  # type: ignore[attr-defined]
    assert "_plates_proposed" in calls and "_faces_proposed" in calls
    det, calls = _spied(AnonymizeConfig(clusters={"full_frame_plates": False}))
    det.detect(img, regions, full_safety=True)  # type: ignore[attr-defined]
    assert "_plates_proposed" not in calls and "_faces_proposed" in calls
    assert "_plates_full" in calls  # the shrunk safety pass's plates
    calls.clear()
    det.detect(img)  # type: ignore[attr-defined]  # no guidance: the whole plan
    assert "_plates_proposed" in calls
    a = AnonymizeConfig().provenance("v")
    b = AnonymizeConfig(clusters={"full_frame_plates": False}).provenance("v")
    assert "clusters.full_frame_plates=True" in a and "clusters.full_frame_plates=False" in b
