"""A cluster-shaped run (#18): every service its own process, as on separate machines.

``deploy/start_cluster.py`` starts a Dask scheduler and two Dask worker processes (their own
working folders; they know the Prefect API and the S3 endpoint only from their environment)
and a Prefect work pool with a concurrency limit and its process worker, against the
session's Prefect server, with the lake on the session's S3 server (``weed mini``). Then:
a clip of fake stages through ``process_clips(runner="dask=ADDRESS")``, and two small
simulated clips through every real stage with the command line ``v2xlake process A B
--lake s3://... --runner dask=ADDRESS``; the catalog over S3 answers for all three, and the
stages ran on the worker processes, not in the caller.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
import uuid
from pathlib import Path
from typing import Any

import pytest
import test_flows_fakestages as fakes

from tests.fixtures.processes import stop_group

REPO = Path(__file__).resolve().parents[1]


def _start_cluster(tmp_path: Path, api_url: str) -> tuple[subprocess.Popen[str], dict[str, Any]]:
    proc = subprocess.Popen(
        [sys.executable, str(REPO / "deploy" / "start_cluster.py"), "--workers", "2",
         "--clips-at-once", "2", "--api-url", api_url, "--home", str(tmp_path / "cluster"),
         "--pythonpath", str(REPO / "tests")],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    assert proc.stdout is not None
    deadline = time.monotonic() + 120
    lines = []
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line and proc.poll() is not None:
            break
        lines.append(line)
        if line.startswith("{"):
            return proc, json.loads(line)
    proc.kill()
    raise RuntimeError("cluster did not start:\n" + "".join(lines)[-3000:])


def _stop_cluster(proc: subprocess.Popen[str]) -> None:
    stop_group(proc)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


@pytest.mark.slow
def test_cluster_shaped_run(prefect_server: Any, s3_env: Any, tmp_path: Path) -> None:
    from distributed import Client

    from v2xlake.flows.bookkeeping import query
    from v2xlake.flows.cli import sim_config
    from v2xlake.flows.pipeline import process_clips
    from v2xlake.storage.lake import Lake
    from v2xlake.tasks.simulate import simulate

    uri = f"s3://{s3_env.bucket}/cluster-{uuid.uuid4().hex[:8]}"
    real = [simulate(tmp_path / f"real{i}", sim_config("small", 0.5, "mcap", 3 + i,
                                                       "red,black", "1", clip_id=f"real{i}"))
            for i in range(2)]
    t_start = time.monotonic()
    cluster, info = _start_cluster(tmp_path, prefect_server.api_url)
    timings = {"start": time.monotonic() - t_start}
    try:
        address = info["dask_scheduler"]
        assert info["pool"] == "v2xlake-cluster"
        pools = subprocess.run([sys.executable, "-m", "prefect", "work-pool", "inspect",
                                "v2xlake-cluster"], capture_output=True, text=True,
                               env=dict(os.environ, PREFECT_API_URL=prefect_server.api_url))
        assert "concurrency_limit=2" in pools.stdout.replace(" ", "").replace("'", "")
        with Client(address, timeout=30) as client:
            workers = set(client.run(os.getpid).values())
        assert len(workers) == 2 and os.getpid() not in workers

        # fake stages (module named by ``pipeline=``, imported by the workers themselves)
        t0 = time.monotonic()
        clips = [fakes.make_fake_clip(tmp_path / "in", "fake0")]
        results = process_clips([str(c) for c in clips], uri, pipeline=fakes.FAKES,
                                runner=f"dask={address}")
        assert [r["status"] for r in results] == ["ok"], results
        pids = {int(next(o for o in r["stages"] if o["stage"] == "qa")["report"]["metrics"]
                    ["pid"]) for r in results}
        assert pids <= workers
        timings["fake"] = time.monotonic() - t0

        # real stages, from the command line, two clips at once on the two workers
        t0 = time.monotonic()
        out = subprocess.run(
            [sys.executable, "-m", "v2xlake.flows.cli", "process", *map(str, real), "--lake",
             uri, "--runner", f"dask={address}"], capture_output=True, text=True, cwd=REPO,
            env=dict(os.environ, PREFECT_API_URL=prefect_server.api_url,
                     PYTHONPATH=str(REPO)), timeout=300)
        assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
        assert "2/2 clip(s) ok" in out.stdout
        timings["real"] = time.monotonic() - t0
        logs = "".join(p.read_text(errors="replace")
                       for p in Path(info["home"]).glob("dask-worker-*.log"))
        for clip in ("real0", "real1"):  # task runs named <clip>:<stage> ran on the workers
            for stage in ("ingest", "anonymize", "deskew", "register", "align"):
                assert f"{clip}:{stage}" in logs, (clip, stage)
    finally:
        _stop_cluster(cluster)
    assert cluster.returncode == 0
    deadline = time.monotonic() + 20  # every worker process went with the cluster
    while any(_alive(pid) for pid in workers) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not any(_alive(pid) for pid in workers)

    lake = Lake(uri)
    got = query(lake, "SELECT clip_id, status FROM clips ORDER BY clip_id").to_pylist()
    assert [r["clip_id"] for r in got] == ["fake0", "real0", "real1"]
    pts = query(lake, "SELECT clip_id, count(*) AS n FROM lidar_points_deskewed "
                      "GROUP BY 1 ORDER BY 1").to_pylist()
    assert [r["clip_id"] for r in pts] == ["real0", "real1"] and min(r["n"] for r in pts) > 0
    stages = query(lake, "SELECT clip_id, count(*) AS n FROM manifests WHERE status = 'done' "
                         "GROUP BY 1 ORDER BY 1").to_pylist()
    assert {r["clip_id"]: r["n"] for r in stages}["real0"] == 7
    print("cluster-shaped run, seconds:", {k: round(v, 1) for k, v in timings.items()})
