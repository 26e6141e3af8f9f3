"""One camera image in, one anonymized PNG out, plus what was blurred (never the pixels).

The output PNG carries only the chunks needed to decode it (IHDR, PLTE, tRNS, IDAT, IEND):
text chunks, EXIF, timestamps (tIME), ICC profiles and any private chunk a camera driver may
have written are dropped, because any of them can hold a time, a place or a serial number.
PNG chunks are parsed directly (``pngcodec.png_chunks``: no imaging library decides what to
keep).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from v2xlake.tasks import pngcodec
from v2xlake.tasks.anonymize.blur import BlurConfig, blur_boxes
from v2xlake.tasks.anonymize.detectors import Detection, Detector
from v2xlake.tasks.pngcodec import PNG_SIGNATURE, build_png, png_chunks

CRITICAL_CHUNKS = frozenset({b"IHDR", b"PLTE", b"tRNS", b"IDAT", b"IEND"})
METADATA_CHUNKS = frozenset({b"tEXt", b"zTXt", b"iTXt", b"eXIf", b"tIME", b"iCCP"})


def strip_png_metadata(data: bytes) -> bytes:
    """Keep only the chunks needed to decode the image."""
    return build_png([(t, p) for t, p in png_chunks(data) if t in CRITICAL_CHUNKS])


def encode_png(img: np.ndarray, compression: int = 1) -> bytes:
    """PNG bytes (``v2xlake.tasks.pngcodec``) with no metadata chunks."""
    return strip_png_metadata(pngcodec.encode_png(img, compression))


def encode_jpeg(img: np.ndarray, quality: int = 95) -> bytes:
    """Baseline JPEG (JFIF header only: OpenCV writes no EXIF, comment or other segment)."""
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError("image could not be encoded as JPEG")
    return buf.tobytes()


def encode_image(img: np.ndarray, fmt: str, png_compression: int = 1, jpeg_quality: int = 95
                 ) -> bytes:
    """``fmt`` "png" (lossless, no metadata chunks) or "jpeg"."""
    return encode_jpeg(img, jpeg_quality) if fmt == "jpeg" else encode_png(img, png_compression)


def decode_image(data: bytes) -> np.ndarray:
    """PNG (``pngcodec.decode_png``: its fast path where it applies) or any other format
    OpenCV reads, as ``cv2.imdecode(..., IMREAD_UNCHANGED)`` gives it."""
    img = (pngcodec.decode_png(data) if data.startswith(PNG_SIGNATURE)
           else cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED))
    if img is None:
        raise ValueError("image could not be decoded")
    return img


def to_bgr8(img: np.ndarray) -> np.ndarray:
    """An 8-bit 3-channel view for the detectors (mono, 16-bit and BGRA cameras exist)."""
    if img.dtype != np.uint8:
        img = (img / max(float(img.max()), 1.0) * 255.0).astype(np.uint8)
    if img.ndim == 2:
        return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    if img.shape[2] == 4:
        return cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    return img


@dataclass(frozen=True)
class AnonymizedImage:
    png: bytes
    width: int
    height: int
    detections: list[Detection]


def anonymize_array(
    img: np.ndarray, detector: Detector, blur: BlurConfig | None = None
) -> tuple[np.ndarray, list[Detection]]:
    """Detect on an 8-bit view, blur the original pixels (any depth/channels); returns a copy."""
    dets = detector.detect(to_bgr8(img))
    out = img.copy()
    blur_boxes(out, [d.box for d in dets], blur, [d.kind for d in dets])
    return out, dets


def anonymize_png(
    data: bytes, detector: Detector, blur: BlurConfig | None = None, compression: int = 1
) -> AnonymizedImage:
    img = decode_image(data)
    out, dets = anonymize_array(img, detector, blur)
    return AnonymizedImage(encode_png(out, compression), img.shape[1], img.shape[0], dets)
