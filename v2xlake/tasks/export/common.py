"""What every export shares besides the clean-zone reader (``tasks/reader.py``): tokens,
output file records, atomic file writes, camera undistortion, progress steps.

Tokens are deterministic (uuid5 of a readable name) so that re-exporting a clip gives
byte-identical tables and a token can be recomputed from the names alone.
"""

from __future__ import annotations

import contextlib
import os
import uuid
from collections.abc import Callable, Iterator
from contextvars import ContextVar
from pathlib import Path

import numpy as np

from v2xlake.schemas.stage import OutputFile
from v2xlake.storage import checksum
from v2xlake.storage.reader import CameraCalib
from v2xlake.tasks.pngcodec import encode_png

__all__ = ["ExportStep", "Undistorter", "export_progress", "file_output", "report_step", "token",
           "write_atomic"]

_NAMESPACE = uuid.UUID("6f1b2c1e-3f55-5d1c-9a7e-7632786c616b")  # "v2xlake" export namespace


def token(*parts: object) -> str:
    """32-hex deterministic token from readable parts (uuid5), as nuScenes tokens look."""
    return uuid.uuid5(_NAMESPACE, "/".join(str(p) for p in parts)).hex


def write_atomic(path: Path, data: bytes | memoryview) -> None:
    """Write a file under a hidden temporary name in its own directory, then rename it into
    place: a killed or failed export never leaves a truncated file that a dataset loader
    would read as a short scan (the temporary is removed on failure)."""
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}-{uuid.uuid4().hex}")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.remove(tmp)
        raise


ExportStep = Callable[[str, int, "int | None"], None]
"""``(what, done, total)``: ``done`` of ``total`` units (clips, images, scans; ``total`` None
when not known in advance, e.g. a bag's messages) of the step named ``what``."""

_PROGRESS: ContextVar[ExportStep | None] = ContextVar("v2xlake_export_progress", default=None)


@contextlib.contextmanager
def export_progress(hook: ExportStep) -> Iterator[None]:
    """Within the block, every :func:`report_step` of an exporter reaches ``hook``.

    WHY a context variable and not a parameter: exports run for minutes, and the CLI (a bar
    on a terminal, plain lines in a pipe or CI log) is only one of their callers; release
    builds and tests call the same functions with no one listening, and no exporter's
    signature changes."""
    token = _PROGRESS.set(hook)
    try:
        yield
    finally:
        _PROGRESS.reset(token)


def report_step(what: str, done: int, total: int | None = None) -> None:
    """An exporter's progress: ``done`` units of the step ``what`` finished (call it per
    unit; the listener decides how often to show it). Nothing when no one listens."""
    hook = _PROGRESS.get()
    if hook is not None:
        hook(what, done, total)


def file_output(path: Path, rows: int | None = None) -> OutputFile:
    return OutputFile(path=str(path), rows=rows, checksum=checksum.of_file(path))


class Undistorter:
    """Undistort one camera's images to a pinhole model with a new K (computed once).

    ``alpha=0`` keeps only valid pixels (no black borders), the convention of COLMAP's and
    ETH3D's undistorted images. A camera without distortion passes through unchanged.
    """

    def __init__(self, cam: CameraCalib, alpha: float = 0.0) -> None:
        import cv2

        self.cam = cam
        size = (cam.width, cam.height)
        d = np.asarray(cam.distortion, dtype=np.float64)
        self.identity = cam.distortion_model == "none" or not np.any(d)
        if self.identity:
            self.K = cam.K.copy()
            self.maps = None
            return
        if cam.distortion_model == "equidistant":
            self.K = cv2.fisheye.estimateNewCameraMatrixForUndistortRectify(
                cam.K, d[:4], size, np.eye(3), balance=alpha)
            self.maps = cv2.fisheye.initUndistortRectifyMap(cam.K, d[:4], np.eye(3), self.K,
                                                            size, cv2.CV_32FC1)
        else:
            self.K, _ = cv2.getOptimalNewCameraMatrix(cam.K, d, size, alpha, size)
            self.maps = cv2.initUndistortRectifyMap(cam.K, d, None, self.K, size, cv2.CV_32FC1)

    def __call__(self, img: np.ndarray) -> np.ndarray:
        import cv2

        if self.maps is None:
            return img
        return cv2.remap(img, self.maps[0], self.maps[1], cv2.INTER_LINEAR)

    def png(self, data: bytes) -> bytes:
        """Undistorted PNG bytes (the input bytes themselves if nothing to undo)."""
        import cv2

        if self.maps is None:
            return data
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise ValueError("cannot decode image")
        return encode_png(self(img))
