"""End to end on the project's simulator: simulate -> ingest -> qa -> manifests -> catalog SQL,
for each storage (ROS 2 sqlite3, MCAP, ROS 1)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.test_stage_reads import handle
from v2xlake.storage import manifest as mf
from v2xlake.storage.catalog import Catalog
from v2xlake.storage.lake import Lake
from v2xlake.tasks.ingest import IngestConfig, clip_inputs, run_ingest
from v2xlake.tasks.ingest.stage import INGEST
from v2xlake.tasks.qa.config import GridTolerance, QaConfig
from v2xlake.tasks.qa.stage import QA, run_qa

simulate_mod = pytest.importorskip("v2xlake.tasks.simulate")


@pytest.fixture(scope="module")
def lake_with_sims(tmp_path_factory: pytest.TempPathFactory) -> tuple[Lake, dict[str, Path]]:
    root = tmp_path_factory.mktemp("sim")
    lake = Lake(root / "lake")
    clips = {}
    for storage in ("sqlite3", "mcap", "ros1"):
        cfg = simulate_mod.SimConfig.preset("small", seconds=0.3, storage=storage, seed=3,
                                            cameras=("CAM_FRONT",), clip_id=f"sim-{storage}")
        d = simulate_mod.simulate(root / storage, cfg)
        cid, files = clip_inputs(d)
        key = mf.stage_key(lake, cid, "ingest", IngestConfig(), input_files=files)
        mf.record(lake, run_ingest(handle(lake, INGEST), d), key)
        qkey = mf.stage_key(lake, cid, "qa", QaConfig(), ("ingest",))
        mf.record(lake, run_qa(handle(lake, QA), cid), qkey)
        clips[storage] = d
    return lake, clips


@pytest.mark.parametrize("storage", ["sqlite3", "mcap", "ros1"])
def test_simulated_clip_counts(lake_with_sims: tuple[Lake, dict[str, Path]],
                               storage: str) -> None:
    lake, clips = lake_with_sims
    cat = Catalog(lake, read_only=True)
    cid = f"sim-{storage}"

    def one(sql: str) -> int:
        return int(cat.query(sql.replace("$CID", f"'{cid}'")).column(0)[0].as_py())

    assert one("SELECT count(*) FROM clips WHERE clip_id = $CID") == 1
    assert one("SELECT count(*) FROM clips WHERE clip_id = $CID AND source = 'simulated'") == 1
    assert one("SELECT count(*) FROM agents WHERE clip_id = $CID AND has_ins") == 2
    assert one("SELECT count(*) FROM lidar_frames WHERE clip_id = $CID") == 2 * 3
    n_pts = one("SELECT sum(n_points) FROM lidar_frames WHERE clip_id = $CID")
    assert n_pts > 0 and one("SELECT count(*) FROM lidar_points WHERE clip_id = $CID") == n_pts
    # 32 beams x 360 columns per scan, single return: every point is either kept or non-finite
    assert one("SELECT max(n_points + n_nan) FROM lidar_frames WHERE clip_id = $CID") <= 32 * 360
    assert one("SELECT count(*) FROM lidar_frames WHERE clip_id = $CID "
               "AND t_end_ns - t_start_ns NOT BETWEEN 90000000 AND 100000000") == 0
    assert one("SELECT count(*) FROM camera_frames WHERE clip_id = $CID") == 2 * 9
    assert one("SELECT count(*) FROM raw.ins WHERE clip_id = $CID") >= 2 * 37
    # LiDAR + camera + INS + IMU + GNSS per agent, every one calibrated
    n_sensors = one("SELECT count(*) FROM sensors WHERE clip_id = $CID")
    assert one("SELECT count(*) FROM calibrated_sensors WHERE clip_id = $CID") == n_sensors
    assert one("SELECT count(*) FROM calibrated_sensors WHERE clip_id = $CID AND "
               "modality = 'camera' AND fx > 0 AND source LIKE '%camera_info'") == 2
    ann = json.loads((clips[storage] / "annotations.json").read_text())["annotations"]
    assert one("SELECT count(*) FROM annotations WHERE clip_id = $CID") == len(ann)
    assert one("SELECT count(*) FROM qa_checks WHERE clip_id = $CID AND NOT passed "
               "AND severity = 'error'") == 0
    assert one("SELECT count(*) FROM qa_checks WHERE clip_id = $CID") > 10
    assert one("SELECT count(*) FROM manifests WHERE clip_id = $CID AND status = 'done'") == 2
    # per-point time inside its scan and PPS-locked scan starts
    assert one("SELECT count(*) FROM lidar_points p JOIN lidar_frames f USING "
               "(clip_id, agent_id, sensor, frame_idx) WHERE p.clip_id = $CID AND "
               "(p.t_ns < f.t_start_ns OR p.t_ns > f.t_end_ns)") == 0
    assert one("SELECT count(*) FROM lidar_frames WHERE clip_id = $CID AND "
               "abs(stamp_ns % 100000000) > 1000 AND abs(stamp_ns % 100000000) < 99999000") == 0


def test_unchanged_simulated_clip_is_current(lake_with_sims: tuple[Lake, dict[str, Path]]
                                             ) -> None:
    lake, clips = lake_with_sims
    cid, files = clip_inputs(clips["mcap"])
    key = mf.stage_key(lake, cid, "ingest", IngestConfig(), input_files=files)
    assert mf.is_current(lake, cid, "ingest", key)
    assert mf.is_current(lake, cid, "qa", mf.stage_key(lake, cid, "qa", QaConfig(), ("ingest",)))
    assert not mf.is_current(lake, cid, "qa", mf.stage_key(
        lake, cid, "qa", QaConfig(tolerance_ms=GridTolerance(lidar=2.0)), ("ingest",)))
    # the same values spelled with an old flat key hash the same: nothing re-runs
    with pytest.warns(DeprecationWarning, match="tolerance_ms.lidar"):
        flat = QaConfig.model_validate({"lidar_tolerance_ms": 1.0})
    assert mf.is_current(lake, cid, "qa", mf.stage_key(lake, cid, "qa", flat, ("ingest",)))
