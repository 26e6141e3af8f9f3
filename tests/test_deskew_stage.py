"""The deskew stage on a small hand-built clean zone: output table, stats, and the failures."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from scipy.spatial.transform import Rotation

from tests.fixtures.real import REAL_DATA_INGEST, requires_real_data
from tests.test_deskew import (
    INS_PERIOD_NS,
    Motion,
    Sweep,
    lidar_extrinsic,
    make_sweep,
    true_pose,
)
from v2xlake.schemas.arrow import arrow_schema, columns_to_table
from v2xlake.schemas.errors import ClipError
from v2xlake.schemas.tables import (
    AgentRow,
    CalibratedSensorRow,
    EgoPoseRow,
    LidarFrameRow,
    LidarPointRow,
)
from v2xlake.storage.lake import Lake
from v2xlake.tasks.deskew.config import DeskewConfig, PoseGaps, UncoveredPolicy
from v2xlake.tasks.deskew.stage import OUT_TABLE, run_deskew
from v2xlake.tasks.ingest.rows import table_of

CLIP = "clipA"
FRAMES = (200_000_000, 300_000_000, 400_000_000)  # clean axis: clip starts at 0.1 s


def write_agent(lake: Lake, agent: str, motion: Motion, ins_span: tuple[int, int] | None,
                gap: tuple[int, int] | None = None, has_ins: bool = True) -> list[Sweep]:
    """Clean tables of one agent: agents, calibrated_sensors, ego_poses, lidar_frames/points."""
    e = lidar_extrinsic()
    lake.write_table("clean", "agents", table_of(AgentRow, [AgentRow(
        clip_id=CLIP, agent_id=agent, kind="vehicle", role="reference" if agent == "red" else
        "cooperative", has_ins=has_ins)]), clip_id=CLIP, agent_id=agent)
    q = Rotation.from_matrix(e[:3, :3]).as_quat(scalar_first=True)
    lake.write_table("clean", "calibrated_sensors", table_of(CalibratedSensorRow, [
        CalibratedSensorRow(clip_id=CLIP, agent_id=agent, sensor="LIDAR_TOP", modality="lidar",
                            tx=e[0, 3], ty=e[1, 3], tz=e[2, 3], qw=q[0], qx=q[1], qy=q[2],
                            qz=q[3], source="tf_static")]), clip_id=CLIP, agent_id=agent)
    if ins_span is not None:
        t = np.arange(ins_span[0], ins_span[1] + 1, INS_PERIOD_NS, dtype=np.int64)
        if gap is not None:
            t = t[(t <= gap[0]) | (t >= gap[1])]
        rot, p = true_pose(t * 1e-9, motion)
        qq = Rotation.from_matrix(rot).as_quat(scalar_first=True)
        z = np.zeros(len(t))
        cols = {"t_ns": t, "x": p[:, 0], "y": p[:, 1], "z": p[:, 2], "qw": qq[:, 0],
                "qx": qq[:, 1], "qy": qq[:, 2], "qz": qq[:, 3], "vx": z, "vy": z, "vz": z,
                "rtk_status": np.full(len(t), 2), "clip_id": [CLIP] * len(t),
                "agent_id": [agent] * len(t)}
        lake.write_table("clean", "ego_poses", columns_to_table(EgoPoseRow, cols),
                         clip_id=CLIP, agent_id=agent)
    sweeps, frames, parts = [], [], []
    for k, t0 in enumerate(FRAMES):
        sw = make_sweep(motion, e, n_cols=180, n_lasers=8, dual=False, t0_ns=t0, seed=k)
        sweeps.append(sw)
        n = len(sw.t_ns)
        frames.append(LidarFrameRow(clip_id=CLIP, agent_id=agent, sensor="LIDAR_TOP", frame_idx=k,
                                    stamp_ns=t0, t_start_ns=t0, t_end_ns=int(sw.t_ns.max()),
                                    n_points=n, n_nan=0))
        parts.append({"sensor": ["LIDAR_TOP"] * n, "frame_idx": np.full(n, k, np.int32),
                      "t_ns": sw.t_ns, "x": sw.raw[:, 0], "y": sw.raw[:, 1], "z": sw.raw[:, 2],
                      "intensity": np.ones(n, np.float32), "ring": np.arange(n) % 8,
                      "return_id": np.zeros(n, np.uint8)})
    pts = {c: np.concatenate([p[c] for p in parts]) for c in parts[0]}
    pts["sensor"] = pa.array(list(pts["sensor"])).dictionary_encode()
    n_all = len(pts["t_ns"])
    pts["clip_id"], pts["agent_id"] = np.full(n_all, CLIP), np.full(n_all, agent)
    lake.write_table("clean", "lidar_points", columns_to_table(LidarPointRow, pts),
                     clip_id=CLIP, agent_id=agent, row_group_by="frame_idx")
    lake.write_table("clean", "lidar_frames", table_of(LidarFrameRow, frames),
                     clip_id=CLIP, agent_id=agent)
    return sweeps


def test_stage_writes_deskewed_points_and_frame_stats(tmp_path: Path) -> None:
    lake = Lake(tmp_path / "lake")
    truth = {"red": write_agent(lake, "red", Motion(), (100_000_000, 600_000_000)),
             "black": write_agent(lake, "black", Motion(yaw_rate=0.5), (100_000_000, 600_000_000))}
    rep = run_deskew(lake, CLIP)
    assert rep.metrics["n_frames"] == 6 and rep.metrics["n_frames_skipped"] == 0
    assert rep.metrics["n_deskewed"] == rep.metrics["n_points"] > 0
    assert rep.metrics["max_shift_m"] > 1.0 and rep.metrics["points_per_s"] > 0
    for agent, sweeps in truth.items():
        out = lake.read_table("clean", OUT_TABLE, clip_id=CLIP, agent_id=agent)
        assert out.schema.names == arrow_schema(LidarPointRow).names
        files = lake.list_files(lake.table_dir("clean", OUT_TABLE, CLIP, agent), ".parquet")
        assert sum(pq.ParquetFile(f).num_row_groups for f in files) == len(FRAMES)
        fi = out.column("frame_idx").to_numpy()
        xyz = np.stack([out.column(c).to_numpy() for c in "xyz"], axis=1)
        for k, sw in enumerate(sweeps):
            err = np.linalg.norm(xyz[fi == k] - sw.truth, axis=1)
            assert np.sqrt(np.mean(err**2)) < 1e-3
        frames = lake.read_table("clean", "deskew_frames", clip_id=CLIP, agent_id=agent)
        assert frames.column("deskew_ref_ns").to_pylist() == list(FRAMES)
        assert frames.column("n_uncovered").to_pylist() == [0, 0, 0]
        shift = np.array(frames.column("deskew_max_shift_m").to_pylist())
        assert np.all((shift > 1.0) & (shift < 6.0))
    # a re-run replaces, it does not append
    run_deskew(lake, CLIP)
    assert lake.read_table("clean", OUT_TABLE, clip_id=CLIP).num_rows == rep.metrics["n_points"]


def test_frame_past_the_ins_end_is_skipped_at_the_edge_or_an_error(tmp_path: Path) -> None:
    lake = Lake(tmp_path / "lake")
    write_agent(lake, "red", Motion(), (100_000_000, 452_000_000))  # last scan ends at 0.5 s
    rep = run_deskew(lake, CLIP)
    assert rep.metrics["n_frames_skipped"] == 1
    assert "red LIDAR_TOP frame 2 skipped" in rep.notes[0]
    frames = lake.read_table("clean", "deskew_frames", clip_id=CLIP)
    assert frames.column("deskew_ref_ns").to_pylist() == [*FRAMES[:2], None]
    assert frames.column("n_uncovered").to_pylist()[2] > 0
    out = lake.read_table("clean", OUT_TABLE, clip_id=CLIP)
    assert set(out.column("frame_idx").to_pylist()) == {0, 1}
    with pytest.raises(ClipError) as ei:
        run_deskew(lake, CLIP, DeskewConfig(uncovered=UncoveredPolicy(policy="error")))
    msg = str(ei.value)
    assert "frame 2" in msg and "INS covers only up to 452000000 ns" in msg and "red" in msg
    assert "points span [400000000," in msg


def test_ins_gap_in_the_middle_is_an_error(tmp_path: Path) -> None:
    lake = Lake(tmp_path / "lake")
    write_agent(lake, "red", Motion(), (100_000_000, 600_000_000), gap=(310_000_000, 390_000_000))
    with pytest.raises(ClipError, match=r"frame 1: .*gap of 88.0 ms between 308000000"):
        run_deskew(lake, CLIP)


def test_a_10_hz_pose_source_is_not_a_gap(tmp_path: Path,
                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """A localisation stack's 10 Hz Odometry: every sample 100 ms apart. The default limit
    follows the track's own period (2.5 periods), as QA does; a stricter explicit limit is
    reported with the parameter that sets it."""
    monkeypatch.setitem(globals(), "INS_PERIOD_NS", 100_000_000)
    lake = Lake(tmp_path / "lake")
    write_agent(lake, "red", Motion(), (0, 700_000_000))
    rep = run_deskew(lake, CLIP)
    assert rep.status == "done" and rep.metrics["n_frames"] == 3
    with pytest.raises(ClipError, match=r"max 50\.0 ms: deskew.pose_gaps.max_ns"):
        run_deskew(lake, CLIP, DeskewConfig(pose_gaps=PoseGaps(max_ns=50_000_000),
                                           uncovered=UncoveredPolicy(policy="error")))


def test_agent_without_ins_says_so(tmp_path: Path) -> None:
    """No pose is a fact about the recording: not applicable with the reason, no error."""
    lake = Lake(tmp_path / "lake")
    write_agent(lake, "red", Motion(), None, has_ins=False)
    rep = run_deskew(lake, CLIP)
    assert rep.status == "not_applicable" and not rep.outputs
    assert "red: agents.has_ins is false" in (rep.reason or "")
    assert "motion compensation needs poses" in (rep.reason or "")
    # with a second agent that has poses, that one is deskewed and the first is named
    write_agent(lake, "black", Motion(), (100_000_000, 600_000_000))
    rep = run_deskew(lake, CLIP)
    assert rep.status == "done" and rep.metrics["n_frames"] == 3
    assert rep.notes[0].startswith("red not deskewed: agents.has_ins is false")


@requires_real_data("bags/ouster_os1_128_3frames_ros2")
def test_real_ouster_clip_without_ins_is_a_clear_error(tmp_path: Path) -> None:
    """The real OS-1-128 bag (shared data) has per-point times but no INS: deskew must stop
    with a ClipError that says why. The clean zone is made from the real ingest output by
    copying the tables deskew reads (what anonymize copies), to test this stage alone."""
    from v2xlake.tasks.ingest import run_ingest

    fixture = Path(__file__).resolve().parent / "fixtures" / "ouster"
    if not (fixture / "clip.yaml").exists():
        pytest.skip("ouster fixture not present")
    cid = "ouster-os1-128-real"
    lake = Lake(tmp_path / "lake")
    run_ingest(lake, fixture, REAL_DATA_INGEST)
    for table in ("agents", "calibrated_sensors", "lidar_frames", "lidar_points", "ins"):
        for path in lake.list_files(lake.table_dir("raw", table, cid), ".parquet"):
            dest = lake.path("clean", path[len(lake.path("raw")):].lstrip("/"))
            lake.write_bytes(dest, lake.read_bytes(path))
    assert lake.read_table("clean", "lidar_points", clip_id=cid).num_rows > 100_000
    assert lake.read_table("clean", "agents", clip_id=cid).column("has_ins").to_pylist() == [False]
    rep = run_deskew(lake, cid)
    assert rep.status == "not_applicable" and not rep.outputs
    assert "ouster: agents.has_ins is false" in (rep.reason or "")
    assert "per-point motion compensation" in (rep.reason or "")
