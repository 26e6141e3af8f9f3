"""``v2xlake.open``: the lazy, read-only Python API, and the map-style dataset.

The lake is the export fixtures' physically consistent street (two agents, world objects
seen by both), so cross-agent checks are physical: a parked car seen by both agents is
where both say it is, each agent's points fall inside the other's box of the same global
instance, a camera's pose at its stamp is the ego pose at that stamp times its mounting.
"""

from __future__ import annotations

import os
import pickle
from pathlib import Path

import numpy as np
import pytest

import v2xlake
from tests.export_fixtures import T_ego_cam, agent_track, build_clean_clip, world_box_at
from v2xlake.schemas.geometry import matrix_to_quat
from v2xlake.schemas.tables import RegistrationRow
from v2xlake.storage.catalog import QueryRefused
from v2xlake.storage.lake import Lake
from v2xlake.tasks.geometry import invert, points_in_boxes

CLIP = "clip-api"


@pytest.fixture(scope="module")
def lake_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("api") / "lake"
    build_clean_clip(Lake(root), CLIP, seconds=1.0, n_ground=1500)
    return root


def _files(root: Path) -> dict[str, float]:
    return {str(p): p.stat().st_mtime for p in root.rglob("*") if p.is_file()}


def test_open_is_lazy_and_read_only(lake_dir: Path) -> None:
    before = _files(lake_dir)
    lake = v2xlake.open(lake_dir)
    assert lake._catalog is None  # nothing queried yet
    assert lake.clips == [CLIP]
    clip = lake.clip(CLIP)
    assert "data" not in clip.__dict__  # the clip's tables are not read until used
    assert clip.agents == ["red", "black"] and clip.reference_agent == "red"
    assert clip.info["location"] == "testville"
    assert lake.sql("SELECT count(*) AS n FROM clean.lidar_frames")["n"][0].as_py() == 20
    with pytest.raises(QueryRefused):
        lake.sql(f"COPY (SELECT 1) TO '{lake_dir}/clean/x.parquet'")
    with pytest.raises(KeyError):
        lake.clip("no-such-clip")
    with pytest.raises(ValueError):
        lake.clip("../escape")
    lake.close()
    assert _files(lake_dir) == before  # no catalog.duckdb, nothing touched
    with pytest.raises(FileNotFoundError):
        v2xlake.open(lake_dir / "typo")


def test_cooperative_sample_is_physically_consistent(lake_dir: Path) -> None:
    clip = v2xlake.open(lake_dir).clip(CLIP)
    assert len(clip) == 10 and clip.sample_frames.tolist() == list(range(10))
    s = clip.sample(4)
    assert s.agents == ["red", "black"] and s["black"].frame_idx == 4
    assert s.t_ns == 100_000_000 + 4 * 100_000_000
    # relative transform = from both agents' poses (no registration in this lake)
    assert np.allclose(s.T("red", "black"), invert(s["red"].T_world_lidar)
                       @ s["black"].T_world_lidar)
    assert np.allclose(s.T("red", "red"), np.eye(4))
    # boxes with global ids: the parked car seen by both agents, in red's LiDAR frame
    boxes = s.boxes()
    br, bb = boxes["red"], boxes["black"]
    assert br.frame == bb.frame == "red"
    common = sorted(set(br.instance_id) & set(bb.instance_id))
    assert "car-parked" in common
    for iid in common:
        i, j = br.instance_id.index(iid), bb.instance_id.index(iid)
        assert np.allclose(br.center[i], bb.center[j], atol=1e-6), iid
    # ... and in the world frame it is the world model's box
    bw = s["black"].boxes("world")
    k = bw.instance_id.index("car-parked")
    assert np.allclose(bw.center[k], world_box_at("car-parked", s.t_ns)[:3, 3], atol=1e-6)
    assert bw.num_lidar_pts[k] > 0 and bw.size[k].tolist() == [1.9, 4.5, 1.6]
    # both agents' deskewed points, in red's frame, fall inside red's boxes
    pts = s.points()
    for aid in ("red", "black"):
        p = pts[aid]
        assert p.frame == "red" and p.xyz.dtype == np.float32 and len(p) > 500
        inside = points_in_boxes(p.xyz.astype(np.float64), br.center, br.size, br.quat_wxyz,
                                 margin=0.02)
        assert len(inside[br.instance_id.index("car-parked")]) > 50, aid
    assert pts["red"].numpy().shape == (len(pts["red"]), 4)
    assert set(pts["red"].to_arrow().column_names) >= {"x", "y", "z", "intensity", "t_ns"}


