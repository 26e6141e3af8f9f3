"""An S3 lake on a real SeaweedFS server: clip processing, catalog over httpfs, releases."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import boto3
import pytest
import test_flows_fakestages as fakes

from v2xlake.flows.bookkeeping import query
from v2xlake.flows.release import build_release, verify_release
from v2xlake.storage.lake import Lake


def _client(s3: Any) -> Any:
    return boto3.client("s3", endpoint_url=s3.endpoint, region_name="us-east-1",
                        aws_access_key_id=s3.access_key, aws_secret_access_key=s3.secret_key)


@pytest.mark.slow
def test_s3_lake_flow_catalog_release(prefect_server: Any, s3_env: Any, tmp_path: Path) -> None:
    from v2xlake.flows.pipeline import process_clips

    uri = f"s3://{s3_env.bucket}/machinery"
    clips = [fakes.make_fake_clip(tmp_path / "in", f"s3clip{i}", weather=w)
             for i, w in enumerate(["clear", "rain", "clear"])]
    bad = fakes.make_fake_clip(tmp_path / "in", "s3bad", corrupt=True)
    results = process_clips([str(c) for c in [*clips, bad]], uri, pipeline=fakes.FAKES)
    assert [r["status"] for r in results] == ["ok", "ok", "ok", "quarantined"]
    lake = Lake(uri)
    assert not lake.is_local
    keys = [o["Key"] for o in _client(s3_env).list_objects_v2(
        Bucket=s3_env.bucket, Prefix="machinery/")["Contents"]]
    assert "machinery/clean/clips/clip_id=s3clip0/part.parquet" in keys
    assert "machinery/quarantine/s3bad/report.json" in keys
    assert not [k for k in keys if "clip_id=s3bad" in k]
    from v2xlake.flows.bookkeeping import user_query

    # the locked-down user connection reads an S3 lake too (and nothing else)
    got = user_query(lake, "SELECT clip_id, weather FROM clips ORDER BY 1").to_pylist()
    assert [r["clip_id"] for r in got] == ["s3clip0", "s3clip1", "s3clip2"]
    n = query(lake, "SELECT count(*) FROM annotations").column(0)[0].as_py()
    assert n == 36

    meta = build_release(uri, "s3rel", "weather = 'clear'")
    assert meta["clip_ids"] == ["s3clip0", "s3clip2"]
    assert verify_release(uri, "s3rel").ok
    key = "machinery/releases/s3rel/lake/clean/clips/clip_id=s3clip2/part.parquet"
    client = _client(s3_env)
    body = bytearray(client.get_object(Bucket=s3_env.bucket, Key=key)["Body"].read())
    body[-10] ^= 0xFF
    client.put_object(Bucket=s3_env.bucket, Key=key, Body=bytes(body))
    res = verify_release(uri, "s3rel")
    assert not res.ok and any("clip_id=s3clip2/part.parquet" in p for p in res.problems)


@pytest.mark.slow
def test_s3_real_clip_end_to_end(prefect_server: Any, s3_env: Any, tmp_path: Path) -> None:
    """A simulated clip through every real stage into an S3 lake, answered by SQL."""
    from v2xlake.flows.cli import sim_config
    from v2xlake.flows.pipeline import STAGE_NAMES, process_clip
    from v2xlake.tasks.simulate import simulate

    clip = simulate(tmp_path / "clip", sim_config("small", 1.0, "mcap", 11, "red,black", "1"))
    uri = f"s3://{s3_env.bucket}/real"
    summary = process_clip(str(clip), uri)
    assert summary["status"] == "ok", summary.get("error")
    assert [o["stage"] for o in summary["stages"]] == list(STAGE_NAMES)
    assert {o["status"] for o in summary["stages"]} == {"done"}
    lake = Lake(uri)
    pts = query(lake, "SELECT agent_id, count(*) AS n FROM lidar_points GROUP BY 1 ORDER BY 1")
    assert pts.column("agent_id").to_pylist() == ["black", "red"]
    assert min(pts.column("n").to_pylist()) > 10_000
    reg = query(lake, "SELECT count(*) AS n, avg(fitness) AS f FROM registrations").to_pylist()[0]
    assert reg["n"] > 0 and reg["f"] > 0
    man = query(lake, "SELECT stage, status FROM manifests ORDER BY stage").to_pylist()
    assert {m["stage"] for m in man} == set(STAGE_NAMES)
    assert {m["status"] for m in man} == {"done"}
    # unchanged clip: every stage is skipped by its manifest
    again = process_clip(str(clip), uri)
    assert {o["status"] for o in again["stages"]} == {"cached"}
