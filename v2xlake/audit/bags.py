"""Rosbags (ROS 1 ``.bag``, ROS 2 ``.db3`` / ``.mcap``): every message walked for absolute
time, latitude / longitude, text and point fields; the images they carry join the images
the detector re-checks."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from v2xlake.audit.points import scan_points
from v2xlake.audit.report import Finding
from v2xlake.audit.rules import EPOCH_HI_S, EPOCH_LO_S, LATLON_NAME, epoch_unit, scan_text


@dataclass(frozen=True)
class BagImage:
    """One Image / CompressedImage message of a bag, for the detector re-check."""

    bag: str  # local path of the bag (file or rosbag2 folder)
    topic: str
    index: int  # n-th message on the topic
    location: str


_PF_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


def _cloud_columns(msg: Any) -> dict[str, np.ndarray]:
    """The fields of a ``sensor_msgs/PointCloud2`` as arrays."""
    step = int(msg.point_step)
    raw = np.ascontiguousarray(np.asarray(msg.data, dtype=np.uint8))
    n = raw.size // step if step else 0
    bo = ">" if msg.is_bigendian else "<"
    names, fmts, offs = [], [], []
    for f in msg.fields:
        t = _PF_TYPES.get(int(f.datatype))
        if t and f.name not in names and int(f.offset) + np.dtype(t).itemsize <= step:
            names.append(f.name)
            fmts.append(bo + t)
            offs.append(int(f.offset))
    if not names or n == 0:
        return {}
    dt = np.dtype({"names": names, "formats": fmts, "offsets": offs, "itemsize": step})
    rec = raw[: n * step].view(dt)
    return {name: rec[name] for name in names}


def _walk_msg(obj: Any, path: str, stamps: list[tuple[str, int]], names: set[str],
              strings: set[str], depth: int = 0) -> None:
    """Collect Time stamps (path, sec), lat/lon-named numeric fields and strings of a
    deserialized message (rosbags messages are dataclasses; number arrays are numpy)."""
    fields = getattr(obj, "__dataclass_fields__", None)
    if not fields or depth > 12:
        return
    if "sec" in fields and "nanosec" in fields:
        stamps.append((path or "stamp", int(obj.sec)))
        return
    for n in fields:
        v = getattr(obj, n)
        p = f"{path}.{n}" if path else n
        if isinstance(v, str):
            strings.add(v)
        elif isinstance(v, bool):
            continue
        elif isinstance(v, int | float | np.ndarray):
            if LATLON_NAME.search(n):
                names.add(p)
        elif isinstance(v, list):
            for x in v[:10000]:
                if isinstance(x, str):
                    strings.add(x)
                else:
                    _walk_msg(x, f"{p}[]", stamps, names, strings, depth + 1)
        else:
            _walk_msg(v, p, stamps, names, strings, depth + 1)


def _open_bag(path: Path) -> Any:
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    # bags without embedded definitions (older sqlite3 rosbag2) decode with the ROS 2 set
    return AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))


def scan_bag(path: Path, where: str) -> tuple[list[Finding], list[BagImage]]:
    """Findings of one bag (file or rosbag2 folder) and its image messages. A bag that
    cannot be opened or read through is an ``unreadable`` finding."""
    out: list[Finding] = []
    images: list[BagImage] = []
    flagged: set[tuple[str, str]] = set()

    def flag(kind: str, topic: str, detail: str) -> None:
        if (kind, topic) not in flagged:
            flagged.add((kind, topic))
            out.append(Finding(kind, f"{where}:{topic}", detail))

    try:
        with _open_bag(path) as r:
            counts: dict[str, int] = {}
            log_hit: int | None = None
            for con, t, raw in r.messages():
                topic, typ = con.topic, con.msgtype
                k = counts.get(topic, 0)
                counts[topic] = k + 1
                if log_hit is None and epoch_unit(float(t), float(t), "t_ns") is not None:
                    log_hit = int(t)
                if typ.endswith(("/Image", "/CompressedImage")):
                    images.append(BagImage(str(path), topic, k, f"{where}:{topic}[{k}]"))
                if typ.endswith("/NavSatFix"):
                    flag("latlon", topic, f"{typ} messages: GNSS latitude/longitude")
                msg = r.deserialize(raw, typ)
                stamps: list[tuple[str, int]] = []
                names: set[str] = set()
                strings: set[str] = set()
                _walk_msg(msg, "", stamps, names, strings)
                for p, sec in stamps:
                    if EPOCH_LO_S <= sec <= EPOCH_HI_S:
                        flag("absolute_time", topic, f"{typ} {p}.sec = {sec}: an epoch time")
                        break
                for p in sorted(names):
                    flag("latlon", topic, f"{typ} field {p}: latitude/longitude")
                if strings and ("absolute_time", topic) not in flagged:
                    for f in scan_text("\n".join(sorted(strings)).encode(), f"{where}:{topic}"):
                        flag(f.kind, topic, f"{typ} string: {f.detail}")
                if typ.endswith("/PointCloud2") and ("absolute_time", topic) not in flagged:
                    for f in scan_points(_cloud_columns(msg), f"{where}:{topic}"):
                        flag(f.kind, topic, f"{typ} {f.location.rsplit(':', 1)[-1]}: "
                                            f"{f.detail}")
            if log_hit is not None:
                out.append(Finding("absolute_time", where,
                                   f"message log time {log_hit} ns is an epoch time"))
    except Exception as e:
        return [Finding("unreadable", where,
                        f"bag cannot be scanned: {type(e).__name__}: {e}")], []
    return out, images


def _decode_ros_image(msg: Any, typ: str) -> np.ndarray | None:
    """A decoded Image / CompressedImage message (BGR or mono), None if it does not decode."""
    import cv2

    data = np.asarray(msg.data, dtype=np.uint8).tobytes()
    if typ.endswith("/CompressedImage"):
        return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    enc = str(msg.encoding).lower()
    table = {"mono8": ("u1", 1), "8uc1": ("u1", 1), "mono16": ("u2", 1), "16uc1": ("u2", 1),
             "bgr8": ("u1", 3), "rgb8": ("u1", 3), "8uc3": ("u1", 3), "bgra8": ("u1", 4),
             "rgba8": ("u1", 4), "8uc4": ("u1", 4)}
    if enc not in table:
        return None
    t, ch = table[enc]
    dt = np.dtype((">" if msg.is_bigendian else "<") + t)
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if step * h > len(data) or w * ch * dt.itemsize > step:
        return None
    rows = np.frombuffer(data[: step * h], np.uint8).reshape(h, step)[:, : w * ch * dt.itemsize]
    img = np.ascontiguousarray(rows).view(dt).reshape(h, w, ch).astype(dt.newbyteorder("="))
    if ch == 1:
        return img[:, :, 0]
    if enc.startswith("rgb"):
        return cv2.cvtColor(img, cv2.COLOR_RGB2BGR if ch == 3 else cv2.COLOR_RGBA2BGRA)
    return img


def read_bag_images(refs: Sequence[BagImage]) -> dict[BagImage, np.ndarray | None]:
    """The sampled image messages, each bag read through once."""
    out: dict[BagImage, np.ndarray | None] = dict.fromkeys(refs)
    for bag in sorted({r.bag for r in refs}):
        want = {(r.topic, r.index): r for r in refs if r.bag == bag}
        topics = {t for t, _ in want}
        try:
            with _open_bag(Path(bag)) as rd:
                cons = [c for c in rd.connections if c.topic in topics]
                counts: dict[str, int] = {}
                for con, _, raw in rd.messages(connections=cons):
                    k = counts.get(con.topic, 0)
                    counts[con.topic] = k + 1
                    ref = want.get((con.topic, k))
                    if ref is not None:
                        out[ref] = _decode_ros_image(rd.deserialize(raw, con.msgtype),
                                                     con.msgtype)
        except Exception:
            continue  # left None: reported as "does not decode"
    return out
