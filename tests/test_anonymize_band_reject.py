"""The far band's learned scorer's second stage (issue #22): boxes that lean like a lane dash
(``bandplate.stripe_slope``) or lie on a face (``bandplate.on_face``) are not plates; level
plates on a car stay; both settings reach the provenance string.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from tests.test_anonymize_band_learned import _white_car_plate
from v2xlake.tasks.anonymize import bandplate as bp
from v2xlake.tasks.anonymize.config import AnonymizeConfig
from v2xlake.tasks.anonymize.guided import GuidedConfig, band_learned_plates
from v2xlake.tasks.geometry import iou_xyxy


def _dash(gray: np.ndarray, x: int, y: int, length: int, slope: float) -> None:
    """A lane dash as a far camera sees it: a bright parallelogram ``length`` px long and
    3.5 px tall leaning ``slope`` rows per column, drawn 8x larger and shrunk, on asphalt."""
    big = np.zeros((8 * (int(abs(slope) * length) + 8), 8 * length), np.uint8)
    y0 = 16 if slope >= 0 else big.shape[0] - 44
    pts = np.array([[0, y0], [8 * length, y0 + 8 * slope * length],
                    [8 * length, y0 + 8 * slope * length + 28], [0, y0 + 28]], np.int32)
    cv2.fillPoly(big, [pts.reshape(-1, 1, 2)], 255)
    small = cv2.resize(big, None, fx=0.125, fy=0.125,
                       interpolation=cv2.INTER_AREA).astype(np.float32) / 255
    h, w = small.shape
    reg = gray[y : y + h, x : x + w].astype(np.float32)
    gray[y : y + h, x : x + w] = (reg * (1 - small) + 230 * small).astype(np.uint8)




def test_a_lane_dash_leans_and_a_level_plate_does_not() -> None:
    gray = np.full((300, 600), 70, np.uint8)
    leaning = []
    for k, slope in enumerate((0.18, 0.25, -0.3, 0.6)):
        x = 30 + 130 * k
        _dash(gray, x, 100, 30, slope)
        box = (x + 5.0, 100.0, x + 25.0, 100.0 + abs(slope) * 30 + 4)
        leaning.append(bp.stripe_slope(gray, box))
    assert min(leaning) >= 0.15, leaning
    img = np.full((300, 600, 3), 70, np.uint8)
    plates = [_white_car_plate(img, x, 150) for x in (100, 300, 500)]
    g = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    level = [bp.stripe_slope(g, tuple(float(v) for v in p)) for p in plates]
    assert max(level) < 0.05, level
    # a flat patch has no shape to lean
    assert bp.stripe_slope(np.full((50, 50), 90, np.uint8), (10.0, 20.0, 30.0, 24.0)) == 0.0


def test_the_scorer_drops_its_boxes_that_lean_past_the_setting() -> None:
    """Plates on white cars sheared to lean 0.1 (a camera rolled 5.7 degrees; the classifier,
    trained with leaning lane dashes as negatives, rates plates leaning 0.15 under its
    threshold itself): the scorer finds all three with the test off and at the default
    (0.15); set below their lean it drops them."""
    img = np.full((1080, 1920, 3), 70, np.uint8)
    truth = [_white_car_plate(img, x, 480) for x in (300, 900, 1500)]
    level = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    m = np.float32([[1, 0, 0], [0.1, 1, -0.1 * 960]])
    sheared = cv2.warpAffine(level, m, (1920, 1080), borderValue=70)
    cfg = replace(GuidedConfig(), band_learned_score=8.0)
    band = (0, 300, 1920, 700)
    off = band_learned_plates(sheared, band, 20.0, replace(cfg, band_learned_max_slope=0.0))
    assert len(off) == 3, off
    at_default = replace(cfg, band_learned_max_slope=0.15)
    assert len(band_learned_plates(sheared, band, 20.0, at_default)) == 3
    assert band_learned_plates(sheared, band, 20.0,
                               replace(cfg, band_learned_max_slope=0.07)) == []
    assert GuidedConfig().band_learned_max_slope == 0.15
    kept = [b for b, _s in band_learned_plates(level, band, 20.0, cfg)]
    assert kept and (iou_xyxy(np.array(truth, float), np.array(kept)) >= 0.3).any(1).all()


def test_a_box_on_a_face_or_just_below_its_chin_is_on_the_face() -> None:
    face = (100.0, 100.0, 130.0, 140.0)  # 30 x 40 px
    assert bp.on_face((105.0, 125.0, 125.0, 129.0), [face])  # its mouth row
    assert bp.on_face((105.0, 141.0, 125.0, 147.0), [face])  # centre 4 px below the chin
    assert not bp.on_face((105.0, 155.0, 125.0, 159.0), [face])  # 15 px below
    assert not bp.on_face((140.0, 125.0, 160.0, 129.0), [face])  # beside it
    assert not bp.on_face((105.0, 125.0, 125.0, 129.0), [])


def test_both_settings_are_config_fields_in_the_provenance() -> None:
    cfg = AnonymizeConfig(clusters={"band_learned_score": 8.0})
    g = GuidedConfig.of(cfg)
    assert g.band_learned_faces is True and g.band_learned_max_slope == 0.15
    p = cfg.provenance("v")
    assert "clusters.band_learned_faces=True" in p
    assert "clusters.band_learned_max_slope=0.15" in p
    other = AnonymizeConfig(clusters={"band_learned_score": 8.0, "band_learned_max_slope": 0})
    assert other.provenance("v") != p


def test_the_scorer_weights_reach_the_detector_version(tmp_path: Path) -> None:
    """A retrained ``bandplate.npz`` blurs other boxes at the same settings: the guided
    detector's version (the first part of ``camera_frames.anonymizer``) names its hash."""
    from v2xlake.tasks.anonymize.guided import GuidedDetector

    on = GuidedConfig.of(AnonymizeConfig(clusters={"band_learned_score": 7.0}))
    off = GuidedConfig.of(AnonymizeConfig(clusters={"band_learned_score": 0.0}))
    assert bp.weights_version() in GuidedDetector(None, None, on).version
    assert "bandplate-sha256" not in GuidedDetector(None, None, off).version
    other = tmp_path / "other.npz"
    w, b = bp.load_weights()
    np.savez(other, w=w * 1.01, b=b)
    assert bp.weights_version(str(other)) != bp.weights_version()
