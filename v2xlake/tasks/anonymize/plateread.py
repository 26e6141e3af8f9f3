"""Is a text line a plate? PP-OCRv4's recogniser reads it, and the reading is judged.

A text line found by the DB detector (``textplate.py``) is only a candidate: facades with
lattices, striped barriers, van and truck lettering, shop signs and timestamp watermarks are
text-like too, and the plate-geometry tests (aspect, tilt) pass many of them. A plate is a
short run of upper-case letters and digits, each about half as wide as tall, at least one of
them a digit; lettering is words (lower case, long runs of letters, no digits), a watermark
is a date or a time (``:`` and ``/``, or digit groups joined by ``-`` / ``.``), a lattice or
a barrier reads as nothing, as punctuation or as a run of one repeated stroke (``IIII``,
``1111``).

The recogniser is ``ch_PP-OCRv4_rec_infer.onnx`` (10.9 MB, Apache-2.0), copied out of the
``rapidocr_onnxruntime`` 1.4.4 wheel beside the detector (its 6,623-symbol dictionary,
Chinese + Latin + digits + punctuation, is in the model's metadata). Input: the de-rotated
text line resized to 48 px tall (PaddleOCR's ``rec_img_shape`` 3 x 48 x 320), output a CTC
sequence of symbol probabilities. ``read_text`` is the decode; ``plate_reading_ok`` the
judgement, a pure function of the reading and the line's aspect.

A line too small to read (``min_read_h`` px tall in the image the detector saw) is not
judged: the guided plan's far plates and a low-resolution safety pass keep their geometry
tests only.
"""

from __future__ import annotations

import re
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from v2xlake.tasks.anonymize.detectors import _file_sha256, bundled_model, model_source, ort_session
from v2xlake.tasks.anonymize.params import FromParams, param

MODEL_SOURCE = "rapidocr_onnxruntime-1.4.4"
REC_FILE = "ch_PP-OCRv4_rec_infer.onnx"
REC_H = 48


def rec_onnx_path() -> Path:
    """The PP-OCRv4 recogniser shipped with the package (``models/<MODEL_SOURCE>/``)."""
    return bundled_model(MODEL_SOURCE, REC_FILE)


@dataclass(frozen=True)
class PlateReadConfig(FromParams):
    """What a reading must look like to be a plate (see the module docstring); the fields
    made with ``param`` are user parameters (params.py: ``PlateReadConfig.of``)."""

    # symbols read with at least this probability count; the line's mean over its
    # plate symbols must reach ``min_conf``
    min_char_conf: float = 0.3
    min_conf: float = param("plates.read_min_conf")
    min_chars: int = 3  # upper-case letters and digits read
    max_chars: int = 10
    min_digits: int = param("plates.read_min_digits")
    # share of the symbols read that are plate symbols (A-Z, 0-9, '-', '.', '·', ' ')
    min_plate_share: float = 0.7
    # at most this many symbols that are neither plate symbols nor lower case letters...
    max_lower: int = 1
    # ...a run of one repeated symbol (lattice, barrier stripes) at most this long
    max_repeat: int = 4
    # symbols per (line width / line height): plate characters are ~0.4-0.8 line heights
    # wide (the DB line is ~1.3x the glyph height after unclipping)
    min_chars_per_aspect: float = 0.5
    max_chars_per_aspect: float = 3.5
    # lines shorter than this (px, in the detector's input) are not judged
    min_read_h: float = 10.0
    # a line lower than ``small_h`` px in the frame (a plate under ~38 px wide: glyphs of
    # 4-5 px, illegible even upscaled) is read with symbols from ``small_char_conf`` and no
    # mean confidence: its reading is a guess, and the guess still has to look like a plate
    small_h: float = param("plates.read_small_h")
    small_char_conf: float = 0.1
    # a reading without a digit is a plate when its line looks like one (``plate_look``)
    no_digit_look: bool = param("plates.read_no_digit_look")
    # ... its glyphs dark on a bright background: the brighter Otsu class of the line at
    # least ``look_min_bright`` of it, the classes' means ``look_min_contrast`` grey levels
    # apart (a small plate's glyphs are blurred grey: real plates read by the full-frame
    # plan, 30-90 px wide, 304 / 417 pass at 40 and 218 / 417 at 50; the lettering read
    # without a digit beside them that passes the other tests is at most 29 apart)
    look_min_bright: float = 0.4
    look_min_contrast: float = 40.0
    # ... both neutral (white / grey plate, black glyphs: CIELAB chroma of each class's mean)
    look_max_chroma: float = 12.0
    look_max_glyph_chroma: float = 10.0
    # ... and the plate ends with the glyphs: at most this share of the rows half a line
    # height above and below the line as bright as its background
    look_max_bound: float = 0.3


