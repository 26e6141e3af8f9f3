"""Projecting points and 3D boxes into a camera with intrinsics and lens distortion.

A 3D box's 2D box is the extent of its *outline*, not of its 8 corners: with distortion,
straight edges bend, and a box that is partly behind the camera has to be cut at the near
plane first, otherwise a corner behind the camera lands on the wrong side of the image. So
each of the 12 edges is clipped to ``z >= near`` exactly (it is a line segment, the cut point
is closed form), sampled, projected with the lens model, and the extent is clipped to the
image. Polynomial lens models fold back outside their calibrated field of view; points
beyond the image corners' field of view are therefore projected with the pinhole model,
which keeps them outside the image where they belong.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from v2xlake.schemas.calibration import CameraIntrinsics, DistortionModel
from v2xlake.tasks.geometry import BOX_EDGES as EDGES
from v2xlake.tasks.geometry import apply, box_corners


@dataclass(frozen=True)
class Camera:
    """What projection needs of one camera: intrinsics and where it sits on the ego."""

    name: str
    intrinsics: CameraIntrinsics
    T_ego_cam: np.ndarray  # 4x4

    @property
    def K(self) -> np.ndarray:
        return np.asarray(self.intrinsics.k_matrix(), dtype=np.float64)


def _dist(intr: CameraIntrinsics) -> np.ndarray:
    return np.asarray(intr.distortion, dtype=np.float64)


def _max_normalized_radius(intr: CameraIntrinsics) -> float:
    """Largest undistorted radius (x/z, y/z) that the image corners correspond to, +10 %."""
    if intr.distortion_model is DistortionModel.NONE or not any(intr.distortion):
        return float("inf")
    return _max_radius_cached(intr.model_dump_json())


@lru_cache(maxsize=64)
def _max_radius_cached(intr_json: str) -> float:
    intr = CameraIntrinsics.model_validate_json(intr_json)
    w, h = intr.width, intr.height
    px = np.array([[[0.0, 0.0]], [[w, 0.0]], [[0.0, h]], [[w, h]]], dtype=np.float64)
    K = np.asarray(intr.k_matrix(), dtype=np.float64)
    if intr.distortion_model is DistortionModel.EQUIDISTANT:
        und = cv2.fisheye.undistortPoints(px.reshape(1, -1, 2), K, _dist(intr)).reshape(-1, 2)
    else:
        und = cv2.undistortPoints(px, K, _dist(intr)).reshape(-1, 2)
    r = float(np.linalg.norm(und, axis=1).max())
    return 1.1 * r if np.isfinite(r) and r > 0 else float("inf")


def project_points(
    xyz_cam: np.ndarray, intr: CameraIntrinsics, near: float = 0.1,
) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points (N, 3) -> pixels (N, 2) and a mask of points in front (z >= near).

    Pixels of points behind the camera are NaN. Optical frame convention: z forward,
    x right, y down.
    """
    xyz = np.asarray(xyz_cam, dtype=np.float64).reshape(-1, 3)
    front = xyz[:, 2] >= near
    uv = np.full((xyz.shape[0], 2), np.nan)
    if not front.any():
        return uv, front
    p = xyz[front]
    xn = p[:, :2] / p[:, 2:3]
    K = np.asarray(intr.k_matrix(), dtype=np.float64)
    pin = xn * [intr.fx, intr.fy] + [intr.cx, intr.cy]
    out = pin.copy()
    rmax = _max_normalized_radius(intr)
    if np.isfinite(rmax):
        ok = np.linalg.norm(xn, axis=1) <= rmax
        if ok.any():
            q = np.concatenate([xn[ok], np.ones((int(ok.sum()), 1))], axis=1)
            zero = np.zeros(3)
            if intr.distortion_model is DistortionModel.EQUIDISTANT:
                d, _ = cv2.fisheye.projectPoints(q.reshape(1, -1, 3), zero, zero, K, _dist(intr))
            else:
                d, _ = cv2.projectPoints(q.reshape(-1, 1, 3), zero, zero, K, _dist(intr))
            out[ok] = d.reshape(-1, 2)
    uv[front] = out
    return uv, front


