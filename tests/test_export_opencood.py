"""OpenCOOD export read back exactly the way the V2V4Real loader reads it."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
import yaml

from tests.export_fixtures import build_clean_clip, world_box_at
from v2xlake.storage.lake import Lake
from v2xlake.storage.reader import iter_point_frames
from v2xlake.tasks.export.opencood import (
    export_opencood,
    matrix_to_opencood_angles,
    opencood_loader_ego,
    opencood_x_to_world,
)


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory) -> tuple[Lake, Path]:
    base = tmp_path_factory.mktemp("ocd")
    lake = Lake(base / "lake")
    # the cooperative agent lost scan 7 (e.g. deskew skipped it): the loader needs the same
    # file names in every agent folder, so frame 7 must be left out for both
    build_clean_clip(lake, "clip-a", with_cameras=False, skip_deskewed_frames=(7,),
                     skip_deskewed_agent="black")
    out = base / "opencood"
    rep = export_opencood(lake, ["clip-a"], out, splits={"clip-a": "test"})
    assert rep.metrics["frames"] == 38
    return lake, out


def test_layout_like_the_loader_scans_it(exported) -> None:
    _, out = exported
    scen = out / "test" / "clip-a"
    cavs = sorted(x.name for x in scen.iterdir() if x.is_dir())
    assert cavs == ["0", "1"] and all(int(c) >= 0 for c in cavs)  # two vehicles
    meta = json.loads((out / "test" / "clip-a.json").read_text())
    assert meta["agents"] == {"red": 0, "black": 1} and meta["loader_ego"] == "red"
    for c in cavs:
        ys = sorted(p.name for p in (scen / c).glob("*.yaml"))
        assert ys == [f"{i:06d}.yaml" for i in range(20) if i != 7]
        assert all((scen / c / y.replace(".yaml", ".pcd")).exists() for y in ys)


def test_pcd_roundtrip_as_opencood_reads_it(exported) -> None:
    lake, out = exported
    for aid, num in (("red", "0"), ("black", "1")):
        src = {f.frame_idx: f for f in iter_point_frames(lake, "clip-a", aid)}
        for fi in (0, 13):
            path = str(out / "test" / "clip-a" / num / f"{fi:06d}.pcd")
            pcd = o3d.io.read_point_cloud(path)  # type: ignore[arg-type]
            xyz = np.asarray(pcd.points)
            intensity = np.expand_dims(np.asarray(pcd.colors)[:, 0], -1)
            pcd_np = np.hstack((xyz, intensity)).astype(np.float32)  # pcd_utils.pcd_to_np
            s = src[fi]
            assert pcd_np.shape == (len(s.xyz), 4)
            assert np.allclose(pcd_np[:, :3], s.xyz, atol=1e-5)
            assert np.abs(pcd_np[:, 3] - s.intensity).max() <= 0.5 / 255 + 1e-6


def test_yaml_boxes_project_to_world(exported) -> None:
    _, out = exported
    for num in ("0", "1"):
        doc = yaml.safe_load((out / "test" / "clip-a" / num / "000005.yaml").read_text())
        T_wl = np.array(doc["lidar_pose_matrix"])
        assert T_wl.shape == (4, 4)
        np.testing.assert_allclose(opencood_x_to_world(doc["lidar_pose"]), T_wl, atol=1e-9)
        assert doc["vehicles"]
        ass = {v["ass_id"] for v in doc["vehicles"].values()}
        assert len(ass) == len(doc["vehicles"])
        for v in doc["vehicles"].values():
            # OpenCOOD: object pose = location + center with angle, then x1_to_x2(...)
            pose = [a + b for a, b in zip(v["location"], v["center"], strict=True)] + v["angle"]
            T_lo = opencood_x_to_world(pose)
            assert np.isclose(np.linalg.det(T_lo[:3, :3]), 1.0)
            W = T_wl @ T_lo
            # find the fixture box with this extent at this time
            t_ns = doc["timestamp_ns"]
            best = min(("car-parked", "car-moving", "truck-car", "trailer", "ped"),
                       key=lambda g: np.linalg.norm(world_box_at(g, t_ns)[:3, 3] - W[:3, 3]))
            Wt = world_box_at(best, t_ns)
            assert np.allclose(W[:3, 3], Wt[:3, 3], atol=1e-4)
            assert np.allclose(W[:3, :3], Wt[:3, :3], atol=1e-6)
    # the same object has the same ass_id in both agents
    a = yaml.safe_load((out / "test" / "clip-a" / "0" / "000010.yaml").read_text())["vehicles"]
    b = yaml.safe_load((out / "test" / "clip-a" / "1" / "000010.yaml").read_text())["vehicles"]
    assert set(a) & set(b)


def test_angles_invert_x_to_world() -> None:
    rng = np.random.default_rng(1)
    from scipy.spatial.transform import Rotation

    for R in Rotation.random(50, random_state=rng).as_matrix():
        ang = matrix_to_opencood_angles(R)
        assert np.allclose(opencood_x_to_world([0, 0, 0, *ang])[:3, :3], R, atol=1e-9)


# V2V4Real's pose path, re-implemented from its published behaviour
# (ucla-mobility/V2V4Real, opencood/hypes_yaml/yaml_utils.py::load_yaml and
# opencood/utils/transformation_utils.py::x1_to_x2 / dist_two_pose), so that the test takes
# exactly the road a training run takes with the values our YAML holds.
def _v2v4real_load_yaml(path: Path) -> dict:
    import re

    loader = yaml.Loader
    loader.add_implicit_resolver(
        "tag:yaml.org,2002:float",
        re.compile("""^(?:[-+]?(?:[0-9][0-9_]*)\\.[0-9_]*(?:[eE][-+]?[0-9]+)?
        |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
        |\\.[0-9_]+(?:[eE][-+][0-9]+)?
        |[-+]?[0-9][0-9_]*(?::[0-5]?[0-9])+\\.[0-9_]*
        |[-+]?\\.(?:inf|Inf|INF)
        |\\.(?:nan|NaN|NAN))$""", re.X), list("-+0123456789."))
    with open(path) as f:
        return dict(yaml.load(f, Loader=loader))


def _v2v4real_x1_to_x2(x1: object, x2: object) -> np.ndarray:
    if isinstance(x1, list) and isinstance(x2, list):
        x1_to_world, x2_to_world = opencood_x_to_world(x1), opencood_x_to_world(x2)
        return np.dot(np.linalg.inv(x2_to_world), x1_to_world)
    if isinstance(x1, np.ndarray) and isinstance(x2, list):
        return np.dot(np.linalg.inv(opencood_x_to_world(x2)), x1)
    if isinstance(x1, np.ndarray) and isinstance(x2, np.ndarray):
        return np.dot(np.linalg.inv(x2), x1)
    x1_to_world = opencood_x_to_world(x1)  # type: ignore[arg-type]  # what the code does
    return np.dot(np.linalg.inv(x2), x1_to_world)  # type: ignore[arg-type]


def _v2v4real_dist_two_pose(cav_pose: list, ego_pose: list) -> float:
    import math

    return math.sqrt((cav_pose[0] - ego_pose[0]) ** 2 + (cav_pose[1] - ego_pose[1]) ** 2)


def test_the_v2v4real_pose_path_takes_our_yaml(exported) -> None:
    lake, out = exported
    from v2xlake.tasks.reader import lidar_world_poses, load_clip

    clip = load_clip(lake, "clip-a")
    agent_of = {"0": "red", "1": "black"}
    for name in ("000005.yaml", "000012.yaml"):
        ego = _v2v4real_load_yaml(out / "test" / "clip-a" / "0" / name)
        cav = _v2v4real_load_yaml(out / "test" / "clip-a" / "1" / name)
        T_ego_cav = _v2v4real_x1_to_x2(cav["lidar_pose"], ego["lidar_pose"])
        d = _v2v4real_dist_two_pose(cav["lidar_pose"], ego["lidar_pose"])
        # the truth from the lake: both LiDARs' world poses at their scan starts
        T = {n: lidar_world_poses(clip.agents[agent_of[n]], "LIDAR_TOP",
                                  np.array([doc["timestamp_ns"]]), "clip-a")[0]
             for n, doc in (("0", ego), ("1", cav))}
        np.testing.assert_allclose(T_ego_cav, np.linalg.inv(T["0"]) @ T["1"], atol=1e-6)
        assert abs(d - np.linalg.norm(T["1"][:2, 3] - T["0"][:2, 3])) < 1e-6
        # and the form we wrote before this test existed (a nested 4x4 list) is what crashed
        with pytest.raises((TypeError, ValueError)):
            _v2v4real_x1_to_x2(cav["lidar_pose_matrix"], ego["lidar_pose_matrix"])


def _opencood_cav_list(scenario: Path) -> list[str]:
    """OpenCOOD ``BaseDataset`` (train=False) / V2V4Real ``reinitialize`` (train=False):
    sorted folder names, a negative first one moved to the end; the first is the ego."""
    cav_list = sorted(x.name for x in scenario.iterdir() if x.is_dir())
    if int(cav_list[0]) < 0:
        cav_list = [*cav_list[1:], cav_list[0]]
    return cav_list


def test_roadside_units_get_negative_ids(tmp_path: Path) -> None:
    """V2XSet marks infrastructure with negative cav ids, and the loader relies on that to
    keep a roadside unit from being the ego; the reference vehicle stays ``0``."""
    from v2xlake.schemas.arrow import rows_to_table
    from v2xlake.schemas.tables import LAKE_TABLES

    lake = Lake(tmp_path / "lake")
    build_clean_clip(lake, "clip-r", seconds=0.5, n_ground=300, with_cameras=False)
    lake.write_table("clean", "agents", rows_to_table(LAKE_TABLES["agents"], [
        dict(clip_id="clip-r", agent_id="red", kind="vehicle", role="reference", has_ins=True),
        dict(clip_id="clip-r", agent_id="black", kind="roadside", role="cooperative",
             has_ins=True)]), clip_id="clip-r")
    out = tmp_path / "oc"
    rep = export_opencood(lake, ["clip-r"], out, splits={"clip-r": "test"})
    assert not rep.notes
    scen = out / "test" / "clip-r"
    assert sorted(x.name for x in scen.iterdir() if x.is_dir()) == ["-1", "0"]
    assert _opencood_cav_list(scen) == ["0", "-1"]  # the reference vehicle is the ego
    meta = json.loads((out / "test" / "clip-r.json").read_text())
    assert meta["agents"] == {"red": 0, "black": -1} and meta["loader_ego"] == "red"
    doc = yaml.safe_load((scen / "-1" / "000002.yaml").read_text())
    assert doc["agent_id"] == "black" and doc["pose_source"] == "ins"
    assert doc["pose_source_reason"].startswith("register has not run")
    assert yaml.safe_load((scen / "0" / "000002.yaml").read_text())["pose_source"] == \
        "reference"


def test_loader_ego_rule() -> None:
    # one roadside unit is moved behind the vehicles; a second one is not (sorted names are
    # "-1", "-2", "0": only "-1" moves), which the export reports in a note
    assert opencood_loader_ego([0, 1, -1]) == 0
    assert opencood_loader_ego([0, -1, -2]) == -2
    assert opencood_loader_ego([-1]) == -1
