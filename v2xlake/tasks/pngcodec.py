"""Lossless PNG encoding and decoding, one definition for every stage that writes camera
frames (ingest, anonymize, exports, the simulator).

Why these settings: libpng's default tries every row filter on every row and zlib's default
strategy then searches for matches; both cost far more than they save. Rows filtered with UP
and compressed with zlib's RLE strategy give the same pixels, smaller files and twice the
speed. Measured on the real 1080p street photo of ``tests/bench/bench_ingest.py`` (camera
case), per frame:

- zlib level 1, defaults: 95 ms, 2.20 MB;
- level 6, defaults: 390 ms, 1.99 MB;
- UP + RLE: 46 ms, 2.12 MB;
- PAETH + RLE: 63 ms, 1.90 MB.

With RLE the zlib level hardly changes size or time, so ``level`` stays only for the
configs that expose it.

Where the ``isal`` package (Intel's ISA-L deflate) is installed, the same UP-filtered rows
are written and read here (NumPy filters the rows, ISA-L deflates / inflates them), because
the system zlib that OpenCV links is the cost of both: on a simulated 1080p frame zlib's
inflate took 18.4 of imdecode's 27 ms (ISA-L: 4.2 ms) and zlib's RLE deflate 17.7 ms
(ISA-L level 1: 1.3 ms, 54 instead of 71 kB). The pixels are the same either way; the bytes
differ. Streams this module does not write the same way (other filters, interlacing,
palettes, transparency keys, 1-4 bit depths) are decoded by OpenCV.
"""

from __future__ import annotations

import struct
import zlib
from typing import Any

import cv2
import numpy as np

_deflate: Any
try:  # optional: the fast path (same pixels), OpenCV otherwise
    from isal import isal_zlib as _deflate
except ImportError:  # pragma: no cover - depends on the environment
    _deflate = None

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_COLOR_TYPES = {1: 0, 3: 2, 4: 6}  # channels -> PNG colour type (grey, RGB, RGBA)
_CHANNELS = {0: 1, 2: 3, 6: 4}
# chunks a frame may carry that do not change its pixels as OpenCV reads them
_PASSIVE = frozenset({b"tEXt", b"zTXt", b"iTXt", b"tIME", b"eXIf", b"iCCP", b"pHYs"})
_UP = 2


def png_chunks(data: bytes) -> list[tuple[bytes, bytes]]:
    """(type, payload) of every chunk up to IEND; raises ValueError on a malformed stream."""
    if not data.startswith(PNG_SIGNATURE):
        raise ValueError("not a PNG (bad signature)")
    out = []
    pos = len(PNG_SIGNATURE)
    while pos + 8 <= len(data):
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        ctype = data[pos + 4 : pos + 8]
        end = pos + 12 + length
        if end > len(data):
            raise ValueError(f"truncated PNG chunk {ctype!r}")
        out.append((ctype, data[pos + 8 : pos + 8 + length]))
        pos = end
        if ctype == b"IEND":
            break
    return out


def build_png(chunks: list[tuple[bytes, bytes]]) -> bytes:
    """The PNG stream of ``chunks`` ((type, payload), in order), each with its CRC."""
    parts = [PNG_SIGNATURE]
    for ctype, payload in chunks:
        crc = zlib.crc32(ctype + payload) & 0xFFFFFFFF
        parts.append(struct.pack(">I", len(payload)) + ctype + payload + struct.pack(">I", crc))
    return b"".join(parts)


def encode_png(img: np.ndarray, level: int = 1) -> bytes:
    """``img`` (OpenCV layout: BGR / BGRA / mono, 8 or 16 bit) as PNG bytes."""
    if _deflate is not None and img.dtype in (np.uint8, np.uint16) and (
            img.ndim == 2 or (img.ndim == 3 and img.shape[2] in _COLOR_TYPES)):
        return _encode_up(img, level)
    ok, buf = cv2.imencode(".png", img, [
        cv2.IMWRITE_PNG_COMPRESSION, int(level),
        cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE,
        cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_UP])
    if not ok:
        raise ValueError(f"PNG encoding failed for an image of shape {img.shape}, {img.dtype}")
    return bytes(buf.tobytes())


