"""Oriented 3D boxes as arrays: corners, rigid transforms, point membership.

Boxes follow ``v2xlake.schemas.annotation.Box3D``: ``size`` is (width, length, height) and the box's
x-axis is its length (heading). Everything here is vectorised over boxes (and points),
because a 128-beam scan has ~225k points and a busy frame dozens of boxes: a Python loop
over points would dominate the stage.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from v2xlake.tasks.geometry import BOX_EDGES, quat_to_matrix, transform_boxes

EDGES = BOX_EDGES  # corner pairs of box_corners' corners, for drawing


@dataclass(frozen=True)
class BoxArray:
    """M boxes in one frame. ``velocity`` rows are NaN where the annotation has none."""

    instance_id: np.ndarray  # (M,) str
    center: np.ndarray  # (M, 3)
    size: np.ndarray  # (M, 3) w, l, h
    quat: np.ndarray  # (M, 4) w, x, y, z
    t_ns: np.ndarray  # (M,) int64: time the box state refers to
    velocity: np.ndarray  # (M, 3) m/s in the same frame, NaN if unknown

    def __len__(self) -> int:
        return int(self.center.shape[0])

    def take(self, idx: np.ndarray) -> BoxArray:
        return BoxArray(
            self.instance_id[idx], self.center[idx], self.size[idx], self.quat[idx],
            self.t_ns[idx], self.velocity[idx],
        )

    def transformed(self, T: np.ndarray) -> BoxArray:
        """Same boxes expressed in another frame: ``T`` (4x4 or (M,4,4)) maps old -> new."""
        center, quat, vel = transform_boxes(T, self.center, self.quat, self.velocity)
        return replace(self, center=center, quat=quat, velocity=vel)

    def shifted(self, displacement: np.ndarray) -> BoxArray:
        return replace(self, center=self.center + displacement)


def yaw_of(quat: np.ndarray) -> np.ndarray:
    """Heading (rotation about z of the box x-axis) of each box, radians."""
    R = quat_to_matrix(quat)
    return np.arctan2(R[..., 1, 0], R[..., 0, 0])

