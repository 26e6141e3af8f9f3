"""Sensor calibration: ``/tf_static`` chains, ``CameraInfo`` and clip.yaml overrides.

Precedence (most explicit first): an ``extrinsic`` / ``intrinsics`` written in clip.yaml,
then the bag's ``tf_static`` tree (looked up from the agent's ``ego_frame`` to the sensor's
frame, through any chain of parents and children) and its ``CameraInfo``. A LiDAR or camera
with no calibration from either source is an error: a sensor with an unknown pose would
silently corrupt every later geometric stage.
"""

from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np

from v2xlake.schemas.calibration import CameraIntrinsics, DistortionModel
from v2xlake.schemas.geometry import Transform
from v2xlake.tasks.geometry import invert


class TfTree:
    """Static transforms as an undirected graph; ``lookup(a, b)`` returns ``T_a_b``.

    A rotation whose quaternion is not unit within ``quat_tolerance`` is refused (ValueError
    naming the transform): normalising it silently would turn a typo in a calibration into
    a mis-calibration of tens of degrees."""

    def __init__(self, quat_tolerance: float) -> None:
        self.edges: dict[str, dict[str, np.ndarray]] = {}
        self.quat_tolerance = quat_tolerance

    def add(self, parent: str, child: str, T_parent_child: np.ndarray) -> None:
        parent, child = parent.lstrip("/"), child.lstrip("/")
        self.edges.setdefault(parent, {})[child] = T_parent_child
        self.edges.setdefault(child, {})[parent] = invert(T_parent_child)

    def add_message(self, msg: Any) -> None:
        for ts in msg.transforms:
            t, q = ts.transform.translation, ts.transform.rotation
            qn = np.array([q.w, q.x, q.y, q.z], dtype=np.float64)
            norm = float(np.linalg.norm(qn))
            if not np.isfinite(norm) or abs(norm - 1.0) > self.quat_tolerance:
                raise ValueError(
                    f"transform {ts.header.frame_id} -> {ts.child_frame_id}: rotation "
                    f"quaternion (w, x, y, z) {qn.tolist()} has norm {norm:.6f}, not 1 "
                    f"(tolerance {self.quat_tolerance:g}); refusing to normalise it")
            qn /= norm
            m = Transform(translation=[t.x, t.y, t.z], rotation=qn.tolist()).matrix()
            self.add(ts.header.frame_id, ts.child_frame_id, m)

    @property
    def frames(self) -> list[str]:
        return sorted(self.edges)

    def lookup(self, target: str, source: str) -> np.ndarray | None:
        """``T_target_source`` (maps points in ``source`` into ``target``) or None."""
        target, source = target.lstrip("/"), source.lstrip("/")
        if target == source:
            return np.eye(4)
        prev: dict[str, tuple[str, np.ndarray]] = {}
        seen, todo = {target}, deque([target])
        while todo:
            a = todo.popleft()
            for b, T_a_b in self.edges.get(a, {}).items():
                if b in seen:
                    continue
                seen.add(b)
                prev[b] = (a, T_a_b)
                if b == source:
                    T = np.eye(4)
                    node = b
                    while node != target:
                        parent, T_p_n = prev[node]
                        T = T_p_n @ T
                        node = parent
                    return T
                todo.append(b)
        return None


_DIST = {"": DistortionModel.NONE, "none": DistortionModel.NONE,
         "plumb_bob": DistortionModel.PLUMB_BOB,
         "rational_polynomial": DistortionModel.RATIONAL_POLYNOMIAL,
         "equidistant": DistortionModel.EQUIDISTANT, "fisheye": DistortionModel.EQUIDISTANT}


def intrinsics_from_camera_info(msg: Any) -> CameraIntrinsics:
    """ROS 2 (``k``, ``d``) or ROS 1 (``K``, ``D``) CameraInfo -> validated intrinsics."""
    k = np.asarray(getattr(msg, "k", getattr(msg, "K", None)), dtype=np.float64).reshape(3, 3)
    d = [float(v) for v in getattr(msg, "d", getattr(msg, "D", []))]
    name = str(msg.distortion_model)
    model = _DIST.get(name)
    if model is None:
        raise ValueError(f"unknown CameraInfo distortion_model {name!r}")
    if model is DistortionModel.NONE and not any(d):
        d = []
    if model is DistortionModel.PLUMB_BOB and len(d) > 5 and not any(d[5:]):
        d = d[:5]
    return CameraIntrinsics(width=int(msg.width), height=int(msg.height), fx=float(k[0, 0]),
                            fy=float(k[1, 1]), cx=float(k[0, 2]), cy=float(k[1, 2]),
                            distortion_model=model, distortion=d)
