"""The ``v2xlake`` command line: parsing, exit codes, output formats, the process command."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
import test_flows_fakestages as fakes

from v2xlake.flows.cli import main
from v2xlake.storage.lake import Lake


def _fake_lake(tmp: Path) -> Lake:
    lake = Lake(tmp / "lake")
    for i, (w, li) in enumerate([("clear", "day"), ("rain", "night"), ("clear", "night")]):
        rep = fakes.fake_ingest(lake, fakes.make_fake_clip(tmp / "in", f"c{i}", weather=w,
                                                             lighting=li))
        fakes.fake_annotate(lake, rep.clip_id)
    from v2xlake.flows.bookkeeping import refresh_catalog

    refresh_catalog(lake)
    return lake


def test_help_is_fast_and_lists_commands() -> None:
    exe = Path(sys.executable).with_name("v2xlake")
    t0 = time.perf_counter()
    out = subprocess.run([str(exe), "--help"], capture_output=True, text=True, timeout=60)
    took = time.perf_counter() - t0
    assert out.returncode == 0
    for cmd in ("demo", "simulate", "process", "query", "export", "convert-bag", "plot",
                "audit", "release", "params", "catalog"):
        assert cmd in out.stdout
    print(f"v2xlake --help: {took:.2f} s")
    # the stage modules and Prefect are imported lazily, by the command that needs them
    probe = subprocess.run(
        [sys.executable, "-c", "import sys, v2xlake.flows.cli as c; "
         "c.main(['--help']); print(sorted(m for m in sys.modules if m.startswith(("
         "'prefect', 'v2xlake.tasks', 'duckdb', 'open3d', 'tasks', 'flows', 'schemas'))))"],
        capture_output=True, text=True, timeout=60)
    assert probe.stdout.strip().splitlines()[-1] == "[]", probe.stdout + probe.stderr


def test_version_and_usage_errors_without_traceback(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from v2xlake import __version__

    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"v2xlake {__version__}"
    lake = _fake_lake(tmp_path)
    cases = [
        (["export", "kitti", "--out", str(tmp_path / "x")], "kitti"),
        (["query", "SELEC clip_id FROM clips", "--lake", lake.uri], "syntax error"),
        (["query", "SELECT 1", "--lake", str(tmp_path / "lakee")], "no lake at"),
        (["export", "bev", "--lake", lake.uri, "--clip", "nope", "--out",
          str(tmp_path / "o")], "unknown clip"),
        (["process", str(tmp_path / "no_clip"), "--lake", lake.uri], "no clip.yaml"),
        # brackets in what the user typed are text, not rich markup (a "[deskew]" stage tag
        # at the start of an error used to vanish)
        (["view", "[deskew]c0", "--lake", lake.uri], "[deskew]c0"),
        (["release", "build", "r1", "--where", "true", "--lake", lake.uri, "--fractions",
          "nan,nan,nan"], "finite"),
        (["plot", "registration", "--clip", "c0", "--lake", lake.uri, "--out", str(tmp_path)],
         "is a folder"),
    ]
    for argv, msg in cases:
        assert main(argv) == 2, argv
        cap = capsys.readouterr()
        assert msg in cap.err + cap.out, (argv, cap.err)
        assert "Traceback" not in cap.err + cap.out
    assert not (tmp_path / "lakee").exists()  # a mistyped lake is never created
    full = tmp_path / "full"
    full.mkdir()
    (full / "keep.txt").write_text("x")
    assert main(["export", "bev", "--lake", lake.uri, "--out", str(full)]) == 2
    assert "not empty" in capsys.readouterr().err


def test_sim_config_from_cli_options() -> None:
    from v2xlake.flows.cli import sim_config

    cfg = sim_config("small", 1.5, "mcap", 9, "red,black,rsu", "3")
    assert cfg.seconds == 1.5 and cfg.storage == "mcap" and cfg.seed == 9
    assert tuple(cfg.agents) == ("red", "black", "rsu") and len(cfg.cameras) == 3
    cfg = sim_config("small", None, None, None, None, "CAM_FRONT,CAM_BACK")
    assert tuple(cfg.cameras) == ("CAM_FRONT", "CAM_BACK")


def test_query_formats(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    lake = _fake_lake(tmp_path)
    sql = "SELECT clip_id, weather FROM clips ORDER BY clip_id"
    assert main(["query", sql, "--lake", lake.uri, "--format", "json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert rows == [{"clip_id": "c0", "weather": "clear"}, {"clip_id": "c1", "weather": "rain"},
                    {"clip_id": "c2", "weather": "clear"}]
    assert main(["query", sql, "--lake", lake.uri, "--format", "csv"]) == 0
    assert capsys.readouterr().out.splitlines() == ["clip_id,weather", "c0,clear", "c1,rain",
                                                     "c2,clear"]
    assert main(["query", "SELECT category, count(*) AS n FROM annotations GROUP BY 1 "
                 "ORDER BY 1", "--lake", lake.uri]) == 0
    assert "pedestrian" in capsys.readouterr().out


def test_release_commands_exit_codes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    lake = _fake_lake(tmp_path)
    assert main(["release", "build", "night", "--lake", lake.uri,
                 "--where", "lighting = 'night'", "--fractions", "0.5,0.5,0"]) == 0
    assert "2 clip(s)" in capsys.readouterr().out
    assert main(["release", "verify", "night", "--lake", lake.uri]) == 0
    assert main(["release", "list", "--lake", lake.uri]) == 0
    assert capsys.readouterr().out.splitlines()[-1] == "night"
    target = Path(lake.path("releases", "night", "RELEASE.md"))
    target.write_text(target.read_text() + "edited\n")
    assert main(["release", "verify", "night", "--lake", lake.uri]) == 1
    assert "RELEASE.md" in capsys.readouterr().out
    assert main(["release", "build", "night", "--lake", lake.uri, "--where", "true"]) == 2
    assert main(["release", "verify", "nope", "--lake", lake.uri]) == 1


@pytest.mark.slow
def test_process_command(prefect_server: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                         capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setenv("COLUMNS", "200")
    good = fakes.make_fake_clip(tmp_path / "in", "cli_good")
    bad = fakes.make_fake_clip(tmp_path / "in", "cli_bad", corrupt=True)
    lake = tmp_path / "lake"
    reg = fakes.FAKES
    rc = main(["process", str(good), str(bad), "--lake", str(lake), "--pipeline", reg])
    out = capsys.readouterr().out
    assert rc == 1  # one clip quarantined
    assert "clip cli_good: ok" in out and "quarantined" in out and "report.json" in out
    assert "1/2 clip(s) ok" in out
    rc = main(["process", str(good), "--lake", str(lake), "--pipeline", reg, "--stages",
               "ingest,qa"])
    out = capsys.readouterr().out
    assert rc == 0 and "cached" in out and "annotate" not in out
    assert main(["process", str(good), "--lake", str(lake), "--stages", "ingest,qaa"]) == 2