def _encode_up(img: np.ndarray, level: int) -> bytes:
    """IHDR, one IDAT, IEND: rows filtered with UP (a byte minus the byte above, modulo
    256), deflated by ISA-L at ``level`` (0-3; zlib's levels above 3 mean 3)."""
    h, w = img.shape[:2]
    ch = 1 if img.ndim == 2 else img.shape[2]
    if ch == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    elif ch == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGBA)
    depth = 8 * img.dtype.itemsize
    data = np.ascontiguousarray(img, ">u2" if depth == 16 else np.uint8)
    rows = data.view(np.uint8).reshape(h, -1)
    filt = np.empty((h, rows.shape[1] + 1), np.uint8)
    filt[:, 0] = _UP
    filt[0, 1:] = rows[0]
    np.subtract(rows[1:], rows[:-1], out=filt[1:, 1:])
    idat = _deflate.compress(filt, min(max(int(level), 0), 3))
    ihdr = struct.pack(">IIBBBBB", w, h, depth, _COLOR_TYPES[ch], 0, 0, 0)
    return build_png([(b"IHDR", ihdr), (b"IDAT", idat), (b"IEND", b"")])


def decode_png(data: bytes) -> np.ndarray | None:
    """PNG bytes as ``cv2.imdecode(..., IMREAD_UNCHANGED)`` gives them (BGR / BGRA / mono,
    8 or 16 bit); None where OpenCV cannot decode them."""
    if _deflate is not None:
        img = _decode_up(data)
        if img is not None:
            return img
    return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)


def _decode_up(data: bytes) -> np.ndarray | None:
    """The fast path: 8 / 16-bit grey, RGB or RGBA, not interlaced, every row filtered with
    UP or not at all (what ``encode_png`` writes); None for anything else."""
    try:
        chunks = png_chunks(data)
    except ValueError:
        return None
    idat, ihdr = [], b""
    for ctype, payload in chunks:
        if ctype == b"IHDR":
            ihdr = payload
        elif ctype == b"IDAT":
            idat.append(payload)
        elif ctype != b"IEND" and ctype not in _PASSIVE:
            return None
    if len(ihdr) != 13 or not idat:
        return None
    w, h, depth, ctype_, comp, filt_m, interlace = struct.unpack(">IIBBBBB", ihdr)
    if (depth not in (8, 16) or ctype_ not in _CHANNELS or comp or filt_m or interlace
            or w == 0 or h == 0):
        return None
    ch = _CHANNELS[ctype_]
    row = w * ch * depth // 8
    try:
        # the output size is known: one buffer, not one grown from 16 kB
        raw = _deflate.decompress(b"".join(idat), bufsize=h * (row + 1))
    except Exception:  # a damaged stream: OpenCV decides (and reports)
        return None
    if len(raw) != h * (row + 1):
        return None
    a = np.frombuffer(raw, np.uint8).reshape(h, row + 1)
    f = a[:, 0]
    if not np.isin(f, (0, _UP)).all():
        return None
    px = np.empty((h, row), np.uint8)
    px[0] = a[0, 1:]  # the first row has no row above: UP leaves it as it is
    for i, up in enumerate(f[1:].tolist(), 1):  # UP: the byte above added (rows in order)
        if up:
            np.add(px[i - 1], a[i, 1:], out=px[i])
        else:
            px[i] = a[i, 1:]
    img = (px.view(">u2").astype(np.uint16) if depth == 16 else px).reshape(h, w, ch)
    if ch == 1:
        return img[:, :, 0]
    return cv2.cvtColor(img, cv2.COLOR_RGB2BGR if ch == 3 else cv2.COLOR_RGBA2BGRA)
