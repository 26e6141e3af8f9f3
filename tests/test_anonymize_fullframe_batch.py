"""The full-frame plan's float look in batches (``GuidedConfig.face_look_batch``).

The full-frame plan's second face stage looks again, with the float network, at a crop around
each uncertain first-pass candidate. Packed into one canvas the crops need gaps (a crop's
context must not be its neighbour's), which cost more network pixels than the crops hold;
batched, each crop sits alone in its own tensor. What must hold: one batched call gives what
one call per crop gives, and the batched look finds every face the canvases find, feeding the
float network fewer pixels.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import cv2
import numpy as np

from v2xlake.tasks.anonymize.detectors import CenterFaceDetector, FaceConfig
from v2xlake.tasks.anonymize.evaluate import match, synth_scene
from v2xlake.tasks.anonymize.guided import GuidedConfig, GuidedDetector


class _Counting(CenterFaceDetector):
    """The float network, counting the pixels it is fed (one call or a batch)."""

    pixels = 0

    def maps(self, view: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        self.pixels += view.shape[0] * view.shape[1]
        return super().maps(view)

    def maps_batch(self, views: Sequence[np.ndarray]
                   ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        if len(views) == 1:
            return [self.maps(views[0])]
        self.pixels += sum(v.shape[0] * v.shape[1] for v in views)
        return super().maps_batch(views)


def test_one_batched_call_equals_one_call_per_view() -> None:
    net = CenterFaceDetector(FaceConfig(threshold=0.2))
    img, _ = synth_scene(7, 512, 256, face_sizes=(24, 48))
    views = [img[0:128, x : x + 160] for x in (0, 100, 200, 300)]
    for got, want in zip(net.maps_batch(views), (net.maps(v) for v in views), strict=True):
        for a, b in zip(got, want, strict=True):
            assert a.shape == b.shape
            assert np.allclose(a, b, atol=1e-4), float(np.abs(a - b).max())


def test_batched_look_finds_what_the_canvases_find_with_fewer_pixels() -> None:
    """Real faces of 14-24 px (the ones the float look decides) in rendered street frames,
    the full-frame plan's two face stages with the look batched and packed into canvases."""
    cv2.setNumThreads(1)
    cfg = GuidedConfig()
    int8 = CenterFaceDetector(FaceConfig(threshold=cfg.face_proposal_threshold, quantized=True))
    nets = {"batch": _Counting(FaceConfig()), "canvas": _Counting(FaceConfig())}
    plans = {"batch": GuidedDetector(nets["batch"], None, cfg, face_first=int8),
             "canvas": GuidedDetector(nets["canvas"], None, replace(cfg, face_look_batch=0),
                                      face_first=int8)}
    found = dict.fromkeys(plans, 0)
    false = dict.fromkeys(plans, 0)
    n = 0
    for seed in (40, 41, 42):
        img, truth = synth_scene(seed, 1024, 512, face_sizes=(14, 16, 18, 20, 24))
        n += len(truth)
        for name, det in plans.items():
            hit, fp = match([("face", t.box) for t in truth], det.full_frame(img), 0.3)
            found[name] += int(hit.sum())
            false[name] += fp
    assert found["canvas"] >= 0.8 * n, (found, n)
    assert found["batch"] >= found["canvas"], found
    assert false["batch"] <= false["canvas"], false
    assert 0 < nets["batch"].pixels <= 0.85 * nets["canvas"].pixels, (
        nets["batch"].pixels, nets["canvas"].pixels)
