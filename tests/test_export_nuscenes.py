"""nuScenes export: the official devkit loads it, renders it, and its detection eval scores
the ground truth against itself at mAP 1.0 on a custom split."""

from __future__ import annotations

import json
import os
from pathlib import Path

import matplotlib
import numpy as np
import pytest

from tests.export_fixtures import build_clean_clip, world_box_at
from v2xlake.schemas.errors import ClipError
from v2xlake.storage.lake import Lake
from v2xlake.tasks.export.nuscenes import (
    NuScenesExportConfig,
    detection_eval,
    export_nuscenes,
    results_from_ground_truth,
)

matplotlib.use("Agg")
VERSION = "v1.0-trainval"


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory) -> tuple[Lake, Path]:
    base = tmp_path_factory.mktemp("nus")
    lake = Lake(base / "lake")
    build_clean_clip(lake, "clip-a", skip_deskewed_frames=(19,))
    out = base / "nuscenes"
    rep = export_nuscenes(lake, ["clip-a"], out, NuScenesExportConfig(
        version=VERSION, splits={"clip-a": "val"}))
    assert rep.metrics["scenes"] == 2 and rep.metrics["samples"] == 8
    assert any("1 LiDAR frames without deskewed points" in n for n in rep.notes)
    return lake, out


@pytest.fixture(scope="module")
def nusc(exported: tuple[Lake, Path]):
    from nuscenes.nuscenes import NuScenes

    return NuScenes(VERSION, str(exported[1]), verbose=False)


def test_devkit_loads_and_files_exist(nusc, exported) -> None:
    nusc.list_scenes()
    assert {s["name"] for s in nusc.scene} == {"clip-a-red", "clip-a-black"}
    assert {lg["vehicle"] for lg in nusc.log} == {"red", "black"}
    for s in nusc.sample:
        assert set(s["data"]) == {"LIDAR_TOP", "CAM_FRONT"}
        for sd in s["data"].values():
            assert os.path.exists(nusc.get_sample_data_path(sd))
    for sd in nusc.sample_data:
        assert os.path.exists(os.path.join(nusc.dataroot, sd["filename"]))
    # 2 Hz keyframes on LiDAR time, prev/next chains complete, sweeps point to the next sample
    for scene in nusc.scene:
        s = nusc.get("sample", scene["first_sample_token"])
        times = [s["timestamp"]]
        while s["next"]:
            s = nusc.get("sample", s["next"])
            times.append(s["timestamp"])
        assert len(times) == scene["nbr_samples"] == 4
        assert np.allclose(np.diff(times), 500_000)
    for sd in nusc.sample_data:
        if not sd["is_key_frame"] and sd["timestamp"] < 1_600_000:
            assert nusc.get("sample", sd["sample_token"])["timestamp"] >= sd["timestamp"]
    lidar = [sd for sd in nusc.sample_data if sd["channel"] == "LIDAR_TOP"]
    # frame 19 has no deskewed points: no sample_data points at a missing file
    assert len(lidar) == 38 and sum(sd["is_key_frame"] for sd in lidar) == 8


def test_boxes_points_and_attributes(nusc) -> None:
    from nuscenes.utils.data_classes import LidarPointCloud

    anns = nusc.sample_annotation
    assert anns and all(a["num_lidar_pts"] > 0 for a in anns)
    attrs = {nusc.get("attribute", a["attribute_tokens"][0])["name"] for a in anns}
    assert {"vehicle.parked", "vehicle.moving", "pedestrian.moving"} <= attrs
    # global = clip world - the map origin (so that the map raster covers the clip)
    origin = np.array([*json.loads((Path(nusc.dataroot) / VERSION / "map_origins.json")
                                   .read_text())["clip-a"]["origin_xy"], 0.0])
    for a in anns:
        s = nusc.get("sample", a["sample_token"])
        inst = nusc.get("instance", a["instance_token"])
        # the global box equals the fixture's world box at the scan start
        gid = json.loads((Path(nusc.dataroot) / VERSION / "instance_global_ids.json")
                         .read_text())[inst["token"]]["instance_id"]
        W = world_box_at(gid, s["timestamp"] * 1000)
        assert np.allclose(a["translation"], W[:3, 3] - origin, atol=1e-4)
    # the devkit's own points_in_box on the loaded .pcd.bin agrees with num_lidar_pts
    s = nusc.sample[0]
    pc = LidarPointCloud.from_file(nusc.get_sample_data_path(s["data"]["LIDAR_TOP"]))
    _, boxes, _ = nusc.get_sample_data(s["data"]["LIDAR_TOP"])
    from nuscenes.utils.geometry_utils import points_in_box

    for b in boxes:
        ann = nusc.get("sample_annotation", b.token)
        assert points_in_box(b, pc.points[:3]).sum() == ann["num_lidar_pts"]


