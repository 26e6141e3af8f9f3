"""#16: a clip folder is untrusted input. Files it names must stay inside it; malformed
contracts are ClipErrors (quarantined, never retried), not bare exceptions."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import yaml

from tests.fixtures.minibag import MiniClip, write_clip
from tests.fixtures.real import REAL_DATA_INGEST, SHARED_REAL, requires_real_data
from v2xlake.flows.params import ParamsError, PipelineParams
from v2xlake.flows.pipeline import STAGES
from v2xlake.schemas.errors import ClipError
from v2xlake.storage.lake import Lake
from v2xlake.tasks.ingest import run_ingest


def _clip(tmp: Path, name: str = "c1") -> Path:
    return write_clip(tmp / name, MiniClip(seconds=0.2, points=100, cameras=(), clip_id=name))


def _set_bag(clip: Path, bag: str) -> None:
    cfg = yaml.safe_load((clip / "clip.yaml").read_text())
    cfg["agents"][0]["bag"] = bag
    (clip / "clip.yaml").write_text(yaml.safe_dump(cfg))


def _nothing_of(lake: Lake, cid: str) -> bool:
    return not [f for f in lake.list_files(lake.path()) if cid in f]


@pytest.mark.parametrize("target", ["/etc/hostname", "{secret}", "../outside_bag"])
def test_bag_paths_outside_the_clip_are_refused(tmp_path: Path, target: str) -> None:
    secret = tmp_path / "secret.txt"
    secret.write_text("password")
    (tmp_path / "outside_bag").mkdir()
    clip = _clip(tmp_path)
    _set_bag(clip, target.format(secret=secret))
    lake = Lake(tmp_path / "lake")
    with pytest.raises(ClipError, match="outside the clip folder") as e:
        run_ingest(lake, clip)
    assert e.value.agent_id == "red"
    assert _nothing_of(lake, "c1")  # nothing linked or copied into landing/


def test_a_symlink_inside_the_clip_pointing_outside_is_refused(tmp_path: Path) -> None:
    clip = _clip(tmp_path)
    cfg = yaml.safe_load((clip / "clip.yaml").read_text())
    real_bag = clip / cfg["agents"][0]["bag"]
    moved = tmp_path / "elsewhere"
    os.rename(real_bag, moved)
    os.symlink(moved, real_bag)  # the path reads as inside, resolves outside
    lake = Lake(tmp_path / "lake")
    with pytest.raises(ClipError, match="outside the clip folder"):
        run_ingest(lake, clip)
    assert _nothing_of(lake, "c1")


@requires_real_data("bags/ouster_os1_128_3frames_ros2")
def test_an_operator_allowed_root_is_read_in_place(tmp_path: Path) -> None:
    assert SHARED_REAL.is_dir()
    fixture = Path(__file__).resolve().parents[1] / "fixtures" / "ouster"
    lake = Lake(tmp_path / "lake")
    with pytest.raises(ClipError, match="outside the clip folder"):
        run_ingest(lake, fixture)
    assert run_ingest(lake, fixture, REAL_DATA_INGEST).clip_id == "ouster-os1-128-real"


def test_a_clip_cannot_widen_what_it_may_read() -> None:
    ingest = next(s for s in STAGES if s.name == "ingest")
    with pytest.raises(ParamsError, match="only be set by the operator"):
        PipelineParams().for_stage(ingest, {"ingest": {"allowed_bag_roots": ["/"]}})
    run = PipelineParams.model_validate({"ingest": {"allowed_bag_roots": ["/data"]}})
    assert run.for_stage(ingest, {}).allowed_bag_roots == ("/data",)  # type: ignore[attr-defined]


@pytest.mark.parametrize("text,match", [
    ("clip_id: [unclosed\n", "not readable YAML"),
    ("clip_id: x\nlocation: y\n\tbad: tab\n", "not readable YAML"),
])
def test_malformed_clip_yaml_is_a_clip_error(tmp_path: Path, text: str, match: str) -> None:
    clip = _clip(tmp_path)
    (clip / "clip.yaml").write_text(text)
    with pytest.raises(ClipError, match=match):
        run_ingest(Lake(tmp_path / "lake"), clip)


def test_missing_bag_and_bag_that_is_a_plain_file(tmp_path: Path) -> None:
    clip = _clip(tmp_path)
    _set_bag(clip, "no_such_bag")
    lake = Lake(tmp_path / "lake")
    with pytest.raises(ClipError, match="does not exist"):
        run_ingest(lake, clip)
    (clip / "plain.txt").write_text("not a bag")
    _set_bag(clip, "plain.txt")
    with pytest.raises(ClipError, match="cannot open bag"):
        run_ingest(lake, clip)
    assert not lake.list_files(lake.path("raw"))


# ------------------------------------------------------------------ clip identity
def _raw_files(lake: Lake, cid: str) -> dict[str, bytes]:
    return {f: lake.read_bytes(f) for f in lake.list_files(lake.path("raw"))
            if f"clip_id={cid}" in f or f"/blobs/{cid}/" in f}


def test_another_delivery_under_an_existing_id_is_refused(tmp_path: Path) -> None:
    from v2xlake.schemas.errors import DeliveryConflict
    from v2xlake.tasks.ingest import IngestConfig

    lake = Lake(tmp_path / "lake")
    first = write_clip(tmp_path / "d1", MiniClip(seconds=0.2, points=100, cameras=(),
                                                 clip_id="same"))
    run_ingest(lake, first)
    before = _raw_files(lake, "same")
    other = write_clip(tmp_path / "d2", MiniClip(seconds=0.3, points=120, cameras=(),
                                                 clip_id="same"))
    with pytest.raises(DeliveryConflict, match="already in the lake with other bags"):
        run_ingest(lake, other)
    assert _raw_files(lake, "same") == before  # untouched
    run_ingest(lake, first)  # the same delivery again is fine (a re-run)
    rep = run_ingest(lake, other, IngestConfig(replace_existing=True))  # explicit
    assert rep.clip_id == "same" and _raw_files(lake, "same") != before


@pytest.mark.slow
def test_the_flow_never_lets_a_bad_delivery_touch_an_existing_clip(
        prefect_server: object, tmp_path: Path) -> None:
    from v2xlake.flows.pipeline import process_clip
    from v2xlake.storage.quarantine import is_quarantined

    lake = Lake(tmp_path / "lake")
    good = write_clip(tmp_path / "in" / "c1", MiniClip(seconds=0.2, points=100, cameras=(),
                                                       clip_id="c1"))
    assert process_clip(str(good), lake.uri, ["ingest"])["status"] == "ok"
    before = _raw_files(lake, "c1")
    # a different recording claiming the id: refused, nothing written
    other = write_clip(tmp_path / "in2" / "x", MiniClip(seconds=0.3, points=150, cameras=(),
                                                        clip_id="c1"))
    state = process_clip(str(other), lake.uri, ["ingest"], return_state=True)
    assert state.is_failed() and "refused" in (state.message or "")
    # a broken clip.yaml in a folder named like the clip
    broken = tmp_path / "in3" / "c1"
    broken.mkdir(parents=True)
    (broken / "clip.yaml").write_text("clip_id: [oops\n")
    state = process_clip(str(broken), lake.uri, ["ingest"], return_state=True)
    assert state.is_failed()
    assert is_quarantined(lake, "_unreadable-c1")
    # a hostile clip.yaml that claims the id and names a file outside its folder
    hostile = write_clip(tmp_path / "in4" / "h", MiniClip(seconds=0.2, points=100, cameras=(),
                                                          clip_id="c1"))
    _set_bag(hostile, "/etc/hostname")
    state = process_clip(str(hostile), lake.uri, ["ingest"], return_state=True)
    assert state.is_failed() and "outside the clip folder" in (state.message or "")
    assert _raw_files(lake, "c1") == before  # the existing clip survived all three
    assert not [f for f in lake.list_files(lake.path("landing")) if "hostname" in f]