def test_images_carry_calibration_at_their_stamp(lake_dir: Path) -> None:
    clip = v2xlake.open(lake_dir).clip(CLIP)
    fr = clip.frame("black", 3)
    (img,) = fr.images()
    assert img.sensor == "CAM_FRONT" and abs(img.stamp_ns - fr.t_ns) <= 17_000_000
    expect = agent_track("black", seconds=1.0).matrices(img.stamp_ns)[0] @ T_ego_cam()
    assert np.allclose(img.T_world_cam, expect, atol=1e-9)
    assert img.K[0, 0] == 160.0 and img.distortion_model == "plumb_bob"
    rgb = img.read()
    assert rgb.shape == (img.height, img.width, 3) and rgb.dtype == np.uint8
    assert img.png()[:4] == b"\x89PNG"


def _reg_row(T: np.ndarray, base: np.ndarray, frame_idx: int, accepted: bool,
             reason: str) -> RegistrationRow:
    q, q0 = matrix_to_quat(T[:3, :3]), matrix_to_quat(base[:3, :3])
    return RegistrationRow(
        clip_id=CLIP, agent_ref="red", agent_other="black", frame_idx=frame_idx, t_ns=0,
        init_tx=base[0, 3], init_ty=base[1, 3], init_tz=base[2, 3], init_qw=q0[0],
        init_qx=q0[1], init_qy=q0[2], init_qz=q0[3], tx=T[0, 3], ty=T[1, 3], tz=T[2, 3],
        qw=q[0], qx=q[1], qy=q[2], qz=q[3], fitness=0.9, inlier_rmse=0.02, correction_m=0.2,
        correction_deg=0.0, accepted=accepted, method="gicp", reason=reason)


def test_registration_overrides_poses(tmp_path: Path) -> None:
    root = tmp_path / "lake"
    lk = Lake(root)
    build_clean_clip(lk, CLIP, seconds=0.3, n_ground=300, with_cameras=False)
    # an accepted refined T_Lred_Lblack 0.2 m off the poses' one on frame 1, a rejected one
    # on frame 2, no row for frame 0
    never = v2xlake.open(root).clip(CLIP).sample(1)
    base = never.T("red", "black")
    assert never.sources == {"red": "reference", "black": "ins"} and not never.registered
    assert never.source_reason("black").startswith("register has not run")
    T = base.copy()
    T[0, 3] += 0.2
    uncertain = "uncertain: clip estimate 1-sigma 2.5 cm / 0.025 deg > 2.0 cm / 0.05 deg"
    from v2xlake.schemas.arrow import rows_to_table

    lk.write_table("clean", "registrations", rows_to_table(RegistrationRow, [
        _reg_row(T, base, 1, True, "ok"), _reg_row(T, base, 2, False, uncertain)]),
        clip_id=CLIP)
    clip = v2xlake.open(root).clip(CLIP)
    assert np.allclose(clip.sample(1).T("red", "black"), T, atol=1e-9)
    assert np.allclose(clip.sample(2).T("red", "black"), clip.sample(2)["red"].T_to("red")
                       @ invert(clip.sample(2)["red"].T_world_lidar)
                       @ clip.sample(2)["black"].T_world_lidar)
    assert clip.sample(1).registration().num_rows == 1
    # which transform each agent got, and why not the refined one
    s0, s1, s2 = clip.sample(0), clip.sample(1), clip.sample(2)
    assert s1.sources == {"red": "reference", "black": "registered"} and s1.registered
    assert s1["black"].T_source == "registered" and s1.source_reason("black") == ""
    assert s2.source("black") == "ins" and s2.source_reason("black") == f"rejected: {uncertain}"
    assert s0.source("black") == "ins" and "no registration row" in s0.source_reason("black")
    assert not s0.registered and not s2.registered
    assert clip.frame("black", 1).T_source == "ins"  # outside a sample: its own INS pose
    off = v2xlake.open(root, use_registration=False).clip(CLIP)
    assert np.allclose(off.sample(1).T("red", "black"), base)
    assert off.sample(1).source_reason("black") == "use_registration=False"
    # the dataset says it per item, and can keep the registered samples only
    ds = v2xlake.CoopDataset(root)
    assert [ds[i]["T_source"]["black"] for i in range(len(ds))] == ["ins", "registered", "ins"]
    assert ds[2]["T_source_reason"] == {"red": "", "black": f"rejected: {uncertain}"}
    for kw in ({}, {"require_all_agents": True}):
        strict = v2xlake.CoopDataset(root, require_registered=True, **kw)
        assert strict.index == [(CLIP, 1)]
        assert strict[0]["T_source"] == {"red": "reference", "black": "registered"}
        assert np.allclose(strict[0]["T"]["black"], T, atol=1e-9)


def test_dataset_unknown_clip_is_an_error(lake_dir: Path) -> None:
    with pytest.raises(KeyError, match="nope"):
        v2xlake.CoopDataset(lake_dir, clips=["nope", CLIP])
    with pytest.raises(KeyError, match="nope"):
        v2xlake.CoopDataset(lake_dir, clips=["nope"], require_all_agents=True)
    assert len(v2xlake.CoopDataset(lake_dir, clips=[CLIP])) == 10


