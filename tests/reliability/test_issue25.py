"""#25: the last holes of the hostile-input surface and two regressions, each reproduced as
the probe did and failing on the code before its fix.

1. a YAML alias bomb hung the run in the log handler; 2. two processes on one clip lost a
table; 3. duplicated LiDAR messages were kept; 4. a symlink inside a zone let user SQL read
any file; 5. a hostile delivery claiming an existing id was reported as that clip
quarantined; 6. user SQL had no bound; 7. rich markup in query output, duplicate YAML keys,
a 300-character id, and unclear bag errors."""

from __future__ import annotations

import json
import os
import sqlite3
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import test_flows_fakestages as fakes
import yaml

from tests.fixtures.minibag import MiniClip, write_clip
from tests.reliability.test_ingest_checks import agent, lidar_sensor, scans, write
from tests.test_pose_sources import _ts
from v2xlake.flows.bookkeeping import refresh_catalog, user_query
from v2xlake.flows.cli import main
from v2xlake.schemas.clip import MAX_YAML_ALIAS_EXPANSION, load_yaml
from v2xlake.schemas.errors import MAX_ERROR_CHARS, ClipError
from v2xlake.storage.catalog import Catalog, QueryRefused, QueryTimeout
from v2xlake.storage.lake import ClipBusy, Lake, safe_name
from v2xlake.storage.quarantine import quarantine, read_report
from v2xlake.tasks.ingest import run_ingest
from v2xlake.tasks.ingest.clipdir import load_clip_config
from v2xlake.tasks.qa.stage import run_qa

REPO = Path(__file__).resolve().parents[2]
BOMB = "\n".join(
    [f"a: &a [{', '.join(['lol'] * 9)}]"]
    + [f"{n}: &{n} [{', '.join([f'*{p}'] * 9)}]" for p, n in zip("abcdefgh", "bcdefghi",
                                                                   strict=True)]) + "\n"


def _child(code: str, timeout: float = 300, **env: str) -> subprocess.CompletedProcess[str]:
    full = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), str(REPO / "tests")]),
            **env}
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=timeout, env=full, cwd=REPO)


# ------------------------------------------------------------------ 1. alias bomb
def test_an_alias_bomb_is_refused_at_once(tmp_path: Path) -> None:
    """Nine lines expanding to 9**9 values: refused by the YAML loader in milliseconds (the
    pydantic error of the expanded input used to take 20+ minutes to render)."""
    clip = tmp_path / "bomb"
    clip.mkdir()
    (clip / "clip.yaml").write_text(BOMB)
    t0 = time.perf_counter()
    with pytest.raises(ClipError, match="alias bomb") as e:
        load_clip_config(clip)
    assert time.perf_counter() - t0 < 2.0
    assert len(str(e.value)) < MAX_ERROR_CHARS + 200
    assert e.value.__cause__ is None or len(str(e.value.__cause__)) < MAX_ERROR_CHARS
    # aliases that stay small are still YAML
    small = "base: &b {x: 1}\nl: [*b, *b]\nm:\n  <<: *b\n  y: 2\n"
    assert load_yaml(small) == {"base": {"x": 1}, "l": [{"x": 1}, {"x": 1}],
                                "m": {"x": 1, "y": 2}}
    assert MAX_YAML_ALIAS_EXPANSION >= 10_000


def test_error_texts_are_bounded(tmp_path: Path) -> None:
    """A reason quoting a huge input: the ClipError, its quarantine report and the CLI line
    are all bounded."""
    e = ClipError("c1", "bad value " + "x" * 5_000_000, topic="/t" * 100_000)
    assert len(str(e)) < MAX_ERROR_CHARS + 1000 and "more characters" in str(e)
    lake = Lake(tmp_path / "lake")
    rep = quarantine(lake, "c1", e, stage="qa")
    assert len(json.dumps(rep)) < 10 * MAX_ERROR_CHARS
    assert len(Path(lake.path("quarantine", "c1", "report.json")).read_text()) < 20_000


