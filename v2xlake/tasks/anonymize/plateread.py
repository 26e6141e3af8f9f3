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
                     frame_h: float = np.inf) -> tuple[bool, str]:
    """(is a plate, why not): the judgement of one reading of a line ``aspect`` (long / short
    side) wide and ``frame_h`` px high in the frame. A line lower than ``small_h`` (a plate
    ~30 px wide) is read with every symbol from ``small_char_conf`` and no mean confidence:
    real 30 px plates pasted into real streets were found by the detector and then rejected
    by their reading 24 times in 38 misses ('14981' at 0.44, '8AT' at 0.22-0.27, 'POKE'
    at 0.44), while the lettering around plates that small reads as sure words (CITROEN,
    NORTH, HOLT at 0.94-1.0): there a reading without a digit is rejected only when its
    plate symbols reach ``min_conf``; the word, share, date and repeat rules still apply."""
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
    if (sum(ch.isdigit() for ch in text) < cfg.min_digits
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
            ok, why = plate_reading_ok(r, rects[i][2] / max(rects[i][3], 1e-6), self.config,
                                       np.inf if frame_h is None else frame_h[i])
            out[i] = (ok, why, r)
        return out
