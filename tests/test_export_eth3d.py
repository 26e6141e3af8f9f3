"""ETH3D-style export: pycolmap reads the model, and projecting the written map with the
model read back through pycolmap reproduces the depth maps (eq. 4-5)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pycolmap
import pytest

from tests.export_fixtures import CAM_D, build_clean_clip, render_pinhole
from v2xlake.storage.lake import Lake
from v2xlake.tasks.export.eth3d import Eth3dConfig, export_eth3d


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory) -> tuple[Lake, Path]:
    base = tmp_path_factory.mktemp("eth")
    lake = Lake(base / "lake")
    build_clean_clip(lake, "clip-a")
    out = base / "eth3d"
    rep = export_eth3d(lake, ["clip-a"], out, Eth3dConfig(image_stride=6, voxel_m=0.02))
    assert rep.metrics["images"] == 20
    return lake, out / "clip-a"


def test_pycolmap_reads_model_and_depth_matches(exported) -> None:
    _, out = exported
    base = out / "red"
    rec = pycolmap.Reconstruction(str(base / "calibration_undistorted"))
    assert rec.num_images() == 10 and rec.num_cameras() == 1
    ply = str(base / "lidar" / "map.ply")
    pts = np.asarray(o3d.io.read_point_cloud(ply).points)  # type: ignore[arg-type]
    assert len(pts) > 10_000
    n_valid = 0
    for img in rec.images.values():
        cam = rec.cameras[img.camera_id]
        assert cam.model_name == "PINHOLE"
        pc = img.cam_from_world().matrix() @ np.c_[pts, np.ones(len(pts))].T
        pc = pc.T
        ok = (pc[:, 2] > 0.5) & (pc[:, 2] < 200)
        uv = cam.img_from_cam(pc[ok])
        u, v = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
        inb = (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
        ref = np.full((cam.height, cam.width), np.inf)
        np.minimum.at(ref, (v[inb], u[inb]), pc[ok][inb, 2])
        ref[np.isinf(ref)] = 0
        dm = np.load(base / "depth" / img.name.replace(".png", ".npy"))
        assert dm.shape == (cam.height, cam.width) and dm.dtype == np.float32
        assert np.array_equal(dm > 0, ref > 0)
        assert np.allclose(dm, ref, rtol=1e-5, atol=1e-4)
        n_valid += int((dm > 0).sum())
        assert (base / "images" / img.name).exists()
    assert n_valid > 1000


def test_undistorted_images_are_pinhole(exported) -> None:
    """The undistorted image equals an ideal pinhole rendering with the written K and pose."""
    _, out = exported
    rec = pycolmap.Reconstruction(str(out / "red" / "calibration_undistorted"))
    cam = next(iter(rec.cameras.values()))
    K_cv = cam.calibration_matrix().copy()
    K_cv[:2, 2] -= 0.5  # COLMAP pixel centres at +0.5
    stamps = dict(line.split(",") for line in
                  (out / "red" / "images.csv").read_text().split()[1:])
    name = "CAM_FRONT/000012.png"
    img = cv2.imread(str(out / "red" / "images" / name))
    assert img is not None
    got = img.astype(float)
    want = render_pinhole("red", int(stamps[name]), K_cv).astype(float)
    diff = np.abs(got - want).mean(axis=2)
    # bilinear resampling blurs edges by a pixel; everything else must agree
    assert np.median(diff) < 2.0 and (diff > 40).mean() < 0.025  # 1 px cx shift: 0.04
    # and the distorted original does NOT match the pinhole view as well
    assert not np.allclose(CAM_D, 0)
