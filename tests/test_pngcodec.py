"""v2xlake.tasks.pngcodec: lossless for every layout the stages write, and on a real street photo no
larger than libpng's defaults (the claim its docstring makes; its speed is benchmarked in
tests/bench/bench_ingest.py, not asserted here)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.fixtures.real import requires_real_data
from v2xlake.tasks.anonymize.images import png_chunks
from v2xlake.tasks.pngcodec import decode_png, encode_png

STREET = (Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "images"
          / "street_plate_small_pjlab_0.png")


@pytest.mark.parametrize(("shape", "dtype"), [
    ((31, 17, 3), np.uint8), ((31, 17, 4), np.uint8), ((31, 17), np.uint8),
    ((31, 17), np.uint16), ((31, 17, 3), np.uint16),
])
def test_lossless(shape: tuple[int, ...], dtype: type) -> None:
    img = np.random.default_rng(3).integers(0, np.iinfo(dtype).max, shape, dtype=dtype)
    png = encode_png(img)
    back = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
    assert back is not None and back.dtype == img.dtype and np.array_equal(back, img)
    # read back as OpenCV reads it, both what is written here (the ISA-L path where isal is
    # installed) and libpng's own choice of row filters (OpenCV decodes those)
    mine = decode_png(png)
    assert mine is not None and mine.dtype == img.dtype and np.array_equal(mine, img)
    other = cv2.imencode(".png", img)[1].tobytes()
    assert np.array_equal(decode_png(other), img)
    assert {t for t, _ in png_chunks(png)} <= {b"IHDR", b"IDAT", b"IEND"}


@requires_real_data("images/street_plate_small_pjlab_0.png")
def test_real_photo_lossless_and_not_larger_than_libpng_defaults() -> None:
    img = cv2.imread(str(STREET), cv2.IMREAD_COLOR)
    assert img is not None
    png = encode_png(img)
    back = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
    assert back is not None and np.array_equal(back, img)
    default = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, 1])[1]
    assert len(png) <= default.size
