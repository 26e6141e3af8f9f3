"""Annotate stage: point counts, instances, links, world boxes, cross-agent consistency."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pytest

from tests.test_align_scene import CLIP, OBJECTS, T_EGO_LIDAR, pose_track, write_lake
from v2xlake.schemas.arrow import columns_to_table, rows_to_table
from v2xlake.schemas.errors import ClipError
from v2xlake.schemas.geometry import matrix_to_quat
from v2xlake.schemas.tables import AgentRow, CalibratedSensorRow, EgoPoseRow
from v2xlake.storage.lake import Lake
from v2xlake.tasks.annotate.config import AnnotateConfig, LinkConfig
from v2xlake.tasks.annotate.consistency import cross_agent_distances
from v2xlake.tasks.annotate.stage import run_annotate

# black rides rigidly next to red: 3.5 m to the left, 0.5 m behind, yawed 10 degrees
D = np.eye(4)
_c, _s = np.cos(np.radians(10)), np.sin(np.radians(10))
D[:3, :3] = [[_c, -_s, 0], [_s, _c, 0], [0, 0, 1]]
D[:3, 3] = (-0.5, 3.5, 0.0)


def _add_black(lake: Lake, box_shift_m: float = 0.0) -> None:
    """A second agent seeing the same world: red's data re-expressed in black's frames."""
    tr = pose_track()
    T_w_red = np.tile(np.eye(4), (len(tr), 1, 1))
    from v2xlake.schemas.geometry import quat_to_matrix

    T_w_red[:, :3, :3] = quat_to_matrix(tr.quat_wxyz)
    T_w_red[:, :3, 3] = tr.xyz
    T_w_black = T_w_red @ D
    n = len(tr)
    lake.write_table("clean", "ego_poses", columns_to_table(EgoPoseRow, {
        "clip_id": [CLIP] * n, "agent_id": ["black"] * n, "t_ns": tr.t_ns,
        "x": T_w_black[:, 0, 3], "y": T_w_black[:, 1, 3], "z": T_w_black[:, 2, 3],
        **dict(zip(("qw", "qx", "qy", "qz"), matrix_to_quat(T_w_black[:, :3, :3]).T,
                   strict=True)),
        "vx": np.zeros(n), "vy": np.zeros(n), "vz": np.zeros(n), "rtk_status": np.full(n, 2)}),
        clip_id=CLIP, agent_id="black")
    lake.write_table("clean", "agents", rows_to_table(AgentRow, [AgentRow(
        clip_id=CLIP, agent_id="black", kind="vehicle", role="cooperative", has_ins=True)]),
        clip_id=CLIP, agent_id="black")
    lake.write_table("clean", "calibrated_sensors", rows_to_table(CalibratedSensorRow, [
        CalibratedSensorRow(clip_id=CLIP, agent_id="black", sensor="LIDAR_TOP",
                            modality="lidar", tx=0.5, ty=0.0, tz=1.9, qw=1.0, qx=0.0, qy=0.0,
                            qz=0.0, source="clip.yaml")]), clip_id=CLIP, agent_id="black")
    # L0 of black = (red L0) mapped by M = T_lidar_ego D^-1 T_ego_lidar
    M = np.linalg.inv(T_EGO_LIDAR) @ np.linalg.inv(D) @ T_EGO_LIDAR
    for table in ("lidar_frames", "deskew_frames", "lidar_points_deskewed", "annotations"):
        t = lake.read_table("clean", table, clip_id=CLIP, agent_id="red")
        t = t.set_column(t.schema.get_field_index("agent_id"), "agent_id",
                         pa.array(["black"] * t.num_rows))
        if table not in ("lidar_frames", "deskew_frames"):
            p = np.stack([t[c].to_numpy() for c in ("x", "y", "z")] if table != "annotations"
                         else [t[c].to_numpy() for c in ("cx", "cy", "cz")], 1)
            p = p @ M[:3, :3].T + M[:3, 3]
            names = ("x", "y", "z") if table != "annotations" else ("cx", "cy", "cz")
            if table == "annotations":
                p[:, 0] += box_shift_m
                q = matrix_to_quat(M[:3, :3] @ quat_to_matrix(
                    np.stack([t[c].to_numpy() for c in ("qw", "qx", "qy", "qz")], 1)))
                v = np.stack([t[c].to_numpy() for c in ("vx", "vy", "vz")], 1) @ M[:3, :3].T
                for k, c in enumerate(("qw", "qx", "qy", "qz")):
                    t = t.set_column(t.schema.get_field_index(c), c, pa.array(q[:, k]))
                for k, c in enumerate(("vx", "vy", "vz")):
                    t = t.set_column(t.schema.get_field_index(c), c, pa.array(v[:, k]))
            for k, c in enumerate(names):
                f = t.schema.field(c)
                t = t.set_column(t.schema.get_field_index(c), f, pa.array(p[:, k]).cast(f.type))
        lake.write_table("clean", table, t, clip_id=CLIP, agent_id="black",
                         row_group_by="frame_idx" if table == "lidar_points_deskewed" else None)


def test_point_counts_instances_world_boxes(tmp_path: Path) -> None:
    lake, _, _scans = write_lake(tmp_path)
    rep = run_annotate(lake, CLIP, AnnotateConfig())
    before = lake.list_files(lake.table_dir("clean", "annotations", CLIP), ".parquet")
    # num_lidar_pts lives in annotate's own table; anonymize's annotations stay as written
    ann = lake.read_table("clean", "annotations_world", clip_id=CLIP)
    assert ann.num_rows == 15
    assert lake.list_files(lake.table_dir("clean", "annotations", CLIP), ".parquet") == before
    counts = ann["num_lidar_pts"].to_numpy()
    # 400 points were sampled inside each object; moving ones smear by a few cm
    assert np.all(counts >= 370) and np.all(counts <= 400), counts
    static = pc.is_in(ann["instance_id"], pa.array(["car-parked", "trailer-parked"]))
    assert np.all(counts[static.to_numpy(zero_copy_only=False)] == 400)
    inst = lake.read_table("clean", "instances", clip_id=CLIP).to_pylist()
    assert {r["instance_id"] for r in inst} == {o.instance_id for o in OBJECTS}
    tr = next(r for r in inst if r["instance_id"] == "trailer-parked")
    assert tr["links"] == ["car-parked"] and tr["n_annotations"] == 3 and tr["agents"] == ["red"]
    assert tr["category"] == "Trailer" and tr["first_t_ns"] < tr["last_t_ns"]
    # world boxes sit where the objects were at the box time
    w = lake.read_table("clean", "annotations_world", clip_id=CLIP).to_pylist()
    assert len(w) == 15
    by_id = {o.instance_id: o for o in OBJECTS}
    for r in w:
        true = by_id[r["instance_id"]].center(np.array(r["t_ns"]))
        np.testing.assert_allclose([r["cx"], r["cy"], r["cz"]], true, atol=1e-4)  # 8 ms INS
        np.testing.assert_allclose([r["vx"], r["vy"], r["vz"]], by_id[r["instance_id"]].v,
                                   atol=1e-6)
    assert rep.metrics["n_instances"] == 5 and rep.metrics["links.n_far"] == 0
    assert "cross_agent.median_dist_m" not in rep.metrics  # one agent only


def test_cross_agent_consistency(tmp_path: Path) -> None:
    lake, _, _ = write_lake(tmp_path / "a")
    _add_black(lake)
    rep = run_annotate(lake, CLIP)
    print({k: round(v, 4) for k, v in rep.metrics.items()})
    assert rep.metrics["cross_agent.n_pairs"] == 15
    assert rep.metrics["cross_agent.median_dist_m"] < 1e-3
    inst = lake.read_table("clean", "instances", clip_id=CLIP).to_pylist()
    assert all(r["agents"] == ["black", "red"] and r["n_annotations"] == 6 for r in inst)
    # black's boxes shifted 1 m: the check sees it
    lake2, _, _ = write_lake(tmp_path / "b")
    _add_black(lake2, box_shift_m=1.0)
    rep2 = run_annotate(lake2, CLIP)
    assert rep2.metrics["cross_agent.median_dist_m"] == pytest.approx(1.0, abs=1e-3)


def test_cross_agent_distances_moves_boxes_to_a_common_time() -> None:
    ids = np.array(["a", "a"], dtype=object)
    agents = np.array(["red", "black"], dtype=object)
    t = np.array([0, 20_000_000])
    c = np.array([[0.0, 0, 0], [0.3, 0, 0]])  # 15 m/s over 20 ms
    v = np.array([[15.0, 0, 0], [15.0, 0, 0]])
    d = cross_agent_distances(ids, agents, t, c, v, 60_000_000)
    assert d.shape == (1,) and d[0] == pytest.approx(0.0, abs=1e-9)
    assert cross_agent_distances(ids, agents, t, c, v, 10_000_000).size == 0


def _edit_annotations(lake: Lake, fn) -> None:  # type: ignore[no-untyped-def]
    t = lake.read_table("clean", "annotations", clip_id=CLIP, agent_id="red")
    lake.write_table("clean", "annotations", fn(t), clip_id=CLIP, agent_id="red")


def _set_links(t: pa.Table, inst: str, links: list[str]) -> pa.Table:
    new = [links if i == inst else lk for i, lk in
           zip(t["instance_id"].to_pylist(), t["links"].to_pylist(), strict=True)]
    return t.set_column(t.schema.get_field_index("links"), "links",
                        pa.array(new, pa.list_(pa.string())))


def test_bad_links_and_categories_are_clip_errors(tmp_path: Path) -> None:
    lake, _, _ = write_lake(tmp_path / "far")
    _edit_annotations(lake, lambda t: _set_links(t, "trailer-parked", ["car-oncoming"]))
    with pytest.raises(ClipError, match="too far apart"):
        run_annotate(lake, CLIP, AnnotateConfig(links=LinkConfig(policy="error")))
    # by default a plausibility finding is reported, never a reason to quarantine (#15)
    rep = run_annotate(lake, CLIP)
    assert rep.status == "done" and rep.metrics["links.n_far"] == 3
    assert any("too far" in n or "apart" in n for n in rep.notes), rep.notes
    lake, _, _ = write_lake(tmp_path / "unknown")
    _edit_annotations(lake, lambda t: _set_links(t, "trailer-parked", ["no-such-car"]))
    with pytest.raises(ClipError, match="unknown instance no-such-car"):
        run_annotate(lake, CLIP)
    lake, _, _ = write_lake(tmp_path / "cat")

    def recat(t: pa.Table) -> pa.Table:
        cats = t["category"].to_pylist()
        cats[0] = "Van" if cats[0] != "Van" else "Car"
        return t.set_column(t.schema.get_field_index("category"), "category", pa.array(cats))

    _edit_annotations(lake, recat)
    with pytest.raises(ClipError, match="more than one category"):
        run_annotate(lake, CLIP)


def test_cross_agent_after_refined_registration(tmp_path: Path) -> None:
    from v2xlake.schemas.tables import RegistrationRow

    lake, _, _ = write_lake(tmp_path)
    _add_black(lake)
    # T_L1_L2 (red L0 <- black L0); the "initial" one is off by 0.5 m, the refined exact
    M = np.linalg.inv(T_EGO_LIDAR) @ np.linalg.inv(D) @ T_EGO_LIDAR
    T = np.linalg.inv(M)
    q = matrix_to_quat(T[:3, :3])
    rows = [RegistrationRow(
        clip_id=CLIP, agent_ref="red", agent_other="black", frame_idx=k, t_ns=0,
        init_tx=T[0, 3] + 0.5, init_ty=T[1, 3], init_tz=T[2, 3], init_qw=q[0], init_qx=q[1],
        init_qy=q[2], init_qz=q[3], tx=T[0, 3], ty=T[1, 3], tz=T[2, 3], qw=q[0], qx=q[1],
        qy=q[2], qz=q[3], fitness=0.9, inlier_rmse=0.02, correction_m=0.5, correction_deg=0.0,
        accepted=True, method="gicp", reason="") for k in range(3)]
    lake.write_table("clean", "registrations", rows_to_table(RegistrationRow, rows),
                     clip_id=CLIP)
    rep = run_annotate(lake, CLIP)
    assert rep.metrics["cross_agent.n_pairs_registered"] == 15
    assert rep.metrics["cross_agent.median_dist_registered_m"] < 1e-3
