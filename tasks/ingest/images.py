"""Camera messages -> lossless PNG bytes.

A ``CompressedImage`` already in PNG is kept byte for byte (re-encoding would cost time and
gain nothing); JPEG and other formats are decoded once and stored as PNG so that every later
stage (anonymization blurs, exports) starts from the same lossless pixels. Raw ``Image``
messages are laid out from ``encoding``/``step`` (row padding dropped), Bayer mosaics are
demosaiced so downstream detectors see colour.
"""

from __future__ import annotations

import struct
from typing import Any

import cv2
import numpy as np

from v2xlake.tasks.pngcodec import encode_png

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"

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
    if not data.startswith(PNG_MAGIC) or data[12:16] != b"IHDR":
        raise ValueError("not a PNG stream")
    w, h = struct.unpack(">II", data[16:24])
    return int(w), int(h)


def compressed_to_png(msg: Any, level: int = 1) -> tuple[bytes, int, int]:
    data = bytes(np.asarray(msg.data, dtype=np.uint8).tobytes())
    if data.startswith(PNG_MAGIC):
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
