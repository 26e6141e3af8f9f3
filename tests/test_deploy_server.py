"""deploy/start_server.py as an operator runs it: the Prefect UI answers at ``/`` and on a
flow run's page, and every deployment of deploy/prefect.yaml is created (its work pools
too); a deployment that cannot be created fails deploy/deploy.py with its name."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest
import yaml

from tests.fixtures.processes import stop_group
from v2xlake.flows.deployments import declared, deployments_on_server, missing
from v2xlake.flows.server import free_port

REPO = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow


def _get(url: str) -> tuple[int, str]:
    """GET as a browser navigating to a page asks (the UI answers its routes' pages only
    to such requests)."""
    req = urllib.request.Request(url, headers={"Accept": "text/html,*/*;q=0.8"})
    with urllib.request.urlopen(req, timeout=30) as r:
        return r.status, r.read().decode(errors="replace")


def test_missing_names_each_absent_deployment() -> None:
    deps = [{"name": "a", "work_pool": {"name": "p"}}, {"name": "b", "work_pool": {"name": "q"}},
            {"name": "c"}]
    assert missing(deps, {"a": "p", "b": "q", "c": ""}) == []
    assert missing(deps, {"a": "p"}) == ["b (work pool 'q')", "c"]
    assert missing(deps, {"a": "other", "b": "q", "c": ""}) == [
        "a (on pool 'other', declared 'p')"]


def test_start_server_serves_ui_and_creates_every_deployment(tmp_path: Path) -> None:
    port = free_port()
    env = dict(os.environ, V2XLAKE_HOME=str(tmp_path / "home"), PYTHONUNBUFFERED="1")
    env.pop("PREFECT_API_URL", None)
    proc = subprocess.Popen(
        [sys.executable, str(REPO / "deploy" / "start_server.py"), "--home",
         str(tmp_path / "server"), "--port", str(port), "--deploy", "--no-worker"],
        cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        start_new_session=True)
    lines: list[str] = []
    try:
        assert proc.stdout is not None
        deadline = time.monotonic() + 400
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line.rstrip())
            if line.startswith("ready"):
                break
        out = "\n".join(lines)
        assert lines and lines[-1].startswith("ready"), out
        api = f"http://127.0.0.1:{port}/api"
        assert f"export PREFECT_API_URL={api}" in out
        assert f"prefect UI: http://127.0.0.1:{port}/" in out
        # the UI: its page at / and a flow run's page (the links the tools print)
        status, html = _get(f"http://127.0.0.1:{port}/")
        assert status == 200 and "<html" in html.lower() and "prefect" in html.lower(), html[:500]
        run = subprocess.run([sys.executable, str(REPO / "tests" / "trivial_flow.py")],
                             env=dict(env, PREFECT_API_URL=api), capture_output=True,
                             text=True, timeout=180)
        assert run.returncode == 0, run.stderr[-2000:]
        run_id = run.stdout.split("flow_run_id=")[1].split()[0]
        status, page = _get(f"http://127.0.0.1:{port}/runs/flow-run/{run_id}")
        assert status == 200 and "<html" in page.lower() and "prefect" in page.lower()
        status, body = _get(f"http://127.0.0.1:{port}/ui-settings")  # where the app calls
        assert json.loads(body)["api_url"].rstrip("/").endswith("/api"), body
        # ... and what it shows there:
        status, body = _get(f"{api}/flow_runs/{run_id}")
        assert status == 200 and json.loads(body)["state"]["type"] == "COMPLETED"
        # every deployment of the file, each on its declared pool
        deps = declared()
        on_server = deployments_on_server(api)
        assert missing(deps, on_server) == [], on_server
        assert {"scan-landing", "release-build", "process-clips-cluster"} <= set(on_server)
        # a deployment whose pool is missing (and not created): plain `prefect deploy --all`
        # skips it beside one that deploys and exits 0; deploy.py exits 1 naming it
        bad = tmp_path / "prefect.yaml"
        entry = "tests/trivial_flow.py:trivial_flow"
        bad.write_text(yaml.safe_dump({"name": "t", "deployments": [
            {"name": "trivial-ok", "entrypoint": entry, "work_pool": {"name": "v2xlake"}},
            {"name": "trivial-on-missing-pool", "entrypoint": entry,
             "work_pool": {"name": "no-such-pool"}}]}))
        res = subprocess.run([sys.executable, str(REPO / "deploy" / "deploy.py"), "--api-url",
                              api, "--prefect-file", str(bad), "--no-create-pools"],
                             env=env, capture_output=True, text=True, timeout=300)
        assert res.returncode == 1, res.stdout[-2000:] + res.stderr[-2000:]
        assert "trivial-on-missing-pool (work pool 'no-such-pool')" in res.stderr, res.stderr
        assert "trivial-ok" in deployments_on_server(api)
    finally:
        stop_group(proc)