def test_frame_index_is_one_query(lake_dir: Path) -> None:
    lake = v2xlake.open(lake_dir)
    idx = lake.frame_index()
    assert idx.num_rows == 10 and set(idx["clip_id"].to_pylist()) == {CLIP}
    assert idx["t_ns"].to_pylist()[0] == 100_000_000
    assert lake.frame_index(clips=["other"]).num_rows == 0


def _count_boxes(item: dict) -> dict:
    item["n_boxes"] = {a: len(b["instance_id"]) for a, b in item["boxes"].items()}
    return item


def test_dataset_map_style_and_picklable(lake_dir: Path) -> None:
    ds = v2xlake.CoopDataset(lake_dir, stride=3, transform=_count_boxes, images=True)
    assert len(ds) == 4  # samples 0, 3, 6, 9
    item = ds[1]
    assert item["clip_id"] == CLIP and item["frame_idx"] == 3 and item["agents"] == ["red",
                                                                                   "black"]
    assert item["points"]["black"].shape[1] == 4 and item["points"]["black"].dtype == np.float32
    assert np.allclose(item["T"]["red"], np.eye(4))
    assert item["n_boxes"]["red"] == len(item["boxes"]["red"]["center"]) > 0
    im = item["images"]["black"][0]
    assert im["rgb"].shape == (180, 320, 3) and im["T_frame_cam"].shape == (4, 4)
    # a DataLoader worker gets a pickled copy: it re-opens the lake itself
    ds2 = pickle.loads(pickle.dumps(ds))
    assert ds2.lake._catalog is None and len(ds2) == 4
    assert np.array_equal(ds2[1]["points"]["red"], item["points"]["red"])
    world = v2xlake.CoopDataset(v2xlake.open(lake_dir), frame="world")
    a = world[3]["points"]["red"][:, :3]
    b = ds[1]["points"]["red"][:, :3]
    T = v2xlake.open(lake_dir).clip(CLIP).sample(3)["red"].T_world_lidar
    assert np.allclose(a, b @ T[:3, :3].T + T[:3, 3], atol=1e-3)


def test_torch_dataloader(lake_dir: Path) -> None:
    torch = pytest.importorskip("torch")  # optional extra: pip install v2xlake[torch]
    from torch.utils.data import DataLoader

    ds = v2xlake.CoopDataset(lake_dir, stride=2)
    dl = DataLoader(ds, batch_size=2, num_workers=1 if os.name == "posix" else 0,
                    collate_fn=lambda b: b)
    batches = list(dl)
    assert sum(len(b) for b in batches) == len(ds) == 5
    t = torch.from_numpy(batches[0][0]["points"]["red"])
    assert t.shape[1] == 4


def _len_points(ds: v2xlake.CoopDataset, i: int) -> int:
    return int(ds[i]["points"]["black"].shape[0])


def test_dataset_in_worker_processes(lake_dir: Path) -> None:
    """What DataLoader(num_workers>0) does without torch: the dataset is pickled into spawned
    processes, each of which opens the lake itself and reads its items."""
    import multiprocessing as mp
    from functools import partial

    ds = v2xlake.CoopDataset(lake_dir, stride=4)
    ds[0]  # the parent's catalog / clip cache must not travel
    with mp.get_context("spawn").Pool(2) as pool:
        got = pool.map(partial(_len_points, ds), range(len(ds)))
    assert got == [_len_points(ds, i) for i in range(len(ds))] and min(got) > 500


def test_samples_with_a_missing_agent(tmp_path: Path) -> None:
    """A reference frame another agent cannot fill (deskew skipped its scan): ``sample_at``
    gives the agents present; the all-agents index leaves the frame out."""
    root = tmp_path / "lake"
    build_clean_clip(Lake(root), CLIP, seconds=0.5, n_ground=300, with_cameras=False,
                     skip_deskewed_frames=(2,), skip_deskewed_agent="black")
    clip = v2xlake.open(root).clip(CLIP)
    assert clip.sample_frames.tolist() == [0, 1, 3, 4] and len(clip) == 4
    assert clip.sample_at(2).agents == ["red"] and clip.sample_at(3).agents == ["red", "black"]
    with pytest.raises(KeyError):
        clip.sample_at(99)
    loose = v2xlake.CoopDataset(root)
    strict = v2xlake.CoopDataset(root, require_all_agents=True)
    assert [k for _, k in loose.index] == [0, 1, 2, 3, 4] and len(strict) == 4
    assert loose[2]["agents"] == ["red"] and set(loose[2]["points"]) == {"red"}
    assert strict[2]["frame_idx"] == 3
