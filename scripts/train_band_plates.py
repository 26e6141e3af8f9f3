"""Train the far band's small-plate classifier (``v2xlake/tasks/anonymize/bandplate.npz``).

Run: ``python scripts/train_band_plates.py [--out PATH]`` (deterministic: seed 0; a few
minutes on one core). Training data that may ship with the repository only:

* positives: EU-style plates (520 x 112 mm: a white or yellow field, a dark rim, a blue EU
  strip, 5-8 random letters and digits in matplotlib's DejaVu Sans Bold) rendered onto
  car rears drawn here (bodies of random colours, half of them white, silver or pale,
  shading, chrome bars, bumper edges, recesses, lamps, a rear window, the road), half in a
  dark holder, some dimmed or of low contrast (dirt, glare), some behind lens blur and haze,
  shrunk so the plate is 16-34 px wide (area resize, some JPEG, blur and noise), then
  brought to the classifier's scale as the band is (linear upscale) and cut with a pixel or
  two of jitter (a fifth of a plate's height up or down, so the score peaks where the
  plate's glyph row is);
* negatives: the same car rears without a plate, windows beside or off a plate (half a
  plate or more) or at the wrong scale, lane dashes and curb edges leaning as ground lines
  do (``road_sample``), and windows of the photos that ship with scikit-image and
  matplotlib (a street with a motorcycle, brick, grass, gravel, text, faces, ...) at
  several scales; then two rounds of the highest-scoring negative windows of those photos
  (hard negatives).

* the second stage (``bandplate.second_score``, weights ``w2``, ``b2``; its own random
  stream, seed 1, after the first stage is fitted): ``bandplate.second_features`` of the
  first stage's best window on each synthetic plate against its windows on no plate (car
  rears with and without a plate, roads, the shipped photos), fitted the same way.

Real plate photos (plates_eu) and the real street frames are test data: never used here.
The classifier is an L2-regularised logistic regression on ``bandplate.window_at`` of
``bandplate.cell_features``. Deterministic: seed 0, and every maths library on one thread
(a multithreaded BLAS sums in an order that depends on its thread count).
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import cv2
import matplotlib
import numpy as np
from PIL import Image, ImageDraw, ImageFont
from scipy.optimize import minimize
from threadpoolctl import threadpool_limits

from v2xlake.tasks.anonymize import bandplate as bp
from v2xlake.tasks.anonymize.plateprop import to_gray

CHARS = "ABCDEFGHJKLMNPRSTUVWXYZ0123456789"
FONT = os.path.join(matplotlib.get_data_path(), "fonts", "ttf", "DejaVuSans-Bold.ttf")
MARGIN = 16  # canonical px of context around a window when its features are computed


def render_plate(rng: np.random.Generator, wpx: int = 156) -> np.ndarray:
    """An EU-style plate, ``wpx`` px wide (BGR uint8)."""
    hpx = round(wpx / bp.PLATE_ASPECT)
    kind = rng.random()
    field = ((40, 200, 235) if kind < 0.2 else (170, 60, 20) if kind < 0.3
             else tuple(int(v) for v in rng.integers(215, 256, 3)))
    img = Image.new("RGB", (wpx, hpx), field[::-1])
    d = ImageDraw.Draw(img)
    rim = int(rng.integers(1, 5))
    # dark glyphs and rim; light ones on a blue field (plates outside the EU)
    dark = (tuple(int(v) for v in rng.integers(0, 50, 3)) if kind < 0.2 or kind >= 0.3
            else tuple(int(v) for v in rng.integers(215, 256, 3)))
    d.rectangle([0, 0, wpx - 1, hpx - 1], outline=dark, width=rim)
    strip = int(0.085 * wpx) if rng.random() < 0.85 else 0
    if strip:
        d.rectangle([rim, rim, rim + strip, hpx - 1 - rim], fill=(20, 50, 170))
        fs = max(6, hpx // 4)
        f = ImageFont.truetype(FONT, fs)
        d.text((rim + strip // 2, hpx - rim - fs // 2 - 3), str(rng.choice(list("DFINLPSB"))),
               fill=(240, 240, 240), font=f, anchor="mm")
    n = int(rng.integers(5, 9))
    text = "".join(rng.choice(list(CHARS), n))
    if rng.random() < 0.6:
        cut = int(rng.integers(1, n - 1))
        text = text[:cut] + rng.choice([" ", "-", " "]) + text[cut:]
    fs = int(hpx * rng.uniform(0.62, 0.78))
    f = ImageFont.truetype(FONT, fs)
    x0, x1 = rim + strip + 3, wpx - rim - 3
    tw = d.textlength(text, font=f)
    if tw > x1 - x0:
        fs = max(6, int(fs * (x1 - x0) / tw))
        f = ImageFont.truetype(FONT, fs)
    d.text(((x0 + x1) / 2, hpx / 2), text, fill=dark, font=f, anchor="mm")
    out = np.asarray(img)[:, :, ::-1].copy()
    return out


def body_colour(rng: np.random.Generator) -> np.ndarray:
    """A car's colour (BGR float): white, silver, grey, black or a colour, light or dark."""
    kind = rng.choice(["white", "white", "silver", "silver", "pale", "dark", "colour", "colour"])
    if kind == "pale":  # a light tint: beige, pale blue, light grey-green
        return rng.uniform(150, 235) + rng.normal(0, 12, 3)
    if kind == "white":
        v = rng.uniform(190, 250)
        return np.array([v, v, v]) + rng.normal(0, 4, 3)
    if kind == "silver":
        v = rng.uniform(120, 200)
        return np.array([v, v, v]) + rng.normal(0, 5, 3)
    if kind == "dark":
        v = rng.uniform(10, 80)
        return np.array([v, v, v]) + rng.normal(0, 5, 3)
    c = rng.uniform(20, 230, 3)
    return c


