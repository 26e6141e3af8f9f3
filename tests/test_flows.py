"""Flow machinery: pipeline, per-clip flow states, quarantine, caching, retries, artifacts.

Runs real Prefect flows against the session's real Prefect server, with the stand-in
stages of ``test_flows_fakestages`` (the real stages get their own end-to-end tests).
"""

from __future__ import annotations

import asyncio
import os
from pathlib import Path
from typing import Any

import pytest
import test_flows_fakestages as fakes

from v2xlake.flows import bookkeeping
from v2xlake.flows.pipeline import STAGE_NAMES, STAGES, resolve_pipeline, select
from v2xlake.storage.lake import Lake


def test_pipeline_order_and_selection() -> None:
    assert STAGE_NAMES == ("ingest", "qa", "anonymize", "deskew", "register", "annotate",
                           "align")
    assert STAGES[0].input == "clip_dir"
    fake = resolve_pipeline(fakes.FAKES)
    assert [s.name for s in select(fake, ["annotate", "ingest"])] == ["ingest", "annotate"]
    with pytest.raises(ValueError, match="unknown stage"):
        select(fake, ["ingest", "deskw"])
    with pytest.raises(ImportError):  # a pipeline that cannot be imported is never skipped
        resolve_pipeline("no_such_module:STAGES")


def _flow_runs(api_flow_name: str) -> list[Any]:
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import FlowFilter, FlowFilterName

    async def go() -> list[Any]:
        async with get_client() as client:
            return list(await client.read_flow_runs(
                flow_filter=FlowFilter(name=FlowFilterName(any_=[api_flow_name]))))

    return asyncio.run(go())


@pytest.mark.slow
def test_process_clips_quarantine_cache_retry(prefect_server: Any, tmp_path: Path) -> None:
    from v2xlake.flows.pipeline import process_clips

    lake_dir = tmp_path / "lake"
    good = fakes.make_fake_clip(tmp_path / "in", "good_clip")
    bad = fakes.make_fake_clip(tmp_path / "in", "bad_clip", corrupt=True)
    pipeline = "test_flows_fakestages:FLAKY_PIPELINE"
    results = process_clips([str(good), str(bad)], str(lake_dir), pipeline=pipeline)
    by_id = {r["clip_id"]: r for r in results}
    lake = Lake(lake_dir)

    ok = by_id["good_clip"]
    assert ok["status"] == "ok"
    statuses = {o["stage"]: o["status"] for o in ok["stages"]}
    assert statuses == {"ingest": "done", "qa": "done", "annotate": "done", "flaky": "done"}
    assert [o["stage"] for o in ok["stages"]] == ["ingest", "qa", "annotate", "flaky"]
    assert fakes.call_count(lake, "flaky", "good_clip") == 2  # failed once, retried

    q = by_id["bad_clip"]
    assert q["status"] == "quarantined"
    assert "no INS messages" in q["error"] and "/red/ins" in q["error"]
    report = lake.read_json(q["quarantine_report"])
    assert report["clip_id"] == "bad_clip" and report["stage"] == "qa"
    assert report["error"]["agent_id"] == "red" and report["error"]["topic"] == "/red/ins"
    # never half-published: nothing of the bad clip in raw/clean, later stages never ran
    assert not lake.exists(lake.table_dir("clean", "clips", "bad_clip"))
    assert not lake.exists(lake.table_dir("raw", "qa_checks", "bad_clip"))
    assert fakes.call_count(lake, "annotate", "bad_clip") == 0
    assert fakes.call_count(lake, "qa", "bad_clip") == 1  # bad input is not retried
    ids = bookkeeping.query(lake, "SELECT clip_id FROM clips ORDER BY 1").column(0).to_pylist()
    assert ids == ["good_clip"]

    # per-clip flow runs on the server: one Completed, one Failed with the reason
    runs = {r.name: r for r in _flow_runs("process-clip")
            if r.name in ("clip-good_clip", "clip-bad_clip")}
    assert runs["clip-good_clip"].state.is_completed()
    assert runs["clip-bad_clip"].state.is_failed()
    assert "quarantined at stage qa" in (runs["clip-bad_clip"].state.message or "")

    # unchanged inputs and code: nothing runs again
    again = process_clips([str(good)], str(lake_dir), pipeline=pipeline)[0]
    assert {o["status"] for o in again["stages"]} == {"cached"}
    assert fakes.call_count(lake, "ingest", "good_clip") == 1
    # a changed input file reruns ingest; its output changed, so the stages after it rerun
    (good / "red.bin").write_bytes(b"\0" * 16)
    third = process_clips([str(good)], str(lake_dir), pipeline=pipeline)[0]
    assert {o["stage"]: o["status"] for o in third["stages"]}["annotate"] == "done"
    assert fakes.call_count(lake, "ingest", "good_clip") == 2
    assert fakes.call_count(lake, "annotate", "good_clip") == 2