@pytest.mark.slow
def test_the_flow_quarantines_an_alias_bomb_and_runs_the_next_clip(
        prefect_server: object, tmp_path: Path) -> None:
    bomb = tmp_path / "in" / "bomb"
    bomb.mkdir(parents=True)
    (bomb / "clip.yaml").write_text(BOMB)
    good = write_clip(tmp_path / "in" / "good", MiniClip(seconds=0.2, points=100, cameras=(),
                                                         clip_id="good"))
    lake = tmp_path / "lake"
    t0 = time.perf_counter()
    out = _child(
        "from v2xlake.flows.pipeline import process_clips\n"
        f"r = process_clips([{str(bomb)!r}, {str(good)!r}], {str(lake)!r}, ['ingest'])\n"
        "print('STATUS', [x['status'] for x in r])\n", timeout=240)
    assert out.returncode == 0, out.stderr[-3000:]
    assert "STATUS ['quarantined', 'ok']" in out.stdout, out.stdout[-2000:]
    assert time.perf_counter() - t0 < 240
    report = json.loads((lake / "quarantine" / "_unreadable-bomb" / "report.json").read_text())
    assert "alias bomb" in report["reason"] and len(report["reason"]) <= MAX_ERROR_CHARS


# ------------------------------------------------------------------ 2. one writer per clip
HOLD = ("import sys, time\nfrom v2xlake.storage.lake import Lake\n"
        "with Lake(sys.argv[1]).clip_lock(sys.argv[2]):\n"
        "    print('HELD', flush=True)\n    time.sleep(float(sys.argv[3]))\n")


def _hold(lake_uri: str, clip: str, seconds: float, env: dict[str, str] | None = None
          ) -> subprocess.Popen[str]:
    p = subprocess.Popen([sys.executable, "-c", HOLD, lake_uri, clip, str(seconds)],
                         stdout=subprocess.PIPE, text=True, cwd=REPO,
                         env={**os.environ, **(env or {})})
    assert p.stdout is not None and p.stdout.readline().strip() == "HELD"
    return p


def _lock_cycle(lake: Lake, holder: subprocess.Popen[str]) -> None:
    t0 = time.perf_counter()
    with pytest.raises(ClipBusy, match="being written by another run"):
        with lake.clip_lock("c1", wait_s=0.5):
            pass
    assert time.perf_counter() - t0 < 5
    with lake.clip_lock("c2", wait_s=0.5):  # another clip: not held
        with lake.clip_lock("c2", wait_s=0.5):  # re-entrant in one thread
            pass
    with lake.clip_lock("c1", wait_s=30):  # waits for the holder to finish
        assert holder.poll() is not None
    holder.wait()


def test_a_second_writer_of_a_clip_waits_or_is_refused(tmp_path: Path) -> None:
    lake = Lake(tmp_path / "lake")
    _lock_cycle(lake, _hold(lake.uri, "c1", 2.0))
    # a killed holder: the kernel drops its lock at once
    holder = _hold(lake.uri, "c1", 60)
    holder.kill()
    holder.wait()
    with lake.clip_lock("c1", wait_s=2):
        pass


@pytest.mark.slow
def test_the_s3_lock_excludes_another_process(s3_env: Any) -> None:
    lake = Lake(f"s3://{s3_env.bucket}/locks")
    _lock_cycle(lake, _hold(lake.uri, "c1", 2.0, s3_env.env()))


