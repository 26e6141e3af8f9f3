"""Camera messages -> image blobs of the raw zone.

A ``CompressedImage`` in JPEG or PNG is kept byte for byte, as delivered (re-encoding a JPEG
to PNG made the raw zone 21x the delivered size and gained nothing: the pixels are the
JPEG's either way); its size is read from the stream's header without decoding. Other
compressed formats are decoded once and stored as PNG. Raw ``Image`` messages are laid out
from ``encoding``/``step`` (row padding dropped), Bayer mosaics are demosaiced so downstream
detectors see colour, and stored as lossless PNG. Every later stage reads a blob through one
decoder (``cv2.imdecode``), whatever its format.
"""

from __future__ import annotations

import struct
from typing import Any

import cv2
import numpy as np

from v2xlake.tasks.pngcodec import PNG_SIGNATURE, encode_png

JPEG_MAGIC = b"\xff\xd8\xff"
# JPEG start-of-frame markers (baseline, progressive, lossless, arithmetic): carry the size
_SOF = frozenset({0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF})

_BAYER = {
    "bayer_rggb8": cv2.COLOR_BayerBG2BGR, "bayer_bggr8": cv2.COLOR_BayerRG2BGR,
    "bayer_gbrg8": cv2.COLOR_BayerGR2BGR, "bayer_grbg8": cv2.COLOR_BayerGB2BGR,
}
# encoding -> (numpy dtype, channels, cv2 conversion to BGR/mono or None)
_RAW: dict[str, tuple[str, int, int | None]] = {
    "rgb8": ("u1", 3, cv2.COLOR_RGB2BGR), "bgr8": ("u1", 3, None),
    "rgba8": ("u1", 4, cv2.COLOR_RGBA2BGRA), "bgra8": ("u1", 4, None),
    "mono8": ("u1", 1, None), "8UC1": ("u1", 1, None), "8UC3": ("u1", 3, None),
    "mono16": ("u2", 1, None), "16UC1": ("u2", 1, None),
}


def png_size(data: bytes) -> tuple[int, int]:
    """(width, height) from the PNG IHDR chunk, without decoding pixels."""
    if not data.startswith(PNG_SIGNATURE) or data[12:16] != b"IHDR":
        raise ValueError("not a PNG stream")
    w, h = struct.unpack(">II", data[16:24])
    return int(w), int(h)


def jpeg_size(data: bytes) -> tuple[int, int]:
    """(width, height) from a JPEG's start-of-frame segment, without decoding pixels."""
    if not data.startswith(JPEG_MAGIC):
        raise ValueError("not a JPEG stream")
    pos = 2
    while pos + 4 <= len(data):
        if data[pos] != 0xFF:
            raise ValueError(f"JPEG marker expected at byte {pos}")
        marker = data[pos + 1]
        if marker == 0xFF:  # fill byte
            pos += 1
            continue
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:  # no length
            pos += 2
            continue
        (length,) = struct.unpack(">H", data[pos + 2:pos + 4])
        if marker in _SOF:
            if pos + 9 > len(data):
                break
            h, w = struct.unpack(">HH", data[pos + 5:pos + 9])
            if w == 0 or h == 0:
                raise ValueError(f"JPEG frame header gives size {w}x{h}")
            return int(w), int(h)
        if marker in (0xD9, 0xDA):  # end of image / start of scan before any frame header
            break
        pos += 2 + length
    raise ValueError("JPEG stream has no frame header (truncated?)")


def compressed_image(msg: Any, level: int = 1) -> tuple[bytes, int, int]:
    """A ``CompressedImage`` as (bytes to store, width, height): JPEG and PNG as delivered
    (their headers must give a size; the stages that need pixels decode them), anything
    else decoded and stored as PNG."""
    data = bytes(np.asarray(msg.data, dtype=np.uint8).tobytes())
    if data.startswith(PNG_SIGNATURE):
        w, h = png_size(data)
        return data, w, h
    if data.startswith(JPEG_MAGIC):
        w, h = jpeg_size(data)
        return data, w, h
    return compressed_to_png(msg, level)


def compressed_to_png(msg: Any, level: int = 1) -> tuple[bytes, int, int]:
    """Decode any compressed frame and re-encode it as PNG (PNG input is kept as is)."""
    data = bytes(np.asarray(msg.data, dtype=np.uint8).tobytes())
    if data.startswith(PNG_SIGNATURE):
        w, h = png_size(data)
        return data, w, h
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"cannot decode CompressedImage with format {msg.format!r}")
    return encode_png(img, level), int(img.shape[1]), int(img.shape[0])


def image_to_array(msg: Any) -> np.ndarray:
    """A raw ``sensor_msgs/Image`` as an OpenCV array (BGR / BGRA / mono)."""
    enc = str(msg.encoding)
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    buf = np.asarray(msg.data, dtype=np.uint8)
    if enc in _BAYER:
        rows = buf[: h * step].reshape(h, step)[:, :w]
        return cv2.cvtColor(np.ascontiguousarray(rows), _BAYER[enc])
    if enc not in _RAW:
        raise ValueError(f"unsupported image encoding {enc!r}")
    code, ch, conv = _RAW[enc]
    dt = np.dtype((">" if msg.is_bigendian else "<") + code)
    rows = buf[: h * step].reshape(h, step)[:, : w * ch * dt.itemsize]
    img = np.ascontiguousarray(rows).view(dt).reshape(h, w, ch) if ch > 1 else \
        np.ascontiguousarray(rows).view(dt).reshape(h, w)
    img = img.astype(dt.newbyteorder("="), copy=False)
    return cv2.cvtColor(img, conv) if conv is not None else img


def image_to_png(msg: Any, level: int = 1) -> tuple[bytes, int, int]:
    img = image_to_array(msg)
    return encode_png(img, level), int(img.shape[1]), int(img.shape[0])