@pytest.mark.slow
def test_artifacts_published(prefect_server: Any, tmp_path: Path) -> None:
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import ArtifactFilter, ArtifactFilterKey

    from v2xlake.flows.pipeline import process_clip

    clip = fakes.make_fake_clip(tmp_path / "in", "Art_Clip")
    summary = process_clip(str(clip), str(tmp_path / "lake"), pipeline=fakes.FAKES)
    assert summary["status"] == "ok"

    async def keys() -> dict[str, Any]:
        async with get_client() as client:
            arts = await client.read_artifacts(artifact_filter=ArtifactFilter(
                key=ArtifactFilterKey(like_="clip-art-clip")))
            return {str(a.key): a for a in arts}

    arts = asyncio.run(keys())
    assert {"clip-art-clip-stages", "clip-art-clip-metrics", "clip-art-clip-qa",
            "clip-art-clip-summary", "clip-art-clip-progress"} <= set(arts)
    assert "annotate" in str(arts["clip-art-clip-stages"].data)
    assert "000000.png" in str(arts["clip-art-clip-summary"].data)


def test_quarantine_removes_partitions(tmp_path: Path) -> None:
    from v2xlake.schemas.errors import ClipError

    lake = Lake(tmp_path / "lake")
    clip = fakes.make_fake_clip(tmp_path / "in", "q1")
    other = fakes.make_fake_clip(tmp_path / "in", "keep")
    for c in (clip, other):
        rep = fakes.fake_ingest(lake, c)
        fakes.fake_annotate(lake, rep.clip_id)
    err = ClipError("q1", "camera_info missing", agent_id="black", topic="/black/cam",
                    stage="ingest")
    path = bookkeeping.quarantine(lake, "q1", err, stage="ingest")
    assert "camera_info missing" in lake.read_json(path)["reason"]
    assert not lake.exists(lake.table_dir("clean", "annotations", "q1"))
    assert not lake.exists(lake.path("clean", "blobs", "q1"))
    assert lake.exists(lake.table_dir("clean", "annotations", "keep"))
    assert "q1" in bookkeeping.processed_clip_ids(lake)
    assert os.path.exists(lake.path("landing", "q1", "clip.yaml"))  # delivery kept


@pytest.mark.slow
def test_release_build_flow(prefect_server: Any, tmp_path: Path) -> None:
    """The release-build deployment's flow: a Prefect run that builds and seals a release."""
    from v2xlake.flows.release import release_build, verify_release

    lake = Lake(tmp_path / "lake")
    for i in range(3):
        rep = fakes.fake_ingest(lake, fakes.make_fake_clip(tmp_path / "in", f"rb{i}"))
        fakes.fake_annotate(lake, rep.clip_id)
    state = release_build(lake.uri, "flow-rel", "clip_id <> 'rb1'", return_state=True)
    assert state.is_completed()
    out = state.result()
    assert out["clip_ids"] == ["rb0", "rb2"] and out["formats"] == ["lake"]
    assert verify_release(lake.uri, "flow-rel").ok
    again = release_build(lake.uri, "flow-rel", "true", return_state=True)
    assert again.is_failed() and "immutable" in (again.message or "")
