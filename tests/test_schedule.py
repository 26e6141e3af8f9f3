"""The scheduled landing-zone scan, for real: server scheduler -> work pool -> process worker.

Deploys ``deploy/prefect.yaml``'s ``scan-landing`` with ``prefect deploy`` (interval cut to
5 s), starts ``prefect worker start --type process``, drops a new clip folder into the inbox
and waits (bounded) until the scheduled run has put it in the catalog.
"""

from __future__ import annotations

import asyncio
import json
import os
import subprocess
import sys
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import test_flows_fakestages as fakes
import yaml

from v2xlake.flows.bookkeeping import query
from v2xlake.flows.scan import find_new_clips
from v2xlake.flows.server import start_worker, stop_process
from v2xlake.storage.lake import Lake

REPO = Path(__file__).resolve().parents[1]


# A cap, not a deadline: each wait returns as soon as its event is seen (about 15-40 s on a
# quiet 2-core machine) and only a run that never happens waits this long; a loaded machine
# (the whole suite beside other jobs) took 150 s and more
WAIT_CAP_S = float(os.environ.get("V2XLAKE_TEST_WAIT_CAP_S", "600"))


def _wait_for(event: Callable[[], bool], cap_s: float = WAIT_CAP_S) -> bool:
    """Poll ``event`` once a second until it holds (True) or ``cap_s`` has passed (False)."""
    end = time.monotonic() + cap_s
    while not event():
        if time.monotonic() > end:
            return False
        time.sleep(1.0)
    return True


def _prefect(args: list[str], api_url: str, timeout: float = WAIT_CAP_S) -> str:
    env = dict(os.environ, PREFECT_API_URL=api_url)
    out = subprocess.run([sys.executable, "-m", "prefect", *args], cwd=REPO, env=env,
                         capture_output=True, text=True, timeout=timeout)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    return out.stdout


def test_prefect_yaml_entrypoints_resolve() -> None:
    spec = yaml.safe_load((REPO / "deploy" / "prefect.yaml").read_text())
    names = {d["name"]: d for d in spec["deployments"]}
    assert {"scan-landing", "release-build"} <= set(names)
    assert names["scan-landing"]["schedules"][0]["interval"] > 0
    from prefect.flows import load_flow_from_entrypoint

    for d in spec["deployments"]:
        path, _, fn = d["entrypoint"].partition(":")
        flow: Any = load_flow_from_entrypoint(f"{REPO / path}:{fn}")
        params = set(flow.parameters.properties)
        assert set(d.get("parameters", {})) <= params, (d["name"], params)


def test_find_new_clips_skips_seen_and_unsettled(tmp_path: Path) -> None:
    lake = Lake(tmp_path / "lake")
    inbox = tmp_path / "inbox"
    a = fakes.make_fake_clip(inbox, "old")
    b = fakes.make_fake_clip(inbox, "new")
    past = time.time() - 60
    for p in [*a.rglob("*"), *b.rglob("*")]:
        os.utime(p, (past, past))
    lake.write_json(lake.path("manifests", "old", "ingest.json"), {})
    assert find_new_clips(lake, inbox, settle_seconds=5) == [b]
    (b / "late.bin").write_bytes(b"still copying")
    assert find_new_clips(lake, inbox, settle_seconds=5) == []


@pytest.mark.slow
def test_schedule_fires_and_processes_new_clip(prefect_server: Any, tmp_path: Path) -> None:
    api = prefect_server.api_url
    pool = f"v2xlake-test-{uuid.uuid4().hex[:6]}"
    lake_dir, inbox = tmp_path / "lake", tmp_path / "inbox"
    inbox.mkdir()
    _prefect(["work-pool", "create", pool, "--type", "process"], api)
    params = {"lake": str(lake_dir), "inbox": str(inbox), "pipeline": fakes.FAKES,
              "settle_seconds": 0.5}
    _prefect(["--no-prompt", "deploy", "--prefect-file", "deploy/prefect.yaml",
              "--name", "scan-landing", "--pool", pool, "--interval", "5",
              "--params", json.dumps(params)], api)
    worker = start_worker(api, pool, home=prefect_server.home, cwd=tmp_path,
                          query_seconds=2)
    try:
        clip = fakes.make_fake_clip(tmp_path / "staging", "arrived_by_schedule")
        os.rename(clip, inbox / clip.name)  # atomic arrival
        seen: list[str] = []

        def in_catalog() -> bool:
            nonlocal seen
            assert worker.poll() is None, "worker died"
            if (lake_dir / "catalog.duckdb").exists():
                seen = query(Lake(lake_dir), "SELECT clip_id FROM clips").column(0).to_pylist()
            return "arrived_by_schedule" in seen

        log = (prefect_server.home / f"worker-{pool}.log")
        if not _wait_for(in_catalog):
            pytest.fail("the scheduled run never put the clip in the catalog:\n"
                        + (log.read_text()[-4000:] if log.exists() else ""))
        done: list[Any] = []

        def completed() -> bool:  # the run finishes after the catalog
            nonlocal done
            done = [r for r in asyncio.run(_deployment_runs()) if r.state.is_completed()]
            return bool(done)

        _wait_for(completed)
        assert done and all(r.auto_scheduled for r in done)
    finally:
        stop_process(worker)
        asyncio.run(_delete_deployment())  # the shared server must stop scheduling it


async def _deployment_runs() -> list[Any]:
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import DeploymentFilter, DeploymentFilterName

    async with get_client() as client:
        return list(await client.read_flow_runs(deployment_filter=DeploymentFilter(
            name=DeploymentFilterName(any_=["scan-landing"]))))


async def _delete_deployment() -> None:
    from prefect.client.orchestration import get_client

    async with get_client() as client:
        try:
            dep = await client.read_deployment_by_name("scan-landing/scan-landing")
        except Exception:
            return
        await client.delete_deployment(dep.id)
