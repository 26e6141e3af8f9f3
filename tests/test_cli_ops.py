"""The command line as an operator uses it in a pipe or CI log: plain progress lines, result
tables or JSON, clear one-line errors, and ``params show`` without importing the stages."""

from __future__ import annotations

import io
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import test_flows_fakestages as fakes

REPO = Path(__file__).resolve().parents[1]
CLI = [sys.executable, "-m", "v2xlake.flows.cli"]


def _env(tmp: Path, **extra: str) -> dict[str, str]:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), str(REPO / "tests")]),
               V2XLAKE_NOOP_CACHE=str(tmp / "noop.json"), COLUMNS="160")
    env.update(extra)
    return env


def test_simulate_into_non_empty_folder_is_one_line(tmp_path: Path) -> None:
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "keep.txt").write_text("mine")
    res = subprocess.run([*CLI, "simulate", str(tmp_path / "out"), "--seconds", "0.2"],
                         env=_env(tmp_path), capture_output=True, text=True, timeout=120)
    assert res.returncode == 2
    assert "Traceback" not in res.stderr and "not empty" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1, res.stderr
    assert (tmp_path / "out" / "keep.txt").read_text() == "mine"


def test_stage_progress_plain_lines_off_a_terminal() -> None:
    from rich.console import Console

    from v2xlake.flows.cli import StageProgress

    events: list[dict[str, Any]] = [
        {"event": "stage_start", "clip_id": "c1", "stage": "ingest"},
        {"event": "stage_end", "clip_id": "c1", "stage": "ingest", "status": "done",
         "seconds": 1.25},
        {"event": "stage_start", "clip_id": "c1", "stage": "register"},
        {"event": "stage_end", "clip_id": "c1", "stage": "register",
         "status": "not_applicable", "seconds": 0.0, "reason": "one agent [x]"}]
    buf = io.StringIO()
    with StageProgress(2, Console(file=buf, width=200)) as prog:  # a pipe
        for e in events:
            prog(e)
    lines = buf.getvalue().splitlines()
    assert any("1/2 c1: ingest done in 1.2 s" in ln for ln in lines), lines
    assert any("2/2 c1: register not_applicable in 0.0 s (one agent [x])" in ln
               for ln in lines), lines
    tty = io.StringIO()
    with StageProgress(2, Console(file=tty, width=200, force_terminal=True)) as prog:
        for e in events:
            prog(e)
    assert "1/2 c1: ingest done" not in tty.getvalue()  # the live bar instead


def test_metric_table_not_a_dict() -> None:
    from rich.console import Console

    from v2xlake.flows.cli import metric_table

    buf = io.StringIO()
    Console(file=buf, width=120).print(metric_table("nuscenes: 1 clip(s)", {
        "samples": 20.0, "boxes_dropped_no_points": 3.0, "mean_points": 1234.5678}))
    out = buf.getvalue()
    assert "{" not in out and "samples" in out and "20" in out and "1235" in out


def test_export_steps_reach_the_cli_as_lines_or_a_bar() -> None:
    """Exporters call ``report_step``; under ``export_progress`` the CLI's listener prints
    one plain line per step finished, per ``every`` units and per unit of a short step (a few
    clips) off a terminal, a bar on one;
    with no listener the call does nothing (release builds, tests)."""
    from rich.console import Console

    from v2xlake.flows.cli import StepProgress
    from v2xlake.tasks.export.common import export_progress, report_step
    from v2xlake.tasks.export.exporters import _per_clip

    def one_clip(cid: str) -> Any:
        for k in range(1, 8):
            report_step(f"bev {cid}/car: scans", k, 7)
        return cid

    report_step("nobody listens", 1, 1)  # no hook: nothing, no error
    buf = io.StringIO()
    with StepProgress(Console(file=buf, width=200), every=2) as prog, export_progress(prog):
        assert _per_clip("bev", ["c1", "c2"], one_clip) == ["c1", "c2"]
        for n in range(1, 4):
            report_step("rosbag c1_all: messages", n)  # total unknown: every 2nd
    report_step("after the block", 1, 1)
    lines = buf.getvalue().splitlines()
    assert sum("bev c1/car: scans 7/7 done" in ln for ln in lines) == 1, lines
    assert any("bev c1/car: scans 6/7" in ln for ln in lines)
    assert not any("bev c1/car: scans 3/7" in ln for ln in lines)
    assert any("bev: clips 1/2" in ln for ln in lines) and any("bev: clips 2/2 done" in ln
                                                               for ln in lines)
    assert any("rosbag c1_all: messages 2" in ln for ln in lines)
    assert not any("after the block" in ln or "nobody" in ln for ln in lines)
    tty = io.StringIO()
    with StepProgress(Console(file=tty, width=200, force_terminal=True)) as prog, \
            export_progress(prog):
        _per_clip("bev", ["c1"], one_clip)
    assert "done" not in tty.getvalue() and "bev: clips" in tty.getvalue()  # the bar