PLATE_SYMBOLS = set("ABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789")
SEPARATORS = set("-.·• ")
# a watermark's time (hh:mm:ss) or date (yyyy-mm-dd, dd.mm.yyyy, dd/mm/yy); one ':' between
# digit groups is not enough: readers see a plate's emblem or hyphen as ':' ("1B1:9839")
DATE_TIME = re.compile(
    r"\d{1,2}[:：]\d{2}[:：]\d{2}|\d{4}[-./]\d{1,2}[-./]\d{1,2}|\d{1,2}[-./]\d{1,2}[-./]\d{4}"
    r"|\d{1,2}/\d{1,2}/\d{2}")


@dataclass(frozen=True)
class Reading:
    text: str
    confs: tuple[float, ...]


def read_text(probs: np.ndarray, charset: list[str]) -> Reading:
    """CTC greedy decode of one line's (T, n_symbols) probabilities (index 0 = blank)."""
    idx = probs.argmax(1)
    conf = probs.max(1)
    text, confs = [], []
    prev = -1
    for i, c in zip(idx, conf, strict=True):
        if i != prev and i != 0:
            text.append(charset[int(i)])
            confs.append(float(c))
        prev = int(i)
    return Reading("".join(text), tuple(confs))


def plate_reading_ok(r: Reading, aspect: float, cfg: PlateReadConfig,
                     frame_h: float = np.inf, looks_plate: bool = False) -> tuple[bool, str]:
    """(is a plate, why not): the judgement of one reading of a line ``aspect`` (long / short
    side) wide and ``frame_h`` px high in the frame. A line lower than ``small_h`` (a plate
    ~30 px wide) is read with every symbol from ``small_char_conf`` and no mean confidence:
    real 30 px plates pasted into real streets were found by the detector and then rejected
    by their reading 24 times in 38 misses ('14981' at 0.44, '8AT' at 0.22-0.27, 'POKE'
    at 0.44), while the lettering around plates that small reads as sure words (CITROEN,
    NORTH, HOLT at 0.94-1.0): there a reading without a digit is rejected only when its
    plate symbols reach ``min_conf``; the word, share, date and repeat rules still apply.
    ``looks_plate``: the line has a plate's look (``plate_look``), and a reading without a
    digit is judged by the other rules (a vanity plate: G-WAGEN, BIMMIAN)."""
    small = frame_h < cfg.small_h
    min_char_conf = cfg.small_char_conf if small else cfg.min_char_conf
    min_conf = 0.0 if small else cfg.min_conf
    kept = [(ch, c) for ch, c in zip(r.text, r.confs, strict=True) if c >= min_char_conf]
    text = "".join(ch for ch, _ in kept)
    plate = [c for ch, c in kept if ch in PLATE_SYMBOLS]
    n = len(plate)
    if n < cfg.min_chars:
        return False, f"{n} plate symbols"
    if n > cfg.max_chars:
        return False, f"{n} plate symbols > {cfg.max_chars}"
    # a small line's reading without a digit is lettering only when it is read as surely as
    # a plate must be (``min_conf``): a guess's digits are guesses too
    if (sum(ch.isdigit() for ch in text) < cfg.min_digits and not looks_plate
            and not (small and float(np.mean(plate)) < cfg.min_conf)):
        return False, "no digit"
    if float(np.mean(plate)) < min_conf:
        return False, f"confidence {np.mean(plate):.2f}"
    stripped = text.strip()
    share = sum(ch in PLATE_SYMBOLS or ch in SEPARATORS for ch in stripped) / max(len(stripped), 1)
    if share < cfg.min_plate_share:
        return False, f"plate symbols {share:.2f}"
    if sum(ch.islower() for ch in text) > cfg.max_lower:
        return False, "lower case"
    if DATE_TIME.search(text):
        return False, "date / time"
    run = max((len(m.group(0)) for m in re.finditer(r"(.)\1*", text)), default=0)
    if run > cfg.max_repeat:
        return False, f"repeated symbol x{run}"
    per = n / max(aspect, 1e-6)
    if not cfg.min_chars_per_aspect <= per <= cfg.max_chars_per_aspect:
        return False, f"{n} symbols for aspect {aspect:.1f}"
    return True, ""


