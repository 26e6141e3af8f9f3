"""nuScenes export of radars: a simulated clip with a front radar per vehicle, processed and
exported, loads in the real devkit as RADAR_FRONT channels whose ``.pcd`` files give back
exactly the lake's detections, and whose boxes' ``num_radar_pts`` the devkit's own
``points_in_box`` reproduces."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.export_fixtures import run_stages
from v2xlake.storage.lake import Lake
from v2xlake.tasks.export.common import token
from v2xlake.tasks.export.nuscenes import NuScenesExportConfig, export_nuscenes
from v2xlake.tasks.export.nuscenes_radar import (
    RCS_MISSING_DBSM,
    radar_pcd_points,
    write_radar_pcd,
)
from v2xlake.tasks.simulate import SimConfig, simulate

VERSION = "v1.0-mini"
NEEDED = ("ingest", "qa", "anonymize", "deskew", "register", "annotate")  # align: not needed


@pytest.fixture(scope="module")
def processed(tmp_path_factory: pytest.TempPathFactory) -> tuple[Lake, str]:
    tmp = tmp_path_factory.mktemp("nusradar")
    clip = simulate(tmp / "clip", SimConfig.preset(
        "small", seconds=1.0, seed=3, cameras=("CAM_FRONT",), camera_hz=10, radar=True,
        write_lidar_truth=False))
    lake = Lake(tmp / "lake")
    return lake, run_stages(lake, clip, NEEDED)


@pytest.fixture(scope="module")
def nusc(processed: tuple[Lake, str], tmp_path_factory: pytest.TempPathFactory) -> Any:
    from nuscenes.nuscenes import NuScenes

    lake, cid = processed
    out = tmp_path_factory.mktemp("nusradar_out")
    rep = export_nuscenes(lake, [cid], out, NuScenesExportConfig(version=VERSION,
                                                                 write_lake_tables=False))
    assert rep.status == "done" and not rep.notes
    return NuScenes(VERSION, str(out), verbose=False)


def _lake_scan(lake: Lake, cid: str, agent: str, frame: int) -> tuple[np.ndarray, np.ndarray]:
    pts = lake.read_table("clean", "radar_points", clip_id=cid, agent_id=agent)
    fi = pts["frame_idx"].to_numpy()
    xyz = np.stack([pts[c].to_numpy() for c in "xyz"], 1)[fi == frame]
    return xyz, pts["velocity"].to_numpy()[fi == frame]


def _sorted_rows(a: np.ndarray) -> np.ndarray:
    return a[np.lexsort(a.T[::-1])]


def test_radar_channels_files_and_points(nusc: Any, processed: tuple[Lake, str]) -> None:
    from nuscenes.utils.data_classes import RadarPointCloud

    lake, cid = processed
    RadarPointCloud.default_filters()
    radar_sd = [sd for sd in nusc.sample_data if sd["channel"] == "RADAR_FRONT"]
    frames = lake.read_table("clean", "radar_frames", clip_id=cid)
    assert len(radar_sd) == frames.num_rows == 40  # 2 vehicles x 20 scans (20 Hz, 1 s)
    for s in nusc.sample:  # every sample has its keyframe radar scan, like a camera
        assert set(s["data"]) == {"LIDAR_TOP", "CAM_FRONT", "RADAR_FRONT"}
    calib = {r["agent_id"]: r for r in lake.read_table(
        "clean", "calibrated_sensors", clip_id=cid).to_pylist() if r["sensor"] == "RADAR_FRONT"}
    n_checked = 0
    for agent in ("red", "black"):
        fr = [r for r in frames.to_pylist() if r["agent_id"] == agent]
        for r in fr:
            sd = nusc.get("sample_data", token("sample_data", cid, agent, "RADAR_FRONT",
                                               r["frame_idx"]))
            assert sd["fileformat"] == "pcd" and sd["sensor_modality"] == "radar"
            assert sd["filename"].startswith("samples/" if sd["is_key_frame"] else "sweeps/")
            cs = nusc.get("calibrated_sensor", sd["calibrated_sensor_token"])
            assert cs["camera_intrinsic"] == []
            assert np.allclose(cs["translation"], [calib[agent][k] for k in ("tx", "ty", "tz")])
            path, _, K = nusc.get_sample_data(sd["token"])
            assert K is None
            pc = RadarPointCloud.from_file(path)  # the devkit's default filters
            xyz, v_r = _lake_scan(lake, cid, agent, r["frame_idx"])
            assert pc.points.shape == (18, r["n_points"]) == (18, len(xyz))
            got = pc.points[:3].T.astype(np.float32)
            assert np.array_equal(_sorted_rows(got), _sorted_rows(xyz.astype(np.float32)))
            # (vx, vy) = v_r * u_xy: the measured radial component, as a vector
            u = pc.points[:3].T / np.linalg.norm(pc.points[:3].T, axis=1, keepdims=True)
            order = np.lexsort(got.T[::-1])
            lake_order = np.lexsort(xyz.astype(np.float32).T[::-1])
            v_file = (pc.points[6:8].T * u[:, :2]).sum(1) / np.maximum(
                (u[:, :2] ** 2).sum(1), 1e-12)
            assert np.allclose(v_file[order], v_r[lake_order], atol=1e-3)
            n_checked += 1
    assert n_checked == 40
    # ego compensation: the street is static, so its compensated velocities are ~0 while
    # the raw ones are the car's own speed along the line of sight
    pc = RadarPointCloud.from_file(nusc.get_sample_data_path(radar_sd[len(radar_sd) // 2][
        "token"]))
    raw = np.linalg.norm(pc.points[6:8], axis=0)
    comp = np.linalg.norm(pc.points[8:10], axis=0)
    assert np.median(raw) > 3.0
    assert np.mean(comp < 0.3) > 0.5
    assert set(np.unique(pc.points[3]).tolist()) <= {0, 1, 2}
    assert np.mean(pc.points[3] == 1) > 0.5  # mostly stationary
    # prev/next chain per channel
    for scene in nusc.scene:
        first = nusc.get("sample", scene["first_sample_token"])["data"]["RADAR_FRONT"]
        sd = nusc.get("sample_data", first)
        while sd["prev"]:
            sd = nusc.get("sample_data", sd["prev"])
        n = 1
        while sd["next"]:
            nxt = nusc.get("sample_data", sd["next"])
            assert nxt["timestamp"] > sd["timestamp"] and nxt["prev"] == sd["token"]
            sd, n = nxt, n + 1
        assert n == 20


def test_render_radar(nusc: Any, tmp_path: Path) -> None:
    """The devkit draws a radar channel over several sweeps (its prev chain, velocities)."""
    import matplotlib
    import matplotlib.pyplot as plt

    matplotlib.use("Agg")
    out = tmp_path / "radar.png"
    nusc.render_sample_data(nusc.sample[1]["data"]["RADAR_FRONT"], nsweeps=3,
                            out_path=str(out), verbose=False, underlay_map=False)
    plt.close("all")
    assert out.stat().st_size > 10_000


def test_num_radar_pts_is_the_devkit_count(nusc: Any) -> None:
    """Every box: the devkit's own points_in_box on the sample's key radar scans (loaded
    without the default filters, as nuScenes counts) gives the exported num_radar_pts."""
    from nuscenes.utils.data_classes import RadarPointCloud
    from nuscenes.utils.geometry_utils import points_in_box

    anns = nusc.sample_annotation
    assert max(a["num_radar_pts"] for a in anns) > 0
    nz = 0
    try:
        RadarPointCloud.disable_filters()
        for s in nusc.sample:
            count = {a: 0 for a in s["anns"]}
            for ch, sd in s["data"].items():
                if not ch.startswith("RADAR_"):
                    continue
                path, boxes, _ = nusc.get_sample_data(sd)
                pts = RadarPointCloud.from_file(path).points[:3]
                for b in boxes:
                    count[b.token] += int(points_in_box(b, pts).sum())
            for a, n in count.items():
                assert nusc.get("sample_annotation", a)["num_radar_pts"] == n
                nz += n > 0
    finally:
        RadarPointCloud.default_filters()
    assert nz >= 3


def test_radar_off(processed: tuple[Lake, str], tmp_path: Path) -> None:
    from nuscenes.nuscenes import NuScenes

    lake, cid = processed
    export_nuscenes(lake, [cid], tmp_path, NuScenesExportConfig(
        version=VERSION, write_lake_tables=False, write_radar=False))
    nusc = NuScenes(VERSION, str(tmp_path), verbose=False)
    assert {s["modality"] for s in nusc.sensor} == {"lidar", "camera"}
    assert all(a["num_radar_pts"] == 0 for a in nusc.sample_annotation)
    assert not (tmp_path / "samples" / "RADAR_FRONT").exists()


def test_pcd_edge_cases(tmp_path: Path) -> None:
    """A NaN RCS becomes the documented stand-in (a NaN in the first point would make the
    devkit read the whole scan as empty), and an empty scan is the devkit's one-NaN-point
    empty cloud."""
    from nuscenes.utils.data_classes import RadarPointCloud

    from v2xlake.storage.reader import RadarScan

    xyz = np.array([[10.0, 1.0, 0.5], [20.0, -2.0, 1.0]], np.float32)
    scan = RadarScan(0, np.zeros(2, np.int64), xyz, np.array([-3.0, 0.0], np.float32),
                     np.array([np.nan, 7.5], np.float32))
    p = tmp_path / "a.pcd"
    assert write_radar_pcd(p, radar_pcd_points(scan, np.array([3.0, 0.0, 0.0]), 0.5)) == 2
    pc = RadarPointCloud.from_file(str(p))
    assert pc.points.shape == (18, 2)
    assert np.allclose(pc.points[5], [RCS_MISSING_DBSM, 7.5])
    assert np.allclose(pc.points[:3].T, xyz)
    # no ego motion given: compensated == raw
    pc_raw = radar_pcd_points(scan, None, 0.5)
    assert np.array_equal(pc_raw["vx_comp"], pc_raw["vx"])
    none = np.zeros(0, np.float32)
    e = tmp_path / "e.pcd"
    assert write_radar_pcd(e, radar_pcd_points(
        RadarScan(1, np.zeros(0, np.int64), np.zeros((0, 3), np.float32), none, none),
        None, 0.5)) == 0
    assert RadarPointCloud.from_file(str(e)).points.shape == (18, 0)