@pytest.mark.slow
def test_process_piped_prints_a_line_per_stage(prefect_server: Any, tmp_path: Path) -> None:
    clip = fakes.make_fake_clip(tmp_path / "in", "piped_clip")
    lake = tmp_path / "lake"
    cmd = [*CLI, "process", str(clip), "--lake", str(lake), "--pipeline", fakes.FAKES]
    env = _env(tmp_path, PREFECT_API_URL=prefect_server.api_url)
    res = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
    for i, stage in enumerate(("ingest", "qa", "annotate"), 1):
        assert f"{i}/3 piped_clip: {stage} done in" in res.stdout, res.stdout
    assert "clip piped_clip: ok" in res.stdout
    # again: answered from the manifests, no Prefect, as JSON
    res = subprocess.run([*cmd, "--format", "json"], env=env, capture_output=True, text=True,
                         timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    doc = json.loads(res.stdout)
    assert [s["status"] for s in doc[0]["stages"]] == ["cached"] * 3
    assert "already current" in res.stderr


def test_params_show_second_call_imports_no_stage(tmp_path: Path) -> None:
    env = _env(tmp_path)
    first = subprocess.run([*CLI, "params", "show"], env=env, capture_output=True, text=True,
                           timeout=300)
    assert first.returncode == 0, first.stderr[-2000:]
    second = subprocess.run([sys.executable, "-X", "importtime", *CLI[1:], "params", "show"],
                            env=env, capture_output=True, text=True, timeout=300)
    assert second.returncode == 0 and second.stdout == first.stdout
    imported = {ln.split("|")[-1].strip() for ln in second.stderr.splitlines() if "|" in ln}
    heavy = sorted(m for m in imported if m.startswith(("v2xlake.tasks.", "prefect", "open3d",
                                                        "scipy")))
    assert heavy == [], heavy
    assert "deskew:" in first.stdout and "export:" in first.stdout


PRESTART_PROBE = """
import json
from v2xlake.flows.server import prestart_temporary_server
from v2xlake.flows.settings import prefect_session
wait = prestart_temporary_server()
import v2xlake.flows.pipeline  # the stages import while the server starts
wait()
from prefect.server.api.server import SubprocessASGIServer
early = SubprocessASGIServer()
url, proc = early.api_url, early.server_process
with prefect_session():
    from trivial_flow import trivial_clip_flow
    from prefect.client.orchestration import get_client
    n = trivial_clip_flow(3)
    with get_client(sync_client=True) as client:
        used = str(client.api_url).rstrip("/")
print(json.dumps([n, url, used, early.server_process is proc,
                  len(SubprocessASGIServer._instances)]))
"""


def test_temporary_server_prestarted_is_the_one_the_flow_uses(tmp_path: Path) -> None:
    """``prestart_temporary_server``: Prefect's temporary server comes up while the stages
    import, and the flow run uses that very server (no second one)."""
    env = _env(tmp_path, V2XLAKE_HOME=str(tmp_path / "home"))
    env.pop("PREFECT_API_URL", None)
    res = subprocess.run([sys.executable, "-c", PRESTART_PROBE], env=env, capture_output=True,
                         text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    n, url, used, same_process, instances = json.loads(res.stdout.strip().splitlines()[-1])
    assert n == 3 and used == url and same_process and instances == 1, res.stdout
