"""The no-op check before Prefect (``flows.noop``): a clip whose stages are all current is
answered from its manifests, with the flow's own key, without starting Prefect; a changed
input makes it run again. ``v2xlake process`` with ``PREFECT_API_URL`` set never starts
Prefect's temporary server."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
import test_flows_fakestages as fakes

from v2xlake.flows.cli import main
from v2xlake.flows.noop import current_summaries

REPO = Path(__file__).resolve().parents[1]


def _no_temporary_server(monkeypatch: pytest.MonkeyPatch) -> None:
    from prefect.server.api import server as prefect_server

    def refuse(*a: Any, **k: Any) -> None:
        raise AssertionError("Prefect's temporary server was started")

    monkeypatch.setattr(prefect_server.SubprocessASGIServer, "start", refuse)


@pytest.mark.slow
def test_current_clips_answered_before_prefect(prefect_server: Any, tmp_path: Path,
                                                monkeypatch: pytest.MonkeyPatch,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setenv("V2XLAKE_NOOP_CACHE", str(tmp_path / "noop.json"))
    monkeypatch.setenv("COLUMNS", "200")
    import v2xlake.flows.noop as noop

    monkeypatch.setattr(noop, "RACY_S", 0.0)  # the files were written seconds ago
    _no_temporary_server(monkeypatch)  # PREFECT_API_URL is set: the real server only
    a = fakes.make_fake_clip(tmp_path / "in", "noop_a")
    b = fakes.make_fake_clip(tmp_path / "in", "noop_b")
    lake = str(tmp_path / "lake")
    assert current_summaries([a, b], lake, pipeline=fakes.FAKES) == [None, None]  # no lake
    rc = main(["process", str(a), str(b), "--lake", lake, "--pipeline", fakes.FAKES])
    assert rc == 0, capsys.readouterr()
    capsys.readouterr()
    # the flow's own answer on a re-run, for comparison
    from v2xlake.flows.pipeline import process_clips

    flow_says = process_clips([str(a)], lake, pipeline=fakes.FAKES)[0]
    assert [o["status"] for o in flow_says["stages"]] == ["cached"] * 3
    t0 = time.perf_counter()
    fast = current_summaries([a, b], lake, pipeline=fakes.FAKES)
    dt = time.perf_counter() - t0
    assert fast[0] is not None and fast[1] is not None
    assert fast[0]["stages"] == flow_says["stages"] and fast[0]["status"] == "ok"
    assert dt < 5.0
    # remembered with the stat of what the check read, and answered the same from there
    assert len(list(noop.answers_dir().glob("*.json"))) == 2
    assert current_summaries([a, b], lake, pipeline=fakes.FAKES) == fast
    # the CLI answers without any flow (process_clips would fail the test)
    import v2xlake.flows.pipeline as pipeline_mod

    def no_flow(*a: Any, **k: Any) -> None:
        raise AssertionError("a flow ran for current clips")

    monkeypatch.setattr(pipeline_mod, "process_clips", no_flow)
    rc = main(["process", str(a), str(b), "--lake", lake, "--pipeline", fakes.FAKES,
               "--format", "json"])
    out = capsys.readouterr().out
    assert rc == 0
    doc = json.loads(out)
    assert [r["clip_id"] for r in doc] == ["noop_a", "noop_b"]
    assert all(s["status"] == "cached" for r in doc for s in r["stages"])
    # a changed input: that clip must run again, the other is still current
    (b / "red.bin").write_bytes(b"changed")
    fast = current_summaries([a, b], lake, pipeline=fakes.FAKES)
    assert fast[0] is not None and fast[1] is None
    # only the stages asked for; unknown stage names are an error
    fast = current_summaries([a], lake, ["qa"], pipeline=fakes.FAKES)
    assert fast[0] is not None and [o["stage"] for o in fast[0]["stages"]] == ["qa"]
    with pytest.raises(ValueError, match="unknown stage"):
        current_summaries([a], lake, ["qaa"], pipeline=fakes.FAKES)
    # in a fresh process: neither Prefect nor any stage module is imported, and for a
    # remembered answer not even the lake's modules (pydantic, NumPy, pyarrow)
    probe = ("import sys, json; from v2xlake.flows.noop import current_summaries; "
             f"r = current_summaries([{str(a)!r}], {lake!r}, pipeline={fakes.FAKES!r}); "
             "print(json.dumps([r[0] is not None, sorted(m for m in sys.modules "
             "if m in ('prefect', 'pydantic', 'numpy', 'pyarrow') "
             "or m.startswith('v2xlake.tasks'))]))")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), str(REPO / "tests")]))
    res = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True,
                         text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    assert json.loads(res.stdout.strip().splitlines()[-1]) == [True, []]