def test_render_sample_data(nusc, tmp_path: Path) -> None:
    s = nusc.sample[1]
    for ch in ("LIDAR_TOP", "CAM_FRONT"):
        out = tmp_path / f"{ch}.png"
        nusc.render_sample_data(s["data"][ch], out_path=str(out), verbose=False,
                                underlay_map=False)
        assert out.stat().st_size > 1000


def test_render_sample_with_the_map(nusc, tmp_path: Path) -> None:
    """The devkit's most used call, map underlay included, in the shipped NumPy."""
    import matplotlib.pyplot as plt
    from nuscenes.nuscenes import NuScenesExplorer

    from v2xlake.tasks.export.nuscenes_devkit import fix_render_for_numpy2

    if int(np.__version__.split(".")[0]) >= 2 and not getattr(
            NuScenesExplorer.render_ego_centric_map, "_v2xlake_numpy2_fix", False):
        with pytest.raises(TypeError, match="0-dimensional"):  # the devkit bug, unpatched
            nusc.render_sample(nusc.sample[0]["token"], out_path=str(tmp_path / "x.png"))
    assert fix_render_for_numpy2() == (int(np.__version__.split(".")[0]) >= 2)
    for scene in nusc.scene:
        s = nusc.get("sample", scene["first_sample_token"])
        out = tmp_path / f"{scene['name']}.png"
        nusc.render_sample(s["token"], out_path=str(out), verbose=False)
        assert out.stat().st_size > 10_000
        plt.close("all")
    # the map covers the whole clip (the fixture drives through negative x and y): around
    # every ego pose the devkit crops a full 80 m window with street in it
    for sd in nusc.sample_data:
        if sd["channel"] != "LIDAR_TOP":
            continue
        fig, ax = plt.subplots()
        nusc.explorer.render_ego_centric_map(sd["token"], axes_limit=40, ax=ax)
        img = np.asarray(ax.images[0].get_array())
        plt.close(fig)
        assert img.shape == (800, 800), sd["filename"]
        assert (img == 125).mean() > 0.01  # foreground: where the LiDAR saw the ground
    log = nusc.get("log", nusc.scene[0]["log_token"])
    mask = nusc.get("map", log["map_token"])["mask"]
    pose = nusc.get("ego_pose", nusc.get("sample_data", nusc.sample[1]["data"]["LIDAR_TOP"])
                    ["ego_pose_token"])
    assert mask.is_on_mask(pose["translation"][0] + 5.0, pose["translation"][1], dilation=1.0)


def test_detection_eval_self_is_perfect(nusc, tmp_path: Path) -> None:
    sample_tokens = [s["token"] for s in nusc.sample]
    res = tmp_path / "results.json"
    res.write_text(json.dumps(results_from_ground_truth(nusc, sample_tokens)))
    m = detection_eval(nusc, res, "v2x_val", tmp_path / "eval")
    assert m["classes_present"] == ["car", "pedestrian", "trailer"]
    assert m["mean_ap_present"] == pytest.approx(1.0)
    # the devkit's own mAP averages all 10 classes; 7 have no ground truth here (AP 0)
    assert m["mean_ap"] == pytest.approx(0.3)
    for c in m["classes_present"]:
        assert m["label_tp_errors"][c]["trans_err"] == pytest.approx(0.0, abs=1e-6)
        assert m["label_tp_errors"][c]["scale_err"] == pytest.approx(0.0, abs=1e-6)


def test_lake_tables_written(exported) -> None:
    lake, _ = exported
    t = lake.read_table("clean", "nuscenes_sample_annotation", clip_id="clip-a")
    assert t.num_rows > 0 and "clip_id" in t.column_names
    inst = lake.read_table("clean", "nuscenes_instance", clip_id="clip-a")
    assert {"trailer", "truck-car"} <= set(inst["global_instance_id"].to_pylist())


def test_missing_deskewed_points_is_a_clip_error(tmp_path: Path) -> None:
    lake = Lake(tmp_path / "lake")
    build_clean_clip(lake, "clip-x", with_deskewed=False, with_cameras=False, seconds=1.0)
    with pytest.raises(ClipError, match="deskew"):
        export_nuscenes(lake, ["clip-x"], tmp_path / "out")


def test_missing_devkit_says_how_to_install_it(monkeypatch: pytest.MonkeyPatch) -> None:
    """nuscenes-devkit is optional (it pins numpy<2): without it the evaluation helpers name
    the way to install it instead of a bare ModuleNotFoundError."""
    import sys

    from v2xlake.tasks.export.nuscenes_devkit import require_devkit

    monkeypatch.setitem(sys.modules, "nuscenes", None)
    with pytest.raises(ImportError, match=r"requirements-oracles\.lock"):
        require_devkit()
    with pytest.raises(ImportError, match="nuscenes-devkit is not installed"):
        results_from_ground_truth(None, [])