@pytest.mark.slow
def test_a_stage_never_runs_while_another_process_writes_the_clip(
        prefect_server: object, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The flow takes the clip's lock from its cache check to its manifest: two runs of one
    clip never interleave (before: both exit 0, a table lost, the manifest current)."""
    from v2xlake.flows.pipeline import process_clip

    clip = fakes.make_fake_clip(tmp_path / "in", "c1")
    lake = Lake(tmp_path / "lake")
    monkeypatch.setenv("V2XLAKE_CLIP_LOCK_WAIT_S", "1")
    holder = _hold(lake.uri, "c1", 120)
    try:
        state = process_clip(str(clip), lake.uri, pipeline=fakes.FAKES, return_state=True)
        assert state.is_failed() and "being written by another run" in (state.message or "")
        assert not Path(lake.path("manifests", "c1")).exists()
    finally:
        holder.kill()
        holder.wait()
    assert process_clip(str(clip), lake.uri, pipeline=fakes.FAKES)["status"] == "ok"
    # a recorded output that went missing is repaired by the next run, not called current
    m = json.loads(Path(lake.path("manifests", "c1", "annotate.json")).read_text())
    lost = Path(lake.path(m["outputs"][0]["path"]))
    lost.unlink()
    summary = process_clip(str(clip), lake.uri, pipeline=fakes.FAKES)
    assert {o["stage"]: o["status"] for o in summary["stages"]}["annotate"] == "done"
    assert lost.is_file()


# ------------------------------------------------------------------ 3. duplicated frames
def test_a_lidar_scan_delivered_twice_is_dropped_and_counted(tmp_path: Path) -> None:
    ts = _ts()
    once = scans(ts, 4)
    d = write(tmp_path / "dup", [agent(sensors=[lidar_sensor()])],
              {"bag_car": [m for m in once for _ in range(2)]})
    lake = Lake(tmp_path / "lake")
    rep = run_ingest(lake, d)
    frames = lake.read_table("raw", "lidar_frames", clip_id="dup")
    assert frames.num_rows == 4 and sorted(frames.column("frame_idx").to_pylist()) == [0, 1, 2, 3]
    ref = run_ingest(Lake(tmp_path / "lake1"),
                     write(tmp_path / "once", [agent(sensors=[lidar_sensor()])],
                           {"bag_car": once}))
    assert rep.metrics["lidar_points"] == ref.metrics["lidar_points"]
    s = lake.read_table("raw", "sensors", clip_id="dup").to_pylist()[0]
    assert (s["n_messages"], s["n_duplicates"]) == (4, 4)
    qa = run_qa(lake, "dup")
    assert any("duplicate_messages car/LIDAR_TOP: 4 message(s) on /lidar repeat an earlier "
               "stamp (dropped at ingest)" in n for n in qa.notes), qa.notes


def test_two_different_scans_with_one_stamp_are_refused(tmp_path: Path) -> None:
    ts = _ts()
    msgs = scans(ts, 3)
    other = scans(ts, 3)[1]
    cloud = other[3]
    data = np.array(cloud.data, copy=True)
    data[:4] ^= 0xFF  # another payload, the same header stamp
    msgs.append((other[0], other[1], other[2] + 1, type(cloud)(**{
        **{f: getattr(cloud, f) for f in cloud.__dataclass_fields__}, "data": data})))
    msgs.sort(key=lambda m: m[2])
    d = write(tmp_path / "clash", [agent(sensors=[lidar_sensor()])], {"bag_car": msgs})
    with pytest.raises(ClipError, match="two different lidar frames with the same stamp") as e:
        run_ingest(Lake(tmp_path / "lake"), d)
    assert (e.value.agent_id, e.value.topic) == ("car", "/lidar")


# ------------------------------------------------------------------ 4. symlinks in zones
@pytest.fixture(scope="module")
def lake(tmp_path_factory: pytest.TempPathFactory) -> Lake:
    tmp = tmp_path_factory.mktemp("i25")
    lake = Lake(tmp / "lake")
    for i, w in enumerate(("clear", "rain")):
        rep = fakes.fake_ingest(lake, fakes.make_fake_clip(tmp / "in", f"c{i}", weather=w))
        fakes.fake_annotate(lake, rep.clip_id)
    refresh_catalog(lake)
    return lake


def test_a_symlink_inside_a_zone_reads_nothing_outside(lake: Lake, tmp_path: Path) -> None:
    """``ln -s /etc L/raw/evil; v2xlake query "SELECT * FROM read_text('L/raw/evil/hostname')"``
    printed the file: DuckDB's allowed folders are a text prefix that follows links. Now the
    connection may open exactly the files its views list, and listings leave links out."""
    Path(lake.path("raw")).mkdir(exist_ok=True)
    evil = Path(lake.path("raw", "evil"))
    evil.symlink_to("/etc")
    outside = tmp_path / "outside" / "clip_id=zz"
    outside.mkdir(parents=True)
    good = next(Path(lake.path("clean", "clips")).rglob("*.parquet"))
    (outside / "part.parquet").write_bytes(good.read_bytes())
    sneaky = Path(lake.path("clean", "clips", "clip_id=zz"))
    sneaky.symlink_to(outside)
    linked_file = Path(lake.path("clean", "clips", "clip_id=c0", "linked.parquet"))
    linked_file.symlink_to(outside / "part.parquet")
    try:
        for sql in (f"SELECT * FROM read_text('{evil}/hostname')",
                    f"SELECT * FROM read_text('{lake.path('raw')}/*/hostname')",
                    f"SELECT * FROM read_parquet('{sneaky}/part.parquet')",
                    f"SELECT * FROM read_parquet('{linked_file}')"):
            with pytest.raises(Exception, match=r"disabled by configuration|No files found"):
                user_query(lake, sql)
        ids = user_query(lake, "SELECT clip_id FROM clips ORDER BY 1").column(0).to_pylist()
        assert ids == ["c0", "c1"]  # the linked partition and file are not the lake's
        assert main(["query", f"SELECT * FROM read_text('{evil}/hostname')", "--lake",
                     lake.uri]) == 2
    finally:
        for p in (evil, sneaky, linked_file):
            p.unlink()


def test_the_api_surface_refuses_the_link_too(lake: Lake) -> None:
    from v2xlake.api import Lake as ApiLake

    evil = Path(lake.path("clean", "evil"))
    evil.symlink_to("/etc")
    try:
        api = ApiLake(lake.uri)
        with pytest.raises(Exception, match="disabled by configuration"):
            api.sql(f"SELECT * FROM read_text('{evil}/hostname')")
    finally:
        evil.unlink()


# ------------------------------------------------------------------ 5. a claimed id
@pytest.mark.slow
def test_a_hostile_delivery_claiming_an_id_never_quarantines_that_clip(
        prefect_server: object, tmp_path: Path) -> None:
    from tests.reliability.test_hostile_inputs import _set_bag
    from v2xlake.flows.pipeline import process_clip
    from v2xlake.storage.quarantine import is_quarantined

    lake = Lake(tmp_path / "lake")
    good = write_clip(tmp_path / "in" / "c1", MiniClip(seconds=0.2, points=100, cameras=(),
                                                       clip_id="c1"))
    assert process_clip(str(good), lake.uri, ["ingest"])["status"] == "ok"
    hostile = write_clip(tmp_path / "in4" / "h", MiniClip(seconds=0.2, points=100, cameras=(),
                                                          clip_id="c1"))
    _set_bag(hostile, "/etc/hostname")
    state = process_clip(str(hostile), lake.uri, ["ingest"], return_state=True)
    assert state.is_failed() and "rejected" in (state.message or "")
    assert "c1 untouched" in (state.message or "")
    assert not is_quarantined(lake, "c1")
    rep = read_report(lake, "_rejected-c1")
    assert rep is not None and "outside the clip folder" in rep["reason"]
    assert user_query(lake, "SELECT count(*) AS n FROM quarantine WHERE clip_id = 'c1'"
                      ).to_pylist() == [{"n": 1}]  # the report names what it claimed
    # the good clip is current: nothing to redo
    summary = process_clip(str(good), lake.uri, ["ingest"])
    assert summary["status"] == "ok" and summary["stages"][0]["status"] == "cached"


# ------------------------------------------------------------------ 6. SQL bounds
def test_a_huge_answer_streams_the_first_rows_and_counts_the_rest(lake: Lake) -> None:
    # the child reports its own peak (RUSAGE_CHILDREN of this process would be the largest
    # of every child any earlier test started, e.g. a Prefect server)
    code = ("import atexit, resource, sys\nfrom v2xlake.flows.cli import main\n"
            "atexit.register(lambda: print('PEAK_KIB', resource.getrusage("
            "resource.RUSAGE_SELF).ru_maxrss, file=sys.stderr))\n"
            f"sys.exit(main(['query', 'SELECT * FROM range(200000000)', '--lake', {lake.uri!r}]))")
    t0 = time.perf_counter()
    out = _child(code, timeout=180)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "199,999,950 more rows" in out.stdout
    peak_mib = int(out.stderr.rsplit("PEAK_KIB", 1)[1].split()[0]) / 1024
    assert peak_mib < 1200, peak_mib  # 200 M int64 materialised would be 1.6 GB
    assert time.perf_counter() - t0 < 170


def test_user_sql_has_a_timeout_a_memory_limit_and_a_row_cap(
        lake: Lake, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("V2XLAKE_QUERY_TIMEOUT_S", "2")
    t0 = time.perf_counter()
    with pytest.raises(QueryTimeout, match="statement timeout"):
        user_query(lake, "SELECT count(*) FROM range(20000000000)")
    assert time.perf_counter() - t0 < 15
    assert user_query(lake, "SELECT current_setting('memory_limit') AS m").to_pylist()[0][
        "m"].endswith("GiB")
    assert user_query(lake, "SELECT * FROM range(1500000)").num_rows == 1_500_000  # no cap
    monkeypatch.setenv("V2XLAKE_QUERY_MAX_ROWS", "1000")
    with pytest.raises(QueryRefused, match="more than 1,000 rows"):
        user_query(lake, "SELECT * FROM range(5000)")
    assert user_query(lake, "SELECT * FROM range(1000)").num_rows == 1000
    with Catalog(lake, read_only=True) as cat:
        head = cat.user_query_head("SELECT * FROM range(5000)", 10)
        assert (head.table.num_rows, head.total_rows) == (10, 5000)


def test_a_where_that_cannot_be_interrupted_is_stopped(
        lake: Lake, monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """``length(repeat('a', 2000000000)) > 0`` ran six minutes: one DuckDB call is not
    interruptible, so the predicate runs in a child process killed at the bound."""
    import tempfile

    from v2xlake.flows.release import build_release

    monkeypatch.setenv("V2XLAKE_QUERY_TIMEOUT_S", "2")
    # the killed child's private database must not outlive it (it leaked one folder a run)
    tmp = tmp_path
    monkeypatch.setenv("TMPDIR", str(tmp))
    monkeypatch.setattr(tempfile, "tempdir", str(tmp))
    t0 = time.perf_counter()
    with pytest.raises(QueryTimeout, match="statement timeout"):
        build_release(lake.uri, "slow", "length(repeat('a', 2000000000)) > 0", ["lake"], 0,
                      (1.0, 0.0, 0.0))
    assert time.perf_counter() - t0 < 2 + 3 + 20
    assert list(tmp.iterdir()) == []
    assert not Path(lake.path("releases", "slow")).exists()
    meta = build_release(lake.uri, "fast", "weather = 'rain'", ["lake"], 0, (1.0, 0.0, 0.0))
    assert meta["clip_ids"] == ["c1"]


# ------------------------------------------------------------------ 7. the smaller items
@pytest.mark.parametrize("sql", ["SELECT '[/x]' AS a", "SELECT '[bold]x[/]' AS \"[/y]\"",
                                 "SELECT * FROM duckdb_settings()"])
def test_query_output_is_text_not_markup(lake: Lake, sql: str,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["query", sql, "--lake", lake.uri]) == 0
    out = capsys.readouterr().out
    if "'[/x]'" in sql:
        assert "[/x]" in out


def test_duplicate_yaml_keys_are_refused(tmp_path: Path) -> None:
    clip = write_clip(tmp_path / "dupkey", MiniClip(seconds=0.2, points=100, cameras=(),
                                                    clip_id="dupkey"))
    text = (clip / "clip.yaml").read_text()
    (clip / "clip.yaml").write_text(text.replace("weather: clear", "weather: clear\n"
                                                 "weather: rain", 1))
    assert "weather: rain" in (clip / "clip.yaml").read_text()
    with pytest.raises(ClipError, match="duplicate key 'weather'"):
        load_clip_config(clip)


def test_a_300_character_clip_id_is_a_clip_error(tmp_path: Path) -> None:
    long_id = "c" * 300
    clip = write_clip(tmp_path / "long", MiniClip(seconds=0.2, points=100, cameras=(),
                                                  clip_id="long"))
    cfg = yaml.safe_load((clip / "clip.yaml").read_text())
    cfg["clip_id"] = long_id
    (clip / "clip.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    lake = Lake(tmp_path / "lake")
    with pytest.raises(ClipError, match="clip_id: String should match pattern"):
        run_ingest(lake, clip)
    # whatever name a broken delivery gets, its report can be written
    rep = quarantine(lake, "_unreadable-" + "x" * 300, "broken", zones=())
    assert len(rep["report_id"]) < 130
    assert read_report(lake, "_unreadable-" + "x" * 300) is not None
    assert safe_name("c1") == "c1"


def test_bag_open_errors_name_the_field_and_the_file(tmp_path: Path) -> None:
    clip = write_clip(tmp_path / "c", MiniClip(seconds=0.2, points=100, cameras=(),
                                               clip_id="c", agents=("red",)))
    meta = clip / "red" / "metadata.yaml"
    original = meta.read_text()
    meta.write_text(original.replace("storage_identifier: sqlite3", "storage_identifier: ''"))
    (clip / "red" / "red.db3").rename(tmp_path / "away.db3")
    with pytest.raises(ClipError, match=r"lists data file\(s\) \['red.db3'\] that are not in"):
        run_ingest(Lake(tmp_path / "l1"), clip)
    (tmp_path / "away.db3").rename(clip / "red" / "red.db3")
    meta.write_text(original.replace("serialization_format: cdr", "serialization_format: ''",
                                     1))
    with pytest.raises(ClipError, match=r"field 'serialization_format' of topic .* is empty in "
                       r"metadata.yaml"):
        run_ingest(Lake(tmp_path / "l2"), clip)


def test_convert_bag_without_type_definitions_names_the_type(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    clip = write_clip(tmp_path / "c", MiniClip(seconds=0.2, points=100, cameras=(),
                                               clip_id="c", agents=("red",)))
    con = sqlite3.connect(clip / "red" / "red.db3")
    con.execute("DELETE FROM message_definitions")
    con.commit()
    con.close()
    meta = clip / "red" / "metadata.yaml"
    meta.write_text("".join(line for line in meta.read_text().splitlines(keepends=True)
                            if "offered_qos_profiles" not in line))
    assert main(["convert-bag", str(clip / "red"), str(tmp_path / "out"), "--to", "ros1"]) == 2
    err = capsys.readouterr().err
    assert "v2xlake_msgs/msg/InsPva" in err and "Traceback" not in err


def test_camera_size_error_names_camera_info_as_the_source(tmp_path: Path) -> None:
    """The extrinsic from clip.yaml, the intrinsics from a CameraInfo topic: the error said
    "clip.yaml intrinsics"."""
    from tests.reliability.test_ingest_checks import T0, _cam_sensor, _camera, _jpeg

    ts = _ts()
    cam = {**_cam_sensor(), "extrinsic": lidar_sensor()["extrinsic"]}
    bag = [*scans(ts, 2), *_camera(ts, T0, _jpeg(64, 48), (32, 24))]
    d = write(tmp_path / "camsize", [agent(sensors=[lidar_sensor(), cam])], {"bag_car": bag})
    with pytest.raises(ClipError) as e:
        run_ingest(Lake(tmp_path / "lake"), d)
    assert "images are 64x48 but its CameraInfo intrinsics (topic /cam_info) are for 32x24" \
        in e.value.reason, e.value.reason


def test_audit_of_a_lake_without_cameras_finds_nothing_unreadable(tmp_path: Path) -> None:
    from v2xlake.audit import audit

    lake = Lake(tmp_path / "lake")
    run_ingest(lake, write_clip(tmp_path / "nocam", MiniClip(seconds=0.2, points=100,
                                                            cameras=(), clip_id="nocam")))
    report = audit(lake, "raw", sample_images=0)
    assert not [f for f in report.findings if f.kind == "unreadable"], report.findings


def test_a_locked_catalog_dropped_without_close_removes_its_copy(lake: Lake) -> None:
    """The read-only copy of a locked-down catalog lives in a private temporary folder; a
    catalog the caller forgets to close must not leave it behind."""
    import gc

    cat = Catalog(lake, read_only=True)
    cat.lock_down()
    folder = cat._tmpdir
    assert folder is not None and Path(folder).is_dir()
    cat.con.close()
    del cat
    gc.collect()
    assert not Path(folder).exists()
    with Catalog(lake, read_only=True) as cat:  # and close() removes it at once
        cat.lock_down()
        folder = cat._tmpdir
    assert folder is not None and not Path(folder).exists()