def in_image(uv: np.ndarray, intr: CameraIntrinsics) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        return (
            (uv[:, 0] >= 0) & (uv[:, 0] < intr.width) & (uv[:, 1] >= 0) & (uv[:, 1] < intr.height)
        )


def points_in_fov(
    xyz_src: np.ndarray, T_cam_src: np.ndarray, intr: CameraIntrinsics, near: float = 0.5,
) -> np.ndarray:
    """Mask of the points (given in frame src) that land inside the image, in front."""
    uv, front = project_points(apply(T_cam_src, xyz_src), intr, near)
    return front & in_image(uv, intr)


def project_boxes_2d(
    center: np.ndarray, size: np.ndarray, quat: np.ndarray, T_cam_src: np.ndarray,
    intr: CameraIntrinsics, near: float = 0.1, samples_per_edge: int = 9,
) -> np.ndarray:
    """(M, 4) image boxes x0, y0, x1, y1 (clipped to the image); NaN rows where not visible.

    ``T_cam_src`` is one 4x4 for all boxes or (M, 4, 4), one per box (target-based alignment
    puts every object at its own time).
    """
    m = center.shape[0]
    out = np.full((m, 4), np.nan)
    if m == 0:
        return out
    corners = box_corners(center, size, quat)  # (M, 8, 3) in src
    T = np.asarray(T_cam_src, dtype=np.float64)
    Tm = np.broadcast_to(T, (m, 4, 4)) if T.ndim == 2 else T
    cam = np.einsum("mij,mkj->mki", Tm[:, :3, :3], corners) + Tm[:, None, :3, 3]
    a = cam[:, EDGES[:, 0]]  # (M, 12, 3)
    b = cam[:, EDGES[:, 1]]
    za, zb = a[..., 2], b[..., 2]
    dz = zb - za
    with np.errstate(divide="ignore", invalid="ignore"):
        s_cross = np.where(np.abs(dz) > 1e-12, (near - za) / dz, 0.0)
    a_in, b_in = za >= near, zb >= near
    lo = np.where(a_in, 0.0, np.where(b_in, s_cross, 1.0))
    hi = np.where(b_in, 1.0, np.where(a_in, s_cross, 0.0))
    keep = a_in | b_in  # edges with some part in front
    s = np.linspace(0.0, 1.0, samples_per_edge)
    ss = lo[..., None] + (hi - lo)[..., None] * s  # (M, 12, S)
    pts = a[..., None, :] + (b - a)[..., None, :] * ss[..., None]  # (M, 12, S, 3)
    pts[..., 2] = np.maximum(pts[..., 2], near)  # guard rounding at the cut
    valid = np.broadcast_to(keep[..., None], ss.shape).reshape(m, -1)
    uv, _ = project_points(pts.reshape(-1, 3), intr, near=near * (1 - 1e-9))
    uv = uv.reshape(m, -1, 2)
    uv = np.where(valid[..., None], uv, np.nan)
    has = np.isfinite(uv[..., 0]).any(axis=1)
    if not has.any():
        return out
    x0 = np.nanmin(uv[has, :, 0], axis=1)
    y0 = np.nanmin(uv[has, :, 1], axis=1)
    x1 = np.nanmax(uv[has, :, 0], axis=1)
    y1 = np.nanmax(uv[has, :, 1], axis=1)
    box = np.stack([
        np.clip(x0, 0, intr.width), np.clip(y0, 0, intr.height),
        np.clip(x1, 0, intr.width), np.clip(y1, 0, intr.height),
    ], axis=1)
    ok = (box[:, 2] > box[:, 0]) & (box[:, 3] > box[:, 1])
    rows = np.flatnonzero(has)
    out[rows[ok]] = box[ok]
    return out
