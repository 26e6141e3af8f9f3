"""Tab. 4 metrics: average IoU, Recall@IoU 0.3/0.5/0.7, mean centre offset (px).

A truth box whose projection is missing (behind the camera, outside the image) counts with
IoU 0 and is left out of the centre offset: a method that loses an object is penalised in
IoU and recall, not rewarded with an undefined offset.
"""

from __future__ import annotations

import numpy as np

RECALL_THRESHOLDS = (0.3, 0.5, 0.7)


def center_offset_px(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Paired distance between box centres in pixels; NaN where either box is missing."""
    a = np.asarray(a, dtype=np.float64).reshape(-1, 4)
    b = np.asarray(b, dtype=np.float64).reshape(-1, 4)
    ca = np.stack([(a[:, 0] + a[:, 2]) / 2, (a[:, 1] + a[:, 3]) / 2], axis=1)
    cb = np.stack([(b[:, 0] + b[:, 2]) / 2, (b[:, 1] + b[:, 3]) / 2], axis=1)
    return np.asarray(np.linalg.norm(ca - cb, axis=1))


def summarize(iou: np.ndarray, offset: np.ndarray) -> dict[str, float]:
    """Tab. 4 row from per-box IoU and centre offset (NaN offsets are ignored)."""
    iou = np.asarray(iou, dtype=np.float64)
    offset = np.asarray(offset, dtype=np.float64)
    n = int(iou.size)
    out: dict[str, float] = {"n_boxes": float(n)}
    out["mean_iou"] = float(iou.mean()) if n else float("nan")
    for t in RECALL_THRESHOLDS:
        out[f"recall@{t:.1f}"] = float((iou >= t).mean()) if n else float("nan")
    finite = offset[np.isfinite(offset)]
    out["center_offset_px"] = float(finite.mean()) if finite.size else float("nan")
    out["n_missing"] = float(n - finite.size)
    return out
