"""QA: PPS-model checks, INS coverage, quarantine of a failing clip."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from tests.fixtures.minibag import MiniClip, write_clip
from tests.fixtures.real import REAL_DATA_INGEST, requires_real_data
from v2xlake.flows import bookkeeping
from v2xlake.schemas.errors import ClipError
from v2xlake.storage.catalog import Catalog
from v2xlake.storage.lake import Lake
from v2xlake.storage.quarantine import is_quarantined, quarantine, read_report
from v2xlake.tasks.ingest import run_ingest
from v2xlake.tasks.qa.config import GridTolerance, QaConfig
from v2xlake.tasks.qa.stage import run_qa
from v2xlake.tasks.qa.timing import (
    camera_offsets_ns,
    dropped_frames,
    grid_offsets_ns,
    ins_uncovered,
)

REPO = Path(__file__).resolve().parents[1]
NS = 1_000_000_000


def test_grid_offsets() -> None:
    t = np.array([5 * NS, 5 * NS + 100_000_000 + 300_000, 5 * NS + 199_000_000])
    assert grid_offsets_ns(t, 100_000_000).tolist() == [0, 300_000, -1_000_000]
    cam = np.array([7 * NS + round(k * NS / 30) for k in range(30)] + [8 * NS - 200])
    off = camera_offsets_ns(cam, 30)
    assert off[:30].tolist() == [0] * 30 and off[30] == -200
    # a 30 Hz stamp rounded the naive way (k * 33_333_333) drifts by 20 ns at k = 20
    assert camera_offsets_ns(np.array([7 * NS + 20 * 33_333_333]), 30).tolist() == [-7]


def test_dropped_frames_and_ins_cover() -> None:
    t = np.arange(0, 1_000_000_000, 100_000_000)
    n, gaps = dropped_frames(np.delete(t, [3, 4]), 1e8)
    assert n == 2 and gaps == [(200_000_000, 500_000_000)]
    ins = np.arange(-16_000_000, 1_100_000_000, 8_000_000)
    ins = ins[(ins < 400_000_000) | (ins > 520_000_000)]
    bad = ins_uncovered(ins, t, t + 99_000_000, 20_000_000)
    assert bad.tolist() == [False] * 3 + [True] * 3 + [False] * 4
    # no sample after the last scan's end
    assert ins_uncovered(ins[ins < 950_000_000], t, t + 99_000_000, 20_000_000)[-1]


def test_clean_clip_passes_and_writes_checks(tmp_path: Path) -> None:
    lake = Lake(tmp_path / "lake")
    run_ingest(lake, write_clip(tmp_path / "c", MiniClip(seconds=0.3, points=200, clip_id="ok")))
    rep = run_qa(lake, "ok")
    assert rep.metrics["errors"] == 0 and rep.metrics["warnings"] == 0
    cat = Catalog(lake)
    checks = cat.query("SELECT * FROM qa_checks WHERE clip_id = 'ok'").to_pylist()
    names = {c["check"] for c in checks}
    assert {"pps_lidar", "pps_camera", "pps_ins", "dropped_frames", "scan_time_span",
            "rtk_fixed", "ins_coverage", "messages_present"} <= names
    assert all(c["passed"] for c in checks)
    assert all(c["agent_id"] in ("red", "black") for c in checks)


def test_ins_gap_quarantines_and_names_the_span(tmp_path: Path) -> None:
    lake = Lake(tmp_path / "lake")
    run_ingest(lake, write_clip(tmp_path / "good", MiniClip(seconds=0.3, points=200,
                                                             clip_id="good", cameras=())))
    run_ingest(lake, write_clip(tmp_path / "gap", MiniClip(
        seconds=0.5, points=200, clip_id="gap", ins_gap_s=(0.15, 0.3), cameras=())))
    run_qa(lake, "good")
    with pytest.raises(ClipError) as e:
        run_qa(lake, "gap")
    err = e.value
    assert err.agent_id == "red" and err.topic == "/red/ins" and err.stage == "qa"
    # INS missing in [0.152, 0.296] s: scans 1-3 (0.1-0.399 s; scan 3 starts at 0.300 and
    # its previous sample is at 0.144) are not bracketed; the clip's axis starts 48 ms before
    assert "ins_coverage" in str(err) and "[+0.148 s, +0.447 s]" in str(err)
    # QA only says why; the flow quarantines, once, with the checks the error carries
    assert not is_quarantined(lake, "gap")
    bookkeeping.quarantine(lake, "gap", err, stage="qa")
    rep = read_report(lake, "gap")
    assert rep is not None and rep["stage"] == "qa"
    assert {c["check"] for c in rep["failed_checks"]} >= {"ins_coverage", "dropped_frames"}
    assert is_quarantined(lake, "gap")
    # the clip is gone from the raw zone and the catalog; the other clip is untouched
    assert not [f for f in lake.list_files(lake.path("raw")) if "clip_id=gap" in f]
    cat = Catalog(lake)
    assert cat.query("SELECT DISTINCT clip_id FROM lidar_points").to_pylist() == [
        {"clip_id": "good"}]
    assert cat.query("SELECT clip_id FROM quarantine").to_pylist() == [{"clip_id": "gap"}]
    # the flow quarantining again with the ClipError keeps the failed checks
    quarantine(lake, "gap", err)
    rep2 = read_report(lake, "gap")
    assert rep2 is not None and rep2["failed_checks"] and rep2["error"]["topic"] == "/red/ins"


def test_camera_off_grid_is_an_error(tmp_path: Path) -> None:
    """A camera declared PPS-locked 5 ms after the edge, whose frames come on the edge."""
    d = write_clip(tmp_path / "c", MiniClip(seconds=0.2, points=100, clip_id="cam"))
    meta = yaml.safe_load((d / "clip.yaml").read_text())
    cam = meta["agents"][0]["sensors"][1]
    assert cam["modality"] == "camera"
    cam["sync"] = {"mode": "pps", "phase_ms": 5.0}
    (d / "clip.yaml").write_text(yaml.safe_dump(meta))
    lake = Lake(tmp_path / "lake")
    run_ingest(lake, d)
    with pytest.raises(ClipError, match=r"pps_camera: 6/6 stamps of /red/camera/CAM_FRONT/image "
                       r"off the PPS \+ 5 ms \+ k x 33.333 ms grid"):
        run_qa(lake, "cam")
    # a tolerance that covers the offset (a per-clip QA parameter) lets them pass
    wide = QaConfig(tolerance_ms=GridTolerance(camera=6.0))
    assert run_qa(lake, "cam", wide).metrics["errors"] == 0



@requires_real_data("bags/ouster_os1_128_3frames_ros2")
def test_ouster_real_bag_passes_with_warnings(tmp_path: Path) -> None:
    lake = Lake(tmp_path / "lake")
    run_ingest(lake, REPO / "tests" / "fixtures" / "ouster", REAL_DATA_INGEST)
    rep = run_qa(lake, "ouster-os1-128-real")
    assert rep.metrics["errors"] == 0
    joined = "\n".join(rep.notes)
    assert "no pose source (no pose block and no INS topic configured): deskew/registration " \
        "impossible" in joined
    assert "free-running clock" in joined  # scans at +50 ms from the grid: no PPS, warning
    checks = {c["check"]: c for c in Catalog(lake).query(
        "SELECT * FROM qa_checks").to_pylist()}
    assert checks["scan_time_span"]["passed"] and 99 < checks["scan_time_span"]["value"] < 100.1
    assert not checks["ins_coverage"]["passed"] and checks["ins_coverage"]["severity"] == "warning"


def test_qa_without_ingest_is_a_clip_error(tmp_path: Path) -> None:
    with pytest.raises(ClipError, match="run ingest first"):
        run_qa(Lake(tmp_path / "lake"), "never")
