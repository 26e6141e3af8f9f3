"""The guided plan's faces in two stages (``faces.regions_first_int8``): CenterFace's int8 copy
looks at the region canvases first, the float network only at crops around its uncertain
candidates.

Real faces (astronaut, Grace Hopper) of 12-24 px pasted into rendered street frames, each in
a region whose expected face is 0.4x its true size (on the simulator's 4K clip window bands
expected 8 px where passengers' faces were 18-24 px): the canvas then holds the faces at
2.5x ``window_face_target_px``, where the int8 copy alone scores some of them under the
threshold (it lost 4K faces of 16-24 px this way). Two stages find every face the float
network finds, more than the int8 copy alone, with no false face (also where the same
regions hold no face), while the float network sees a part of the canvas pixels.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from v2xlake.tasks.anonymize.build import build_detector
from v2xlake.tasks.anonymize.config import AnonymizeConfig
from v2xlake.tasks.anonymize.detectors import CenterFaceDetector, FaceConfig, nms
from v2xlake.tasks.anonymize.evaluate import match, synth_scene
from v2xlake.tasks.anonymize.guide import Region
from v2xlake.tasks.anonymize.guided import GuidedConfig, GuidedDetector

SIZES = (12, 14, 16, 18, 20, 24)


class _Counting(CenterFaceDetector):
    """The float network, counting the pixels it is fed."""

    pixels = 0

    def maps(self, view: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        self.pixels += view.shape[0] * view.shape[1]
        return super().maps(view)


@pytest.fixture(scope="module")
def scenes() -> list[tuple[np.ndarray, list[tuple[str, tuple[float, float, float, float]]],
                           list[Region]]]:
    out = []
    for seed in range(30, 38):
        img, truth = synth_scene(seed, 1024, 512, face_sizes=SIZES)
        regions = []
        for t in truth:
            x0, y0, x1, y1 = t.box
            s = y1 - y0
            regions.append(Region("face", (x0 - s, y0 - s, x1 + s, y1 + s), 0.4 * s, "car-1",
                                  part="window"))
        out.append((img, [("face", t.box) for t in truth], regions))
        # the same regions on the street without the faces (a pedestrian seen from behind,
        # an empty seat): most region pixels of a real clip hold no face
        empty, _ = synth_scene(seed, 1024, 512)
        out.append((empty, [], regions))
    return out


def test_two_stages_find_what_the_float_network_finds(scenes: list) -> None:
    cv2.setNumThreads(1)
    cfg = GuidedConfig()
    two_float = _Counting(FaceConfig(threshold=cfg.face_threshold))
    alone_float = _Counting(FaceConfig(threshold=cfg.face_threshold))
    int8 = CenterFaceDetector(FaceConfig(threshold=cfg.face_proposal_threshold, quantized=True))
    plans = {
        "two stages": GuidedDetector(two_float, None, cfg, region_first=int8),
        "float": GuidedDetector(alone_float, None, cfg),
        "int8 alone": GuidedDetector(
            CenterFaceDetector(FaceConfig(threshold=cfg.face_threshold, quantized=True)),
            None, cfg),
    }
    found = dict.fromkeys(plans, 0)
    false = dict.fromkeys(plans, 0)
    n = 0
    for img, truth, regions in scenes:
        n += len(truth)
        for name, det in plans.items():
            hit, fp = match(truth, nms(det.in_regions(img, regions), 0.3)) if truth else (
                np.zeros(0, bool), len(det.in_regions(img, regions)))
            found[name] += int(hit.sum())
            false[name] += fp
    assert found["float"] >= 0.95 * n, found
    assert found["two stages"] >= found["float"], found
    # never fewer than int8 alone (which misses faces here on some CPUs' int8 kernels: one
    # more found by two stages on earlier machines, the same 48 on an AVX2-less AMD EPYC)
    assert found["two stages"] >= found["int8 alone"], found
    assert false["two stages"] == 0, false
    # the float network looks only at the crops around uncertain candidates
    assert two_float.pixels <= 0.7 * alone_float.pixels, (two_float.pixels,
                                                          alone_float.pixels)


def test_the_stage_builds_two_stages_and_names_them() -> None:
    """On by default; ``faces.int8`` (the int8 copy decides alone) and
    ``regions_first_int8: false`` (float alone) build one stage; the detector's version,
    and so ``camera_frames.anonymizer``, says which."""
    det = build_detector(AnonymizeConfig())
    assert det.region_first is not None and "|region-first@" in det.version
    assert ":int8" in det.region_first.version
    off = build_detector(AnonymizeConfig(faces={"regions_first_int8": False}))
    assert off.region_first is None and "|region-first@" not in off.version
    q = build_detector(AnonymizeConfig(faces={"int8": True}))
    assert q.region_first is None
    a = AnonymizeConfig(faces={"first_accept": 0.4})
    assert a.provenance(det.version) != AnonymizeConfig().provenance(det.version)
