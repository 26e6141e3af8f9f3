"""A face is blurred whole: the blur box of a face is grown by margins measured on real faces.

The whole face (hairline to chin, ear to ear; ``evaluate.WHOLE_FACES``, hand-labelled on the
two real photos) sticks out of CenterFace's box by up to 0.18 of the box width at the sides,
0.17 of its height at the top and 0.09 at the bottom (faces pasted at 24-160 px, tilted
+-20 deg, into the real street images; full-frame plan and safety pass). The face margins
(0.3 / 0.35 / 0.25) cover that with room for a turned or bent head; plates keep ``margin``.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from tests.fixtures.real import requires_real_data
from v2xlake.tasks.anonymize.blur import BlurConfig, blur_boxes, grow_box

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"


def test_face_margins_are_asymmetric_plate_margin_unchanged() -> None:
    cfg = BlurConfig()
    box = (100.0, 100.0, 200.0, 200.0)
    assert grow_box(box, (1000, 1000), cfg, "face") == (70, 65, 230, 225)
    assert grow_box(box, (1000, 1000), cfg, "plate") == (80, 80, 220, 220)
    assert grow_box(box, (1000, 1000), cfg) == (80, 80, 220, 220)
    # clipped to the image
    assert grow_box((0.0, 0.0, 10.0, 10.0), (8, 8), cfg, "face") == (0, 0, 8, 8)
    img = np.zeros((300, 300, 3), np.uint8)
    img[::2] = 255
    done = blur_boxes(img, [box, (10.0, 10.0, 30.0, 20.0)], cfg, ["face", "plate"])
    assert done == [(70, 65, 230, 225), (6, 8, 34, 22)]


def test_blur_is_the_pixelated_gaussian_in_few_operations() -> None:
    """``blur_region`` computes the Gaussian of the pixelated box from its cells; the pixels
    are those of pixelating and then ``cv2.GaussianBlur`` (OpenCV's 8-bit fixed point: within
    2 grey levels), for boxes of every shape, clipped by the image or not, colour and grey."""
    from v2xlake.tasks.anonymize.blur import blur_region

    cfg = BlurConfig()
    rng = np.random.default_rng(3)
    base = rng.integers(0, 256, (240, 320, 3), np.uint8)
    base = cv2.GaussianBlur(base, (0, 0), 3)  # some structure, not only noise
    for t in range(40):
        x0, y0 = int(rng.integers(0, 300)), int(rng.integers(0, 220))
        box = (x0, y0, min(320, x0 + int(rng.integers(1, 200))),
               min(240, y0 + int(rng.integers(1, 200))))
        img = base if t % 2 else np.ascontiguousarray(base[:, :, 0])
        a, b = img.copy(), img.copy()
        bx0, by0, bx1, by1 = box
        roi = a[by0:by1, bx0:bx1]
        rh, rw = roi.shape[:2]
        side = max(rh, rw)
        small = cv2.resize(roi, (max(1, round(cfg.cells * rw / side)),
                                 max(1, round(cfg.cells * rh / side))),
                           interpolation=cv2.INTER_AREA)
        big = cv2.resize(small, (rw, rh), interpolation=cv2.INTER_NEAREST)
        sigma = max(1.0, cfg.sigma_frac * side)
        a[by0:by1, bx0:bx1] = cv2.GaussianBlur(big, (0, 0), sigmaX=sigma, sigmaY=sigma,
                                               borderType=cv2.BORDER_REPLICATE).reshape(roi.shape)
        blur_region(b, box, cfg)
        assert np.abs(a.astype(int) - b.astype(int)).max() <= 2, box
        assert (a[:, :bx0] == b[:, :bx0]).all() and (a[by1:] == b[by1:]).all()


def _paste(img: np.ndarray, photo: np.ndarray, whole: tuple[float, ...], h: int, ang: float,
           px: int, py: int) -> tuple[float, float, float, float]:
    """Paste the photo's face ``h`` px tall, tilted ``ang`` deg, centred at (px, py) with a
    round context; returns the whole face's box (the tilted ellipse's bounding box)."""
    cx, cy = (whole[0] + whole[2]) / 2, (whole[1] + whole[3]) / 2
    s = h / (whole[3] - whole[1])
    m = cv2.getRotationMatrix2D((cx, cy), ang, s)
    m[0, 2] += px - cx
    m[1, 2] += py - cy
    H, W = img.shape[:2]
    warped = cv2.warpAffine(photo, m, (W, H))
    mask = np.zeros((H, W), np.uint8)
    cv2.circle(mask, (px, py), int(0.8 * max(whole[2] - whole[0], whole[3] - whole[1]) * s), 255,
               -1)
    img[mask > 0] = warped[mask > 0]
    a, b, t = (whole[2] - whole[0]) * s / 2, (whole[3] - whole[1]) * s / 2, np.deg2rad(ang)
    ex = float(np.hypot(a * np.cos(t), b * np.sin(t)))
    ey = float(np.hypot(a * np.sin(t), b * np.cos(t)))
    return (px - ex, py - ey, px + ex, py + ey)


@requires_real_data("images/street_pjlab_sensorx2car_0.png")
def test_real_faces_tilted_are_blurred_whole() -> None:
    """Two real faces at 24-160 px tall, tilted -20 / 0 / +20 deg, pasted into a real street
    image (tiled to 1920 x 1080): the full-frame plan finds them and >= 0.95 of them have
    >= 80 % of the whole face under the blur (all of them measured, with >= 0.97 covered)."""
    from v2xlake.tasks.anonymize.build import blur_config, build_detector
    from v2xlake.tasks.anonymize.config import AnonymizeConfig
    from v2xlake.tasks.anonymize.evaluate import WHOLE_FACES, blurred_share, match, real_faces

    cfg = AnonymizeConfig()
    det = build_detector(cfg)
    street = cv2.imread(str(REAL / "images" / "street_pjlab_sensorx2car_0.png"))
    base = np.tile(street, (3, 2, 1))[:1080, :1920].copy()
    faces = real_faces()
    shares, found_all = [], []
    for sizes in ((24, 48, 96), (160,)):
        for name, (photo, _box) in sorted(faces.items()):
            img = base.copy()
            truth = []
            k = 0
            for h in sizes:
                for ang in (-20.0, 0.0, 20.0):
                    px = 150 + (k % 6) * 300 if h < 160 else 300 + k * 600
                    py = 250 + (k // 6) * 500 if h < 160 else 540
                    truth.append(("face", _paste(img, photo, WHOLE_FACES[name], h, ang, px, py)))
                    k += 1
            dets = [d for d in det.detect(img) if d.kind == "face"]
            found, _ = match(truth, dets, 0.1)
            found_all += found.tolist()
            done = blur_boxes(np.zeros_like(img), [d.box for d in dets], blur_config(cfg),
                              [d.kind for d in dets])
            shares += [blurred_share(b, done, img.shape) for (_k, b), f in
                       zip(truth, found, strict=True) if f]
    print(f"found {sum(found_all)}/{len(found_all)}, whole-face share blurred: min "
          f"{min(shares):.2f}")
    assert np.mean(found_all) >= 0.95, found_all
    assert np.mean(np.array(shares) >= 0.8) >= 0.95, shares
