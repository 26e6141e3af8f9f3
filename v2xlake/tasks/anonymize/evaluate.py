"""Recall measurement on real faces pasted into rendered street scenes.

Why here and not only in tests: the report, the benchmark and the tests all need the same
scenes and the same matching rule (a true box counts as found when some detection of its kind
overlaps it with IoU >= 0.3), so the rule lives in one place. The faces are real photographs
that ship inside installed packages (scikit-image's astronaut, public domain; matplotlib's
grace_hopper.jpg); plates are rendered the way the project's simulator renders them (white or
yellow plate, dark border, black alphanumerics drawn with ``cv2.putText``).
"""

from __future__ import annotations

import itertools
import os
import string
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from v2xlake.tasks.anonymize.detectors import Box, Detection
from v2xlake.tasks.geometry import iou_xyxy

# Face boxes inside the source photos (CenterFace's own box on the full photo, rounded).
ASTRONAUT_FACE: Box = (181.0, 58.0, 270.0, 178.0)
GRACE_HOPPER_FACE: Box = (175.0, 131.0, 357.0, 336.0)
# The whole face, hand-labelled on the same photos: hairline to chin, ear to ear (what must be
# blurred, as against the detector's box; the astronaut's ears are under her hair).
WHOLE_FACES: dict[str, Box] = {"astronaut": (176.0, 58.0, 278.0, 178.0),
                               "grace_hopper": (152.0, 131.0, 375.0, 325.0)}


@dataclass(frozen=True)
class TrueBox:
    kind: str
    box: Box
    source: str
    size_px: float  # face: box height; plate: box width


def real_faces() -> dict[str, tuple[np.ndarray, Box]]:
    """BGR photos and their face boxes: astronaut (scikit-image) and grace_hopper (matplotlib)."""
    import matplotlib
    from skimage import data

    ast = cv2.cvtColor(data.astronaut(), cv2.COLOR_RGB2BGR)
    gh_path = os.path.join(matplotlib.get_data_path(), "sample_data", "grace_hopper.jpg")
    gh = cv2.imread(gh_path)
    if gh is None:
        raise FileNotFoundError(gh_path)
    return {"astronaut": (ast, ASTRONAUT_FACE), "grace_hopper": (gh, GRACE_HOPPER_FACE)}