def car_rear(rng: np.random.Generator, h: int, w: int, plate: tuple[int, int, int, int] | None
             ) -> np.ndarray:
    """A car rear ``h`` x ``w`` px (BGR float) drawn around the plate box ``plate`` (x0, y0,
    x1, y1; None: where a plate would be, left empty or given a recess only)."""
    body = body_colour(rng)
    img = np.empty((h, w, 3), np.float32)
    img[:] = body
    # vertical shading and a horizontal gradient
    yy = np.linspace(-1, 1, h)[:, None, None]
    xx = np.linspace(-1, 1, w)[None, :, None]
    img *= (1 + rng.uniform(-0.25, 0.25) * yy + rng.uniform(-0.1, 0.1) * xx)
    px0, py0, px1, py1 = plate if plate is not None else (
        int(w * 0.35), int(h * 0.45), int(w * 0.65), int(h * 0.45 + 0.3 * w / bp.PLATE_ASPECT))
    ph = py1 - py0
    # rear window above, road below, maybe the car's sides beyond
    if rng.random() < 0.7:
        top = int(py0 - rng.uniform(1.5, 4.0) * ph)
        if top > 0:
            img[: max(0, top - int(rng.uniform(0, 2) * ph))] = rng.uniform(10, 120)
    if rng.random() < 0.8:
        bot = int(py1 + rng.uniform(1.0, 3.5) * ph)
        if bot < h:
            img[bot:] = rng.uniform(40, 140) + rng.normal(0, 3, 3)
            if rng.random() < 0.5:  # shadow under the car
                img[bot : bot + int(rng.uniform(0.3, 1.0) * ph)] *= rng.uniform(0.2, 0.5)
    if rng.random() < 0.4:
        cut = int(rng.uniform(0.05, 0.25) * w)
        bg = rng.uniform(30, 200)
        img[:, :cut] = bg
        img[:, w - cut :] = bg + rng.normal(0, 10)
    # bumper edges and chrome bars
    for _ in range(int(rng.integers(0, 4))):
        y = int(rng.uniform(0, h))
        t = int(rng.integers(1, max(2, ph // 2)))
        tone = rng.uniform(0.3, 0.8) if rng.random() < 0.5 else rng.uniform(1.1, 1.6)
        x0, x1 = sorted(rng.integers(0, w, 2))
        if rng.random() < 0.5:
            x0, x1 = 0, w
        img[y : y + t, x0:x1] *= tone
    if rng.random() < 0.5:  # chrome bar right above or below the plate
        t = int(rng.uniform(0.2, 0.8) * ph) + 1
        gap = int(rng.uniform(0, 0.6) * ph)
        y = py0 - gap - t if rng.random() < 0.5 else py1 + gap
        xa = int(px0 - rng.uniform(0, 2) * (px1 - px0))
        xb = int(px1 + rng.uniform(0, 2) * (px1 - px0))
        img[max(0, y) : max(0, y + t), max(0, xa) : xb] = rng.uniform(170, 255)
    if rng.random() < 0.6:  # the recess the plate sits in
        m = int(rng.uniform(0.1, 0.6) * ph) + 1
        img[max(0, py0 - m) : py1 + m, max(0, px0 - 2 * m) : px1 + 2 * m] *= rng.uniform(
            0.4, 1.3)
    if rng.random() < 0.7:  # tail lamps
        lw, lh = int(rng.uniform(0.3, 0.9) * (px1 - px0)), int(rng.uniform(0.8, 2.5) * ph)
        ly = int(py0 - rng.uniform(0.5, 3) * ph)
        red = np.array([rng.uniform(0, 60), rng.uniform(0, 60), rng.uniform(120, 255)])
        for lx in (int(rng.uniform(0, 0.15) * w), int(w - rng.uniform(0.15, 0.3) * w)):
            img[max(0, ly) : max(0, ly + lh), lx : lx + lw] = red
    if rng.random() < 0.3:  # a grille or slats
        gy0 = int(py0 - rng.uniform(0, 3) * ph)
        step = int(rng.integers(2, 6))
        img[max(0, gy0) : max(0, gy0 + ph), px0:px1:step] *= rng.uniform(0.3, 0.7)
    return img


def finish(img: np.ndarray, rng: np.random.Generator, scale: float) -> np.ndarray:
    """A drawn patch as a far camera sees it: some JPEG at full size, shrunk by ``scale``
    (area), blurred and noised a little (uint8)."""
    if rng.random() < 0.5:  # the optics' blur, at the drawn size (a few px there)
        img = cv2.GaussianBlur(img, (0, 0), rng.uniform(0.5, 1.2) / scale)
    if rng.random() < 0.3:  # haze: far away, everything towards one grey
        a = rng.uniform(0.1, 0.4)
        img = (1 - a) * img + a * rng.uniform(120, 220)
    u8 = np.clip(img, 0, 255).astype(np.uint8)
    if rng.random() < 0.5:
        _ok, enc = cv2.imencode(".jpg", u8, [cv2.IMWRITE_JPEG_QUALITY, int(rng.integers(40, 95))])
        u8 = cv2.imdecode(enc, cv2.IMREAD_COLOR)
    small = cv2.resize(u8, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    f = small.astype(np.float32)
    if rng.random() < 0.5:
        f = cv2.GaussianBlur(f, (0, 0), rng.uniform(0.3, 1.0))
    f *= rng.uniform(0.6, 1.15)
    f += rng.normal(0, rng.uniform(0, 4), f.shape)
    return np.clip(f, 0, 255).astype(np.uint8)


def window_at(native: np.ndarray, cx: float, cy: float, width: float) -> np.ndarray | None:
    """The feature vector of the window whose plate (``width`` native px) is centred at (cx,
    cy) native px, the patch brought to the canonical scale as the band is (linear)."""
    s = bp.PLATE_PX / width
    wh, ww = bp.window_px()
    up = cv2.resize(to_gray(native), None, fx=s, fy=s, interpolation=cv2.INTER_LINEAR)
    x0 = round(cx * s - ww / 2) - MARGIN
    y0 = round(cy * s - wh / 2) - MARGIN
    if x0 < 0 or y0 < 0 or x0 + ww + 2 * MARGIN > up.shape[1] or \
            y0 + wh + 2 * MARGIN > up.shape[0]:
        return None
    f = bp.cell_features(up[y0 : y0 + wh + 2 * MARGIN, x0 : x0 + ww + 2 * MARGIN])
    o = MARGIN // bp.STRIDE
    return bp.window_at(f, o, o)


def car_sample(rng: np.random.Generator, with_plate: bool
               ) -> tuple[np.ndarray, tuple[float, float, float]]:
    """A finished car rear (native px) and its plate's centre and width (native px)."""
    pw = 156
    ph = round(pw / bp.PLATE_ASPECT)
    h, w = int(pw * rng.uniform(2.6, 3.2)), int(pw * rng.uniform(3.6, 4.4))
    px0 = int(w / 2 - pw / 2 + rng.uniform(-0.2, 0.2) * pw)
    py0 = int(h / 2 - ph / 2 + rng.uniform(-0.3, 0.3) * pw)
    box = (px0, py0, px0 + pw, py0 + ph)
    img = car_rear(rng, h, w, box)
    if with_plate:
        plate = render_plate(rng, pw).astype(np.float32)
        if rng.random() < 0.5:  # a dark plastic holder around the plate
            m = int(rng.integers(2, 10))
            img[max(0, py0 - m) : py0 + ph + m, max(0, px0 - m) : px0 + pw + m] = \
                rng.uniform(10, 70)
        if rng.random() < 0.4:  # dirt or glare: glyphs and field closer together
            plate = plate.mean() + (plate - plate.mean()) * rng.uniform(0.35, 0.8)
        shade = rng.uniform(0.45, 1.05)
        # a plate dimmer than a white body is common (shade, dirt, its angle)
        img[py0 : py0 + ph, px0 : px0 + pw] = plate * shade
    target = rng.uniform(16.0, 34.0)
    scale = target / pw
    out = finish(img, rng, scale)
    return out, ((px0 + pw / 2) * scale, (py0 + ph / 2) * scale, pw * scale)


def road_sample(rng: np.random.Generator) -> tuple[np.ndarray, tuple[float, float, float]]:
    """A stretch of road with a lane dash or a curb's edge (a bright stroke leaning 0.1-0.6,
    as a ground line beside a camera appears), finished as ``car_sample``; a point on the
    stroke and a plate width (native px). Why: far dashes are bright, plate-sized strokes on
    a dark field, which a scorer trained on car rears alone rates as plates."""
    pw = 156
    h, w = int(pw * 2.6), int(pw * 4.0)
    img = np.full((h, w, 3), rng.uniform(50, 130), np.float32) + rng.normal(0, 4, (h, w, 1))
    slope = rng.uniform(0.1, 0.6) * rng.choice([-1, 1])
    t = rng.uniform(0.2, 1.0) * pw / bp.PLATE_ASPECT
    x0 = rng.uniform(0, 0.4) * w
    x1 = x0 + rng.uniform(1.0, 5.0) * pw
    cy = h / 2
    pts = np.array([[x0, cy - slope * (w / 2 - x0)], [x1, cy - slope * (w / 2 - x1)],
                    [x1, cy - slope * (w / 2 - x1) + t], [x0, cy - slope * (w / 2 - x0) + t]])
    if rng.random() < 0.3:  # a curb: the field on one side of the edge lighter
        pts[2:, 1] += h
        pts[2, 0], pts[3, 0] = w, 0
        pts[0, 0], pts[1, 0] = 0, w
        pts[0, 1], pts[1, 1] = cy - slope * w / 2, cy + slope * w / 2
    cv2.fillPoly(img, [pts.astype(np.int32)], (float(rng.uniform(140, 240)),) * 3)
    target = rng.uniform(16.0, 34.0)
    scale = target / pw
    cx = rng.uniform(max(x0, w * 0.3), min(x1, w * 0.7)) if x1 > w * 0.3 else w / 2
    cyy = cy - slope * (w / 2 - cx) + t / 2
    return finish(img, rng, scale), (cx * scale, cyy * scale, pw * scale)


def photos() -> tuple[list[np.ndarray], list[str]]:
    """Photos that ship with scikit-image and matplotlib (BGR or grey uint8), and their names.
    A scikit-image fetcher that needs the network is skipped; the names used are printed and
    stored with the weights, so a run on another scikit-image shows what it trained on."""
    import skimage
    import skimage.data as sd

    out: list[np.ndarray] = []
    names: list[str] = []
    for name in ("astronaut", "coffee", "chelsea", "rocket", "immunohistochemistry", "brick",
                 "grass", "gravel", "camera", "page", "text", "coins", "horse", "moon",
                 "hubble_deep_field", "retina", "clock", "logo", "cell", "microaneurysms"):
        try:
            im = getattr(sd, name)()
        except Exception:  # a fetcher that needs the network: skip it
            continue
        if im.ndim == 3:
            im = cv2.cvtColor(np.ascontiguousarray(im[..., :3]), cv2.COLOR_RGB2BGR)
        out.append(np.ascontiguousarray(im.astype(np.uint8)))
        names.append(name)
    d = Path(skimage.__file__).parent / "data"
    files = [d / f for f in ("motorcycle_left.png", "motorcycle_right.png",
                             "chessboard_RGB.png", "color.png", "clock_motion.png")]
    files.append(Path(matplotlib.get_data_path()) / "sample_data" / "grace_hopper.jpg")
    for path in files:
        im = cv2.imread(str(path)) if path.exists() else None
        if im is not None:
            out.append(im)
            names.append(path.name)
    return out, names


def photo_windows(rng: np.random.Generator, ims: list[np.ndarray], n: int) -> list[np.ndarray]:
    """Random windows of the photos at random scales (a plate width of 16-34 px on the
    photo shrunk by 0.15-1)."""
    out: list[np.ndarray] = []
    while len(out) < n:
        im = ims[int(rng.integers(len(ims)))]
        sc = rng.uniform(0.15, 1.0)
        small = cv2.resize(im, None, fx=sc, fy=sc, interpolation=cv2.INTER_AREA)
        width = rng.uniform(16.0, 34.0)
        half = width * 1.5
        if small.shape[0] < 2 * half or small.shape[1] < 3 * half:
            continue
        for _ in range(8):
            cx = rng.uniform(half * 1.5, small.shape[1] - half * 1.5)
            cy = rng.uniform(half, small.shape[0] - half)
            v = window_at(small, cx, cy, width)
            if v is not None:
                out.append(v)
    return out


def hard_negatives(w: np.ndarray, b: float, ims: list[np.ndarray], per: int,
                   rng: np.random.Generator) -> list[np.ndarray]:
    """The highest-scoring windows of every photo at several plate widths (dense scoring
    as the band is scored), ``per`` per photo and width."""
    out = []
    wr = w.reshape(*bp.WIN_CELLS, bp.CHANNELS).astype(np.float32)
    for im in ims:
        for sc in (0.25, 0.5, 1.0):
            small = to_gray(cv2.resize(im, None, fx=sc, fy=sc, interpolation=cv2.INTER_AREA))
            for width in bp.WIDTHS:
                s = bp.PLATE_PX / width
                up = cv2.resize(small, None, fx=s, fy=s, interpolation=cv2.INTER_LINEAR)
                if up.shape[0] > 1600 or up.shape[1] > 1600:
                    y = int(rng.integers(0, max(1, up.shape[0] - 1600)))
                    x = int(rng.integers(0, max(1, up.shape[1] - 1600)))
                    up = up[y : y + 1600, x : x + 1600]
                f = bp.cell_features(up)
                m = bp.score_map(f, wr, b)
                if m.size == 0:
                    continue
                idx = np.argsort(m.ravel())[::-1][: per * 6]
                taken: list[tuple[int, int]] = []
                for k in idx:
                    i, j = divmod(int(k), m.shape[1])
                    if any(abs(i - a) < 4 and abs(j - bb) < 8 for a, bb in taken):
                        continue
                    taken.append((i, j))
                    out.append(bp.window_at(f, i, j))
                    if len(taken) >= per:
                        break
    return out


def second_samples(rng: np.random.Generator, first: tuple[np.ndarray, float], n: int,
                   ims: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The second stage's training data (``bp.second_features``): per car rear with a plate
    the first stage's best window at IoU >= 0.3 with it (scoring 4 or more: what the second
    stage is asked about), and as negatives every first-stage window (0 or more, overlaps
    dropped) on no plate: elsewhere on that rear, on rears without a plate, on roads with
    dashes and curbs (every other sample each), and on the shipped photos."""
    from v2xlake.tasks.geometry import iou_xyxy

    def found(gray: np.ndarray, thr: float, keep: int) -> list:
        return bp.band_plate_scores(gray, (0, 0, gray.shape[1], gray.shape[0]), bp.WIDTHS,
                                    thr, keep, weights=first)

    pos: list[np.ndarray] = []
    neg: list[np.ndarray] = []
    for it in range(n):
        img, (cx, cy, wd) = car_sample(rng, True)
        g = to_gray(img)
        ph = wd / bp.PLATE_ASPECT
        truth = np.array([[cx - wd / 2, cy - ph / 2, cx + wd / 2, cy + ph / 2]])
        best: tuple[tuple[float, float, float, float], float] | None = None
        for box, sc in found(g, 0.0, 40):
            iou = iou_xyxy(truth, np.array([box]))[0, 0]
            if iou >= 0.3 and sc >= 4.0 and (best is None or sc > best[1]):
                best = (box, sc)
            elif iou < 0.05:
                neg.append(bp.second_features(g, box))
        if best is not None:
            pos.append(bp.second_features(g, best[0]))
        img, _ = car_sample(rng, False) if it % 2 == 0 else road_sample(rng)
        g = to_gray(img)
        neg += [bp.second_features(g, box) for box, _sc in found(g, 0.0, 40)]
    for im in ims:
        for sc in (0.25, 0.5, 1.0):
            small = to_gray(cv2.resize(im, None, fx=sc, fy=sc, interpolation=cv2.INTER_AREA))
            neg += [bp.second_features(small, box) for box, _s in found(small, 0.0, 150)]
    return np.array(pos, np.float32), np.array(neg, np.float32)


def fit(x: np.ndarray, y: np.ndarray, l2: float, wts: np.ndarray) -> tuple[np.ndarray, float]:
    """L2-regularised logistic regression (L-BFGS); ``wts`` per-sample weights."""
    mu = x.mean(axis=0)
    sd = x.std(axis=0) + 1e-3
    z = (x - mu) / sd
    d = z.shape[1]

    def loss(p: np.ndarray) -> tuple[float, np.ndarray]:
        t = z @ p[:d] + p[d]
        sgn = 2 * y - 1
        m = -sgn * t
        lv = np.logaddexp(0, m)
        g = -sgn / (1 + np.exp(-m))
        gw = wts * g
        return (float((wts * lv).sum() + 0.5 * l2 * p[:d] @ p[:d]),
                np.concatenate([z.T @ gw + l2 * p[:d], [gw.sum()]]))

    res = minimize(loss, np.zeros(d + 1), jac=True, method="L-BFGS-B",
                   options={"maxiter": 500})
    p = res.x
    w = p[:d] / sd
    return w, float(p[d] - (mu / sd) @ p[:d])


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", type=Path, default=bp.WEIGHTS)
    ap.add_argument("--n-pos", type=int, default=5000)
    ap.add_argument("--n-neg", type=int, default=14000)
    ap.add_argument("--n-second", type=int, default=3000,
                    help="car rears (and as many rears without a plate or roads) for the "
                    "second stage")
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    cv2.setNumThreads(1)
    pos: list[np.ndarray] = []
    neg: list[np.ndarray] = []

    def off_window(img: np.ndarray, cx: float, cy: float, wd: float, plate: bool
                   ) -> np.ndarray | None:
        """A negative window of a car rear: beside, above or below its plate, or at the
        wrong scale (``plate``), or where a plate would be (none there)."""
        kind = rng.integers(3) if plate else 0
        if kind == 0:  # the plate's place, or beside it
            dx, dy, sw = rng.uniform(-0.3, 0.3) * wd, rng.uniform(-0.2, 0.2) * wd, wd
            if plate:
                dx = rng.choice([-1, 1]) * rng.uniform(0.55, 1.2) * wd
        elif kind == 1:  # above or below it
            dx = rng.uniform(-0.3, 0.3) * wd
            dy = rng.choice([-1, 1]) * rng.uniform(1.3, 3.0) * wd / bp.PLATE_ASPECT
            sw = wd
        else:  # at the wrong scale
            dx, dy = 0.0, 0.0
            sw = wd * (rng.uniform(1.9, 3.0) if rng.random() < 0.5 else rng.uniform(0.3, 0.5))
        return window_at(img, cx + dx, cy + dy, sw)

    while len(pos) < args.n_pos:
        img, (cx, cy, wd) = car_sample(rng, True)
        v = window_at(img, cx + rng.uniform(-0.06, 0.06) * wd, cy + rng.uniform(-0.2, 0.2)
                      * wd / bp.PLATE_ASPECT, wd * rng.uniform(0.85, 1.15))
        if v is not None:
            pos.append(v)
        v = off_window(img, cx, cy, wd, True)
        if v is not None:
            neg.append(v)
    while len(neg) < args.n_neg // 2:
        img, (cx, cy, wd) = car_sample(rng, False)
        v = off_window(img, cx, cy, wd, False)
        if v is not None:
            neg.append(v)
    n_road = len(neg) + args.n_neg // 10
    while len(neg) < n_road:
        img, (cx, cy, wd) = road_sample(rng)
        v = window_at(img, cx + rng.uniform(-0.3, 0.3) * wd, cy, wd * rng.uniform(0.85, 1.15))
        if v is not None:
            neg.append(v)
    ims, names = photos()
    print(f"photos ({len(names)}): {', '.join(names)}")
    neg += photo_windows(rng, ims, args.n_neg - len(neg))
    x = np.array(pos + neg, np.float32)
    y = np.r_[np.ones(len(pos)), np.zeros(len(neg))]
    wts = np.where(y == 1, len(neg) / len(pos), 1.0)
    w, b = fit(x, y, 1.0, wts)
    print(f"round 1: {len(pos)} positives, {len(neg)} negatives", flush=True)
    for rnd in (2, 3):  # two rounds of hard negatives
        hard = hard_negatives(w, b, ims, 60, rng)
        x = np.concatenate([x, np.array(hard, np.float32)])
        y = np.r_[y, np.zeros(len(hard))]
        wts = np.where(y == 1, (len(y) - len(pos)) / len(pos), 1.0)
        w, b = fit(x, y, 1.0, wts)
        t = x @ w + b
        print(f"round {rnd}: +{len(hard)} hard negatives; training accuracy positives "
              f"{(t[y == 1] > 0).mean():.3f}, negatives {(t[y == 0] <= 0).mean():.3f}",
              flush=True)
    # the second stage: its own random stream, so the first stage's weights do not depend
    # on it (and its data on nothing but the first stage's weights)
    first = (w.astype(np.float32).reshape(*bp.WIN_CELLS, bp.CHANNELS), float(np.float32(b)))
    p2, n2 = second_samples(np.random.default_rng(1), first, args.n_second, ims)
    x2 = np.concatenate([p2, n2])
    y2 = np.r_[np.ones(len(p2)), np.zeros(len(n2))]
    w2, b2 = fit(x2, y2, 1.0, np.where(y2 == 1, len(n2) / len(p2), 1.0))
    t2 = x2 @ w2 + b2
    print(f"second stage: {len(p2)} positives, {len(n2)} negatives; training accuracy "
          f"positives {(t2[y2 == 1] > 0).mean():.3f}, negatives {(t2[y2 == 0] <= 0).mean():.3f}",
          flush=True)
    np.savez_compressed(args.out, w=w.astype(np.float32), b=np.float32(b),
                        photos=np.array(names), w2=w2.astype(np.float32), b2=np.float32(b2))
    print(f"wrote {args.out} ({args.out.stat().st_size} bytes)")


if __name__ == "__main__":
    with threadpool_limits(limits=1):  # the weights must not depend on the core count
        main()
