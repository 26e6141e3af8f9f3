"""Temporal consistency: a face or plate seen in the frames before and after, missed in one.

Why: a detector's score flickers around its threshold from frame to frame (motion blur, a
plate glinting, a head turning), and one frame in which a face stays sharp is enough to
identify the person in a 30 Hz video. When the same object is found in the previous and the
next frame of the same camera (same kind, moved at most ``match_factor`` times its size, of
similar size), the frame between gets the box interpolated at its own time, unless a
detection of that kind already covers it. Pure function of the detections and stamps.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from v2xlake.tasks.anonymize.detectors import Detection
from v2xlake.tasks.geometry import iou_xyxy

TEMPORAL = "temporal"


def _centre_size(b: Sequence[float]) -> tuple[float, float, float]:
    return (b[0] + b[2]) / 2, (b[1] + b[3]) / 2, max(b[2] - b[0], b[3] - b[1], 1e-6)


def fill_gaps(dets: Sequence[Sequence[Detection]], t_ns: Sequence[int], max_gap_ns: int,
              match_factor: float = 1.0, cover_iou: float = 0.2) -> list[list[Detection]]:
    """Detections to add to each frame (frames in time order, one camera)."""
    out: list[list[Detection]] = [[] for _ in dets]
    for i in range(1, len(dets) - 1):
        t0, t1, t2 = int(t_ns[i - 1]), int(t_ns[i]), int(t_ns[i + 1])
        if t2 - t0 > max_gap_ns or t2 <= t0:
            continue
        a = (t1 - t0) / (t2 - t0)
        for p in dets[i - 1]:
            px, py, ps = _centre_size(p.box)
            best, best_d = None, np.inf
            for q in dets[i + 1]:
                if q.kind != p.kind:
                    continue
                qx, qy, qs = _centre_size(q.box)
                d = float(np.hypot(qx - px, qy - py))
                similar = max(ps, qs) <= 2 * min(ps, qs)
                if similar and d <= match_factor * max(ps, qs) and d < best_d:
                    best, best_d = q, d
            if best is None:
                continue
            box = tuple(float((1 - a) * u + a * v) for u, v in zip(p.box, best.box, strict=True))
            same = [d.box for d in (*dets[i], *out[i]) if d.kind == p.kind]
            if same and (iou_xyxy(np.asarray(box), np.asarray(same)) >= cover_iou).any():
                continue
            out[i].append(Detection(p.kind, box, min(p.score, best.score), TEMPORAL))  # type: ignore[arg-type]
    return out
