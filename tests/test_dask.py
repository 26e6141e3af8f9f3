"""Distributed runs: clips processed on Dask workers against a real Prefect server."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import pytest
import test_flows_fakestages as fakes

from v2xlake.flows.runners import RunnerSpec, needs_api_server, parse_runner
from v2xlake.storage.lake import Lake


def test_parse_runner() -> None:
    assert parse_runner("local") == RunnerSpec("local")
    assert parse_runner("dask") == RunnerSpec("dask", None, 2)
    assert parse_runner("dask=3") == RunnerSpec("dask", None, 3)
    assert parse_runner("dask=tcp://10.0.0.5:8786") == RunnerSpec("dask", "tcp://10.0.0.5:8786")
    with pytest.raises(ValueError):
        parse_runner("ray")
    with pytest.raises(ValueError):
        parse_runner("local=foo")
    assert not needs_api_server("local")


@pytest.mark.slow
def test_two_clips_on_two_dask_workers(prefect_server: Any, tmp_path: Path) -> None:
    from distributed import Client, LocalCluster

    from v2xlake.flows.pipeline import process_clips

    lake_dir = tmp_path / "lake"
    clips = [fakes.make_fake_clip(tmp_path / "in", f"dask{i}") for i in range(2)]
    bad = fakes.make_fake_clip(tmp_path / "in", "dask_bad", corrupt=True)
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                      dashboard_address=None) as cluster, Client(cluster) as client:
        worker_pids = set(client.run(os.getpid).values())
        assert len(worker_pids) == 2
        results = process_clips([str(c) for c in [*clips, bad]], str(lake_dir),
                                pipeline=fakes.FAKES,
                                runner=f"dask={cluster.scheduler_address}")
    by_id = {r["clip_id"]: r for r in results}
    assert by_id["dask0"]["status"] == by_id["dask1"]["status"] == "ok"
    assert by_id["dask_bad"]["status"] == "quarantined"
    assert "no INS messages" in by_id["dask_bad"]["error"]
    pids = {int(next(o for o in by_id[c]["stages"] if o["stage"] == "qa")["report"]["metrics"]
                ["pid"]) for c in ("dask0", "dask1")}
    assert pids <= worker_pids and os.getpid() not in pids  # ran on the workers
    lake = Lake(lake_dir)
    from v2xlake.flows.bookkeeping import query

    got = query(lake, "SELECT clip_id FROM clips ORDER BY 1").column(0).to_pylist()
    assert got == ["dask0", "dask1"]

    # --runner dask: the flow starts (and stops) its own LocalCluster
    more = fakes.make_fake_clip(tmp_path / "in", "dask2")
    res2 = process_clips([str(more)], str(lake_dir), pipeline=fakes.FAKES,
                         runner="dask")
    assert res2[0]["status"] == "ok"
    qa_pid = int(next(o for o in res2[0]["stages"] if o["stage"] == "qa")["report"]["metrics"]
                 ["pid"])
    assert qa_pid != os.getpid()


@pytest.mark.slow
def test_one_clips_deskew_spread_over_two_workers(prefect_server: Any, tmp_path: Path) -> None:
    """Parallelism inside a clip: a chunked stage's chunks run on different workers and the
    output is the same, byte for byte, as one process doing it all."""
    import pyarrow.parquet as pq
    import yaml
    from distributed import Client, LocalCluster, get_task_stream

    from tests.test_deskew import Motion
    from tests.test_deskew_stage import CLIP, write_agent
    from v2xlake.flows.pipeline import process_clips

    clip_dir = tmp_path / "clip"
    clip_dir.mkdir()
    (clip_dir / "clip.yaml").write_text(yaml.safe_dump({"clip_id": CLIP}))
    params = {"deskew": {"frames_per_file": 1}}  # one chunk per frame: 6 chunks
    lakes = {}
    for name in ("one", "two"):
        lake = Lake(tmp_path / name)
        write_agent(lake, "red", Motion(), (100_000_000, 600_000_000))
        write_agent(lake, "black", Motion(yaw_rate=0.5), (100_000_000, 600_000_000))
        lakes[name] = lake
    local = process_clips([str(clip_dir)], lakes["one"].uri, ["deskew"], params)
    assert local[0]["status"] == "ok", local[0].get("error")
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                      dashboard_address=None) as cluster, Client(cluster) as client, \
            get_task_stream(client) as stream:
        dist = process_clips([str(clip_dir)], lakes["two"].uri, ["deskew"], params,
                             runner=f"dask={cluster.scheduler_address}")
    workers = {t["worker"] for t in stream.data}  # filled when the block exits
    assert dist[0]["status"] == "ok", dist[0].get("error")
    assert dist[0]["stages"][0]["report"]["metrics"]["n_chunks"] == 6
    assert len(workers) == 2  # both workers took chunks
    for table in ("lidar_points_deskewed", "deskew_frames"):
        a, b = (sorted(lk.list_files(lk.table_dir("clean", table, CLIP), ".parquet"))
                for lk in (lakes["one"], lakes["two"]))
        assert [p[len(lakes["one"].base):] for p in a] == [p[len(lakes["two"].base):] for p in b]
        for fa, fb in zip(a, b, strict=True):
            assert pq.read_table(fa).equals(pq.read_table(fb)), fa