def render_plate(rng: np.random.Generator, width: int) -> np.ndarray:
    """A plate like the simulator's: a 416 x 88 px texture (520 x 110 mm at 0.8 px/mm; white
    or yellow, dark border, black ``cv2.putText`` alphanumerics) resized to ``width``."""
    w, h = 416, 88
    colour = (255, 255, 255) if rng.random() < 0.5 else (40, 210, 250)
    plate = np.full((h, w, 3), colour, np.uint8)
    cv2.rectangle(plate, (3, 3), (w - 4, h - 4), (30, 30, 30), 5)
    text = "".join(rng.choice(list(string.ascii_uppercase + string.digits), 7))
    text = text[:3] + " " + text[3:]
    font, scale, thick = cv2.FONT_HERSHEY_SIMPLEX, 2.2, 6
    (tw, th), _ = cv2.getTextSize(text, font, scale, thick)
    scale *= min(1.0, (w - 30) / tw)
    (tw, th), _ = cv2.getTextSize(text, font, scale, thick)
    cv2.putText(
        plate, text, ((w - tw) // 2, (h + th) // 2), font, scale, (0, 0, 0), thick, cv2.LINE_AA
    )
    out_h = max(round(width * h / w), 4)
    return cv2.resize(plate, (width, out_h), interpolation=cv2.INTER_AREA)


def street_background(rng: np.random.Generator, width: int, height: int) -> np.ndarray:
    """Sky, buildings with windows, road with lane marks: enough clutter to draw false boxes."""
    img = np.zeros((height, width, 3), np.float32)
    horizon = int(height * 0.45)
    sky = np.linspace(235, 170, horizon)[:, None]
    img[:horizon] = np.stack([sky * 1.0, sky * 0.92, sky * 0.8], -1)
    x = 0
    while x < width:
        bw = int(rng.integers(width // 12, width // 5))
        top = int(rng.integers(int(height * 0.08), horizon - 10))
        c = rng.uniform(70, 180, 3)
        img[top:horizon, x : x + bw] = c
        win = max(4, bw // 10)
        for wy in range(top + win, horizon - win, 2 * win):
            for wx in range(x + win // 2, x + bw - win, 2 * win):
                img[wy : wy + win, wx : wx + win] = c * 0.45
        x += bw
    img[horizon:] = rng.uniform(70, 100)
    lane_w = max(2, width // 300)
    for k in range(-3, 4):
        xb = width / 2 + k * width / 5
        pts = np.array([[width / 2 + k * 6, horizon], [xb, height]], np.int32)
        cv2.line(img, tuple(pts[0]), tuple(pts[1]), (215, 215, 215), lane_w)
    img += rng.normal(0, 4, img.shape).astype(np.float32)
    return np.clip(img, 0, 255).astype(np.uint8)


def paste_face(
    img: np.ndarray,
    photo: np.ndarray,
    face: Box,
    face_h: int,
    x: int,
    y: int,
    body_max: int = 10**6,
) -> Box:
    """Paste the photo's face (with 40 % context) so the face box is ``face_h`` tall at (x, y)."""
    fx0, fy0, fx1, fy1 = face
    s = face_h / (fy1 - fy0)
    mx, my = 0.4 * (fx1 - fx0), 0.4 * (fy1 - fy0)
    cx0, cy0 = max(0, int(fx0 - mx)), max(0, int(fy0 - my))
    cx1, cy1 = min(photo.shape[1], int(fx1 + mx)), min(photo.shape[0], int(fy1 + my))
    crop = photo[cy0:cy1, cx0:cx1]
    cw, ch = max(1, round((cx1 - cx0) * s)), max(1, round((cy1 - cy0) * s))
    patch = cv2.resize(crop, (cw, ch), interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR)
    H, W = img.shape[:2]
    px0, py0 = min(max(0, x), W - cw), min(max(0, y), H - ch)
    # a pedestrian body under the head
    body_w = int(cw * 1.2)
    bx0 = px0 + cw // 2 - body_w // 2
    cv2.rectangle(
        img,
        (bx0, py0 + ch),
        (bx0 + body_w, min(H - 1, py0 + ch + min(3 * ch, body_max))),
        (60, 60, 140),
        -1,
    )
    img[py0 : py0 + ch, px0 : px0 + cw] = patch
    return (
        (fx0 - cx0) * s + px0,
        (fy0 - cy0) * s + py0,
        (fx1 - cx0) * s + px0,
        (fy1 - cy0) * s + py0,
    )


def paste_vehicle_with_plate(
    rng: np.random.Generator,
    img: np.ndarray,
    plate_w: int,
    x: int,
    y: int,
    max_w: int = 10**6,
    max_h: int = 10**6,
) -> Box:
    """A car rear (body, window, lights) with a rendered plate; returns the plate box."""
    plate = render_plate(rng, plate_w)
    ph, pw = plate.shape[:2]
    car_w = max(int(pw * 1.3), min(int(pw * 4.2), max_w))
    car_h = max(int(ph / 0.3), min(int(pw * 3.0), max_h))
    H, W = img.shape[:2]
    cx0, cy0 = min(max(0, x), W - car_w), min(max(0, y), H - car_h)
    body = tuple(float(v) for v in rng.uniform(20, 230, 3))
    cv2.rectangle(img, (cx0, cy0), (cx0 + car_w, cy0 + car_h), body, -1)
    cv2.rectangle(
        img,
        (cx0 + car_w // 8, cy0 + car_h // 10),
        (cx0 + car_w * 7 // 8, cy0 + car_h * 4 // 10),
        (40, 40, 50),
        -1,
    )
    lw = max(2, car_w // 8)
    for lx in (cx0 + car_w // 16, cx0 + car_w - car_w // 16 - lw):
        cv2.rectangle(
            img,
            (lx, cy0 + car_h // 2),
            (lx + lw, cy0 + car_h // 2 + max(2, lw // 2)),
            (30, 30, 200),
            -1,
        )
    px0 = cx0 + (car_w - pw) // 2
    py0 = cy0 + int(car_h * 0.62)
    img[py0 : py0 + ph, px0 : px0 + pw] = plate
    return (float(px0), float(py0), float(px0 + pw), float(py0 + ph))


def synth_scene(
    seed: int,
    width: int,
    height: int,
    face_sizes: Sequence[int] = (),
    plate_widths: Sequence[int] = (),
    camera_blur: float = 0.6,
) -> tuple[np.ndarray, list[TrueBox]]:
    """A street frame with real faces of the given heights and plates of the given widths.

    Objects are laid out on a grid so none overlap; a light Gaussian blur and noise imitate a
    camera (a pasted patch would otherwise have unnaturally crisp edges).
    """
    rng = np.random.default_rng(seed)
    img = street_background(rng, width, height)
    faces = real_faces()
    names = sorted(faces)
    items: list[tuple[str, int]] = [("face", s) for s in face_sizes] + [
        ("plate", w) for w in plate_widths
    ]
    n = len(items)
    cols = max(1, int(np.ceil(np.sqrt(n * width / height))))
    rows = max(1, int(np.ceil(n / max(cols, 1))))
    cell_w, cell_h = width // cols, height // rows
    truth: list[TrueBox] = []
    for i, (kind, size) in enumerate(items):
        r, c = divmod(i, cols)
        x = c * cell_w + int(rng.integers(0, max(1, cell_w // 6)))
        y = r * cell_h + int(rng.integers(0, max(1, cell_h // 6)))
        if kind == "face":
            name = names[i % len(names)]
            photo, fbox = faces[name]
            box = paste_face(
                img, photo, fbox, size, x, y, body_max=max(0, int(cell_h * 0.8) - size * 2)
            )
            truth.append(TrueBox("face", box, name, float(size)))
        else:
            box = paste_vehicle_with_plate(
                rng, img, size, x, y, int(cell_w * 0.8), int(cell_h * 0.8)
            )
            truth.append(TrueBox("plate", box, "rendered", float(size)))
    if camera_blur > 0:
        img = cv2.GaussianBlur(img, (0, 0), camera_blur)
    noise = rng.normal(0, 2.0, img.shape)
    img = np.clip(img.astype(np.float32) + noise, 0, 255).astype(np.uint8)
    return img, truth


def match(
    truth: Sequence[TrueBox] | Sequence[tuple[str, Box]],
    dets: Sequence[Detection],
    iou: float = 0.3,
) -> tuple[np.ndarray, int]:
    """(found flag per true box, number of detections that match no true box)."""
    tk = [t.kind if isinstance(t, TrueBox) else t[0] for t in truth]
    tb = np.array([t.box if isinstance(t, TrueBox) else t[1] for t in truth], float).reshape(-1, 4)
    found = np.zeros(len(tk), bool)
    used = np.zeros(len(dets), bool)
    if len(dets) and len(tk):
        db = np.array([d.box for d in dets], float)
        m = iou_xyxy(tb, db)
        for i, k in enumerate(tk):
            same = np.array([d.kind == k for d in dets])
            hit = (m[i] >= iou) & same
            found[i] = bool(hit.any())
            used |= hit
    return found, int((~used).sum())


def whole_face(t: TrueBox) -> Box:
    """The hand-labelled whole face (``WHOLE_FACES``) of a face pasted by ``synth_scene``,
    in the frame: the photo's detector box maps onto the pasted box ``t.box``."""
    name = t.source
    src = ASTRONAUT_FACE if name == "astronaut" else GRACE_HOPPER_FACE
    whole = WHOLE_FACES[name]
    s = (t.box[3] - t.box[1]) / (src[3] - src[1])
    return (t.box[0] + (whole[0] - src[0]) * s, t.box[1] + (whole[1] - src[1]) * s,
            t.box[0] + (whole[2] - src[0]) * s, t.box[1] + (whole[3] - src[1]) * s)


def blurred_share(box: Box, blurred: Sequence[tuple[int, int, int, int]],
                  shape: tuple[int, ...]) -> float:
    """Share of ``box``'s pixels inside the union of the ``blurred`` pixel regions (what
    ``blur.blur_boxes`` returns: the detector boxes grown by the blur margin)."""
    h, w = shape[:2]
    x0, y0 = max(int(np.floor(box[0])), 0), max(int(np.floor(box[1])), 0)
    x1, y1 = min(int(np.ceil(box[2])), w), min(int(np.ceil(box[3])), h)
    if x1 <= x0 or y1 <= y0:
        return 1.0
    m = np.zeros((y1 - y0, x1 - x0), bool)
    for bx0, by0, bx1, by1 in blurred:
        m[max(by0 - y0, 0) : max(by1 - y0, 0), max(bx0 - x0, 0) : max(bx1 - x0, 0)] = True
    return float(m.mean())


# ------------------------------------------------------------------ simulator ground truth
# Sizes from which the default setting is *reliable* (recall >= 0.95 at IoU >= 0.3), measured
# on the simulator's visible boxes at 640x360, 1920x1080 and 3840x2160 with the guided plan
# (tests/test_anonymize_sim.py) and on real faces pasted into street frames (docs/anonymization.md).
# Faces: box height; plates: box width, in pixels of the original frame.
FACE_MIN_PX = 16  # guided plan, any frame size
PLATE_MIN_PX = 20  # guided plan, any frame size
FACE_MIN_PX_NATIVE = 24  # full-frame plan without the x2 fine pass ("fast")
FACE_MIN_PX_FINE = 16  # full-frame plan with the x2 fine pass (default)
SIZE_BINS: dict[str, tuple[float, ...]] = {
    "face": (0, 8, 12, 16, 24, 32, 48, 1e9),
    "plate": (0, 16, 25, 30, 40, 60, 90, 1e9),
}


def face_min_px(finest_scale: float) -> float:
    """The documented reliable face height for a frame whose finest pass ran at this scale."""
    return float(FACE_MIN_PX_FINE if finest_scale >= 2.0 else FACE_MIN_PX_NATIVE / finest_scale)


@dataclass(frozen=True)
class SimTruthHit:
    """One visible simulator face / plate and whether a detection of its kind covered it."""

    agent: str
    camera: str
    stamp_ns: int
    kind: str
    size_px: float  # face: box height; plate: box width
    found: bool


def sim_hits(
    truth: dict[str, list],
    detections: Mapping[tuple[str, str, int], Sequence[Detection]],
    iou: float = 0.3,
) -> list[SimTruthHit]:
    """Match the simulator's ``truth/boxes2d.parquet`` rows (as a column dict) to detections.

    Only images present in ``detections`` (keyed by agent, camera, absolute stamp) count, and
    only faces / plates the truth marks visible (``occluded`` false: a person could not
    identify a half-hidden face either). A visible box is end-exclusive pixels, as is ours.
    """
    occluded = truth.get("occluded") or [False] * len(truth["kind"])
    rows: dict[tuple[str, str, int], list[tuple[str, Box]]] = {}
    for i, kind in enumerate(truth["kind"]):
        if kind not in ("face", "plate") or occluded[i]:
            continue
        key = (str(truth["agent"][i]), str(truth["camera"][i]), int(truth["stamp_ns"][i]))
        if key not in detections:
            continue
        box = (
            float(truth["x0"][i]),
            float(truth["y0"][i]),
            float(truth["x1"][i]),
            float(truth["y1"][i]),
        )
        rows.setdefault(key, []).append((kind, box))
    out: list[SimTruthHit] = []
    for key, items in rows.items():
        found, _ = match(items, detections[key], iou)
        for (kind, b), f in zip(items, found, strict=True):
            size = b[3] - b[1] if kind == "face" else b[2] - b[0]
            out.append(SimTruthHit(key[0], key[1], key[2], kind, size, bool(f)))
    return out


def false_blurs(truth: dict[str, list],
                detections: Mapping[tuple[str, str, int], Sequence[Detection]],
                iou: float = 0.1) -> float:
    """Detections per image that overlap no true face / plate of their kind (visible or not,
    any size: blurring a hidden or tiny face is not a false blur) at IoU >= ``iou``."""
    boxes: dict[tuple[str, str, int], list[tuple[str, Box]]] = {}
    for i, kind in enumerate(truth["kind"]):
        if kind in ("face", "plate"):
            key = (str(truth["agent"][i]), str(truth["camera"][i]), int(truth["stamp_ns"][i]))
            boxes.setdefault(key, []).append((kind, (
                float(truth["x0"][i]), float(truth["y0"][i]), float(truth["x1"][i]),
                float(truth["y1"][i]))))
    n = sum(match(boxes.get(k, []), d, iou)[1] for k, d in detections.items())
    return n / max(len(detections), 1)


def recall_by_size(hits: Sequence[SimTruthHit], kind: str) -> list[tuple[str, int, float]]:
    """(size bin label, count, recall) per ``SIZE_BINS[kind]`` bin that holds any box."""
    edges = SIZE_BINS[kind]
    out = []
    for lo, hi in itertools.pairwise(edges):
        sel = [h.found for h in hits if h.kind == kind and lo <= h.size_px < hi]
        if sel:
            label = f"{lo:g}-{hi:g}" if hi < 1e9 else f">={lo:g}"
            out.append((label, len(sel), float(np.mean(sel))))
    return out


# ------------------------------------------------------------------ real labelled images
@dataclass(frozen=True)
class LabelledImage:
    """A real photo with hand-labelled faces / plates (every other blur on it is false)."""

    path: str
    truth: tuple[tuple[str, Box], ...]


def paste_plate_photo(img: np.ndarray, item: LabelledImage, width: float, x: int | None = None,
                      bottom: int = 10) -> tuple[str, Box]:
    """Paste the photo of a one-plate ``item`` shrunk (area-averaged, as optics would) so its
    plate is ``width`` px wide, its lower edge ``bottom`` px above the image's and its left
    edge at ``x`` (centred when None): how the tests put real plates at a given size into
    real streets. A photo reaching past the image's left or right edge is cut by it (a car
    leaving the frame). Returns the pasted plate's kind and its box within the image."""
    photo = cv2.imread(item.path)
    if photo is None:
        raise FileNotFoundError(item.path)
    (kind, (x0, y0, x1, y1)), = item.truth
    s = width / (x1 - x0)
    small = cv2.resize(photo, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
    sh, sw = small.shape[:2]
    ox = (img.shape[1] - sw) // 2 if x is None else x
    oy = img.shape[0] - sh - bottom
    xa, xb = max(0, ox), min(img.shape[1], ox + sw)
    img[oy : oy + sh, xa:xb] = small[:, xa - ox : xb - ox]
    return kind, (max(0.0, x0 * s + ox), y0 * s + oy, min(float(img.shape[1]), x1 * s + ox),
                  y1 * s + oy)


def plates_eu(folder: str | os.PathLike[str]) -> list[LabelledImage]:
    """openalpr's ``endtoend/eu`` benchmark as found in ``folder``: ``NAME.txt`` holds
    ``file x y width height text`` for one plate of ``file`` (others may be unlabelled, so
    only recall is measured on this set). Read in place: the set is AGPL test data."""
    out = []
    for name in sorted(os.listdir(folder)):
        if not name.endswith(".txt"):
            continue
        with open(os.path.join(folder, name)) as f:
            fields = f.read().split()
        if len(fields) < 5:
            continue
        x, y, w, h = (float(v) for v in fields[1:5])
        box = (x, y, x + w, y + h)
        out.append(LabelledImage(os.path.join(folder, fields[0]), (("plate", box),)))
    return out


def street_images(folder: str | os.PathLike[str]) -> list[LabelledImage]:
    """The real street images of ``folder/labels.json`` ({name: {faces: [{box}], plates: [...]}}),
    boxes x0, y0, x1, y1."""
    import json

    with open(os.path.join(folder, "labels.json")) as f:
        labels = json.load(f)
    out = []
    for name, lab in sorted(labels.items()):
        if not isinstance(lab, dict):
            continue
        truth = tuple(
            (kind, tuple(float(v) for v in item["box"]))
            for kind, key in (("face", "faces"), ("plate", "plates"))
            for item in lab.get(key, [])
        )
        out.append(LabelledImage(os.path.join(folder, name), truth))  # type: ignore[arg-type]
    return out


@dataclass(frozen=True)
class RealScore:
    """Recall and false blurs of one detector on a labelled set."""

    n_true: int
    n_found: int
    n_images: int
    n_false: int
    false_area: list[float]  # per image: share of the image area under false boxes (union)
    missed: list[str]

    @property
    def recall(self) -> float:
        return self.n_found / self.n_true if self.n_true else 1.0

    @property
    def false_per_image(self) -> float:
        return self.n_false / max(self.n_images, 1)


def score_real(
    images: Sequence[LabelledImage], detect: Callable[[np.ndarray], Sequence[Detection]],
    kinds: tuple[str, ...] = ("face", "plate"), iou: float = 0.3,
) -> RealScore:
    """Run ``detect`` on every image; a detection of a kind in ``kinds`` that matches no true
    box of its kind is a false blur; its area (union of false boxes) is measured too."""
    n_true = n_found = n_false = 0
    areas: list[float] = []
    missed: list[str] = []
    for item in images:
        img = cv2.imread(item.path, cv2.IMREAD_COLOR)
        if img is None:
            raise FileNotFoundError(item.path)
        dets = [d for d in detect(img) if d.kind in kinds]
        truth = [t for t in item.truth if t[0] in kinds]
        found, _ = match(truth, dets, iou)
        n_true += len(truth)
        n_found += int(found.sum())
        name = os.path.basename(item.path)
        missed += [f"{name}:{t[0]}" for t, f in zip(truth, found, strict=True) if not f]
        tb = np.array([t[1] for t in truth], float).reshape(-1, 4)
        mask = np.zeros(img.shape[:2], bool)
        for d in dets:
            same = [i for i, t in enumerate(truth) if t[0] == d.kind]
            if same and (iou_xyxy(np.asarray(d.box), tb[same]) >= iou).any():
                continue
            n_false += 1
            x0, y0, x1, y1 = (round(v) for v in d.box)
            mask[max(y0, 0) : y1, max(x0, 0) : x1] = True
        areas.append(float(mask.mean()))
    return RealScore(n_true, n_found, len(images), n_false, areas, missed)
