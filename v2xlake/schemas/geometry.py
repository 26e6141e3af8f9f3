"""Rigid transforms as stored everywhere in v2xlake.

A transform named ``T_a_b`` maps points from frame ``b`` into frame ``a``. Rotations are unit
quaternions in (w, x, y, z) order (docs/architecture.md, Space). Validation lives here so that a bad
calibration is rejected where it enters, with the offending field named, instead of producing
a subtly sheared point cloud three stages later.
"""

from __future__ import annotations

from typing import Annotated

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

QUAT_NORM_TOL = 1e-6
ORTHO_TOL = 1e-6

Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]
Quat = Annotated[list[float], Field(min_length=4, max_length=4)]


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """(..., 4) w,x,y,z unit quaternions -> (..., 3, 3) rotation matrices."""
    q = np.asarray(q, dtype=np.float64)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    r = np.empty((*q.shape[:-1], 3, 3))
    r[..., 0, 0] = 1 - 2 * (y * y + z * z)
    r[..., 0, 1] = 2 * (x * y - w * z)
    r[..., 0, 2] = 2 * (x * z + w * y)
    r[..., 1, 0] = 2 * (x * y + w * z)
    r[..., 1, 1] = 1 - 2 * (x * x + z * z)
    r[..., 1, 2] = 2 * (y * z - w * x)
    r[..., 2, 0] = 2 * (x * z - w * y)
    r[..., 2, 1] = 2 * (y * z + w * x)
    r[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return r


def transform(translation: np.ndarray, quat_wxyz: np.ndarray) -> np.ndarray:
    """(..., 3) translations + (..., 4) unit quaternions (w, x, y, z) -> (..., 4, 4) ``T_a_b``.

    The stored form of a transform is (translation, quaternion); this is its one conversion
    to a matrix (``tasks.geometry`` re-exports it for every stage and export).
    """
    t = np.asarray(translation, dtype=np.float64)
    m = np.zeros((*t.shape[:-1], 4, 4))
    m[..., :3, :3] = quat_to_matrix(quat_wxyz)
    m[..., :3, 3] = t
    m[..., 3, 3] = 1.0
    return m


def matrix_to_quat(r: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices -> (..., 4) w,x,y,z with w >= 0 (canonical sign).

    Shepperd's method as SciPy's ``Rotation.from_matrix`` runs it (the largest of the four
    quaternion components is computed from the diagonal, the rest from off-diagonal sums,
    so no branch divides by a small number), in NumPy because schemas/ may not import
    SciPy; tests/test_geometry.py checks it against SciPy.
    """
    r = np.asarray(r, dtype=np.float64)
    m = r.reshape(-1, 3, 3)
    tr = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    choice = np.argmax(np.stack([m[:, 0, 0], m[:, 1, 1], m[:, 2, 2], tr], axis=1), axis=1)
    xyzw = np.empty((m.shape[0], 4))
    for i in range(3):
        j, k = (i + 1) % 3, (i + 2) % 3
        s = choice == i
        ms = m[s]
        xyzw[s, i] = 1.0 - tr[s] + 2.0 * ms[:, i, i]
        xyzw[s, j] = ms[:, j, i] + ms[:, i, j]
        xyzw[s, k] = ms[:, k, i] + ms[:, i, k]
        xyzw[s, 3] = ms[:, k, j] - ms[:, j, k]
    s = choice == 3
    ms = m[s]
    xyzw[s, 0] = ms[:, 2, 1] - ms[:, 1, 2]
    xyzw[s, 1] = ms[:, 0, 2] - ms[:, 2, 0]
    xyzw[s, 2] = ms[:, 1, 0] - ms[:, 0, 1]
    xyzw[s, 3] = 1.0 + tr[s]
    wxyz = np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1)
    wxyz /= np.linalg.norm(wxyz, axis=1, keepdims=True)
    wxyz *= np.where(wxyz[:, :1] < 0, -1.0, 1.0)
    return wxyz.reshape(*r.shape[:-2], 4)


class Transform(BaseModel):
    """A rigid transform ``T_a_b``; validated so that only proper rotations are stored."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    translation: Vec3 = Field(description="metres, frame a")
    rotation: Quat = Field(description="unit quaternion w, x, y, z")

    @field_validator("translation")
    @classmethod
    def _finite_translation(cls, v: list[float]) -> list[float]:
        if not all(np.isfinite(v)):
            raise ValueError(f"translation must be finite, got {v}")
        return v

    @field_validator("rotation")
    @classmethod
    def _unit_rotation(cls, v: list[float]) -> list[float]:
        if not all(np.isfinite(v)):
            raise ValueError(f"rotation must be finite, got {v}")
        n = float(np.linalg.norm(v))
        if abs(n - 1.0) > QUAT_NORM_TOL:
            raise ValueError(
                f"rotation must be a unit quaternion (w, x, y, z); norm is {n:.9f}, "
                f"tolerance {QUAT_NORM_TOL}"
            )
        return v

    @classmethod
    def identity(cls) -> Transform:
        return cls(translation=[0.0, 0.0, 0.0], rotation=[1.0, 0.0, 0.0, 0.0])

    @classmethod
    def from_matrix(cls, m: np.ndarray | list[list[float]]) -> Transform:
        """Build from a 4x4 matrix, rejecting anything that is not a proper rigid motion."""
        a = np.asarray(m, dtype=np.float64)
        if a.shape != (4, 4):
            raise ValueError(f"transform matrix must be 4x4, got shape {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError("transform matrix must be finite")
        if not np.allclose(a[3], [0, 0, 0, 1], atol=1e-9):
            raise ValueError(f"transform matrix last row must be [0 0 0 1], got {a[3].tolist()}")
        r = a[:3, :3]
        err = float(np.abs(r @ r.T - np.eye(3)).max())
        if err > ORTHO_TOL:
            raise ValueError(f"rotation is not orthonormal (max |R R^T - I| = {err:.3g})")
        if np.linalg.det(r) < 0:
            raise ValueError("rotation is a reflection (det R = -1), not a proper rotation")
        q = matrix_to_quat(r)
        return cls(translation=a[:3, 3].tolist(), rotation=(q / np.linalg.norm(q)).tolist())

    def matrix(self) -> np.ndarray:
        """The 4x4 ``T_a_b``; compose, invert and apply it with ``tasks.geometry``."""
        return transform(np.asarray(self.translation), np.asarray(self.rotation))