LOOK_W, LOOK_H = 1.4, 2.0  # the look's patch: the line's width and height times these


def look_crop(image: np.ndarray, rect: tuple[float, ...]) -> np.ndarray:
    """The de-rotated text line (cx, cy, long, short, tilt deg) with ``LOOK_H`` / 2 of its
    height above and below and a fifth of its width each side, ``REC_H`` px tall (BGR):
    what ``plate_look`` judges."""
    cx, cy, a, b, ang = rect[:5]
    return line_crop(image, (cx, cy, a * LOOK_W, b * LOOK_H, ang), grow_y=0.0)


def plate_look(patch: np.ndarray, cfg: PlateReadConfig) -> tuple[bool, str]:
    """(looks like a plate, why not): a text line's ``look_crop`` patch (BGR). Why: a
    vanity plate has no digit (G-WAGEN, BIMMIAN: 3 of the 108 plates_eu photos) and reads
    exactly like lettering, so its reading cannot tell it apart; its look can. A plate is
    dark, neutral glyphs on a bright, neutral background that ends with them (the plate's
    edge within a glyph height); lettering is mostly light on a dark or coloured ground
    (road signs, van and shop lettering: NORTH, EXIT, SILUMA, HOLT), coloured glyphs
    (stickers), or dark glyphs on a body that runs on around them (CRAFTER on a white van).
    Real plates_eu plates pasted into the real street images at 30-90 px, their lines as
    the full-frame plan reads them (both halves of plates_eu): 304 of 417 lines of plates
    with digits have this look (the others: low contrast, a plate on a body of its colour,
    a tinted photo), none of the 20 lettering lines read without a digit beside them (road
    signs, van, shop and dealer lettering, stickers): it is strong evidence, asked only of
    a reading without a digit. Yellow plates do not pass."""
    g = cv2.cvtColor(patch, cv2.COLOR_BGR2GRAY)
    lab = cv2.cvtColor(patch, cv2.COLOR_BGR2LAB).astype(np.float32)
    h, w = g.shape
    r0, r1 = round(h * (0.5 - 0.5 / LOOK_H)), round(h * (0.5 + 0.5 / LOOK_H))
    c0, c1 = round(w * (0.5 - 0.5 / LOOK_W)), round(w * (0.5 + 0.5 / LOOK_W))
    line = np.ascontiguousarray(g[r0:r1, c0:c1])
    if line.size < 4 or r0 < 1:
        return False, "no patch"
    t, _ = cv2.threshold(line, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    bright = line > t
    if bright.all() or not bright.any():
        return False, "plain"
    if bright.mean() < cfg.look_min_bright:
        return False, f"bright share {bright.mean():.2f}"
    lb, ld = float(line[bright].mean()), float(line[~bright].mean())
    if lb - ld < cfg.look_min_contrast:
        return False, f"contrast {lb - ld:.0f}"
    ab = lab[r0:r1, c0:c1, 1:] - 128.0
    for name, m, top in (("background", bright, cfg.look_max_chroma),
                         ("glyph", ~bright, cfg.look_max_glyph_chroma)):
        chroma = float(np.hypot(*ab[m].mean(axis=0)))
        if chroma > top:
            return False, f"{name} chroma {chroma:.1f}"
    ring = np.concatenate([g[:r0, c0:c1].ravel(), g[r1:, c0:c1].ravel()]).astype(np.float32)
    bound = float(np.mean(np.abs(ring - lb) < 0.35 * (lb - ld)))
    if bound > cfg.look_max_bound:
        return False, f"background runs on {bound:.2f}"
    return True, ""


def line_crop(image: np.ndarray, rect: tuple[float, ...], grow_y: float = 0.1) -> np.ndarray:
    """The de-rotated text line (cx, cy, long, short, tilt deg) as a ``REC_H`` px tall BGR
    patch (width in proportion, at least ``REC_H``)."""
    cx, cy, a, b, ang = rect[:5]
    b = b * (1 + 2 * grow_y)
    s = REC_H / max(b, 1e-6)
    out_w = max(round(a * s), REC_H)
    m = cv2.getRotationMatrix2D((cx, cy), ang, s)
    m[0, 2] += out_w / 2 - cx
    m[1, 2] += REC_H / 2 - cy
    interp = cv2.INTER_AREA if s < 1 else cv2.INTER_CUBIC
    return cv2.warpAffine(image, m, (out_w, REC_H), flags=interp, borderMode=cv2.BORDER_REPLICATE)


class PlateReader:
    """PP-OCRv4 recognition of text lines, and the plate judgement of ``plate_reading_ok``."""

    def __init__(self, config: PlateReadConfig | None = None, onnx_path: Path | None = None):
        self.config = config or PlateReadConfig()
        self.onnx_path = Path(onnx_path) if onnx_path else rec_onnx_path()
        self._session: Any = ort_session(str(self.onnx_path))
        self._input = self._session.get_inputs()[0].name
        meta = self._session.get_modelmeta().custom_metadata_map
        self.charset = ["<blank>", *meta["character"].splitlines(), " "]
        c = self.config
        self.version = (
            f"ppocrv4-rec@{model_source(self.onnx_path)}+onnx-sha256:"
            f"{_file_sha256(str(self.onnx_path))[:12]}:c{c.min_conf:g}/{c.min_char_conf:g}"
            f":n{c.min_chars}-{c.max_chars}:d{c.min_digits}:s{c.min_plate_share:g}"
            f":l{c.max_lower}:r{c.max_repeat}:k{c.min_chars_per_aspect:g}-"
            f"{c.max_chars_per_aspect:g}:h{c.min_read_h:g}:sh{c.small_h:g}/{c.small_char_conf:g}")
        if c.no_digit_look:
            self.version += (f":look{c.look_min_bright:g}/{c.look_min_contrast:g}/"
                             f"{c.look_max_chroma:g}/{c.look_max_glyph_chroma:g}/"
                             f"{c.look_max_bound:g}")
        self._lock = threading.Lock()

    def read(self, crops: list[np.ndarray]) -> list[Reading]:
        """Readings of ``REC_H`` px tall BGR patches (one batch, right-padded)."""
        if not crops:
            return []
        wmax = max(c.shape[1] for c in crops)
        batch = np.zeros((len(crops), 3, REC_H, wmax), np.float32)
        for i, c in enumerate(crops):
            x = (c[:, :, ::-1].astype(np.float32) / 255.0 - 0.5) / 0.5
            batch[i, :, :, : c.shape[1]] = x.transpose(2, 0, 1)
        probs = self._session.run(None, {self._input: batch})[0]
        return [read_text(p, self.charset) for p in probs]

    def judge(self, image: np.ndarray, rects: list[tuple[float, ...]],
              frame_h: list[float] | None = None) -> list[tuple[bool, str, Reading | None]]:
        """(is a plate, why not, reading) per text line of ``image`` (original pixels);
        ``frame_h``: each line's height in the frame when ``image`` is a scaled view (the
        reading of a line low in the frame is a guess: ``plate_reading_ok``)."""
        out: list[tuple[bool, str, Reading | None]] = [(True, "", None)] * len(rects)
        todo = [i for i, r in enumerate(rects) if r[3] >= self.config.min_read_h]
        readings = self.read([line_crop(image, rects[i]) for i in todo])
        for i, r in zip(todo, readings, strict=True):
            args = (r, rects[i][2] / max(rects[i][3], 1e-6), self.config,
                    np.inf if frame_h is None else frame_h[i])
            ok, why = plate_reading_ok(*args)
            # a reading without a digit: a vanity plate when the line looks like a plate
            if (not ok and why == "no digit" and self.config.no_digit_look
                    and plate_look(look_crop(image, rects[i]), self.config)[0]):
                ok, why = plate_reading_ok(*args, looks_plate=True)
            out[i] = (ok, why, r)
        return out
