"""Manifests: unchanged clips do no work; a changed stage re-runs itself and what follows."""

from __future__ import annotations

import json
from pathlib import Path

import pyarrow as pa
import pytest
from pydantic import BaseModel

from tests.fixtures.minibag import MiniClip, write_clip
from v2xlake.schemas.stage import OutputFile, StageReport
from v2xlake.storage import manifest as mf
from v2xlake.storage.catalog import Catalog
from v2xlake.storage.lake import Lake
from v2xlake.tasks.ingest import IngestConfig, clip_inputs, run_ingest

CHAIN = ("ingest", "qa", "deskew", "register")
UPSTREAM = {"ingest": (), "qa": ("ingest",), "deskew": ("qa",), "register": ("deskew",)}


class FakeConfig(BaseModel):
    scale: float = 1.0


def fake_stage(lake: Lake, clip_id: str, stage: str, cfg: FakeConfig, src: Path) -> StageReport:
    """A stage whose output depends on its params and on its upstream's output."""
    ups = UPSTREAM[stage]
    base = (lake.read_table("raw", ups[0], clip_id=clip_id).column("v").to_pylist()
            if ups else [float(x) for x in src.read_text().split()])
    t = pa.table({"v": [v * cfg.scale + 1 for v in base]})
    path, n = lake.write_table("raw", stage, t, clip_id=clip_id)
    return StageReport(stage=stage, clip_id=clip_id,
                       outputs=[OutputFile(path=path[len(lake.base) + 1:], rows=n)])


class Flow:
    """What the flows owner does per stage: key -> is_current? -> run -> record."""

    def __init__(self, lake: Lake, src: Path, code: Path) -> None:
        self.lake, self.src, self.code = lake, src, code
        self.ran: list[str] = []

    def run(self, configs: dict[str, FakeConfig]) -> list[str]:
        self.ran = []
        for stage in CHAIN:
            key = mf.stage_key(self.lake, "c1", stage, configs[stage], UPSTREAM[stage],
                               input_files=[self.src] if stage == "ingest" else None,
                               code_paths=[self.code / f"{stage}.py"])
            if mf.is_current(self.lake, "c1", stage, key):
                continue
            rep = fake_stage(self.lake, "c1", stage, configs[stage], self.src)
            mf.record(self.lake, rep, key)
            self.ran.append(stage)
        return self.ran


@pytest.fixture
def flow(tmp_path: Path) -> Flow:
    src = tmp_path / "bag.txt"
    src.write_text("1 2 3")
    code = tmp_path / "code"
    code.mkdir()
    for s in CHAIN:
        (code / f"{s}.py").write_text(f"# {s} v1\n")
    return Flow(Lake(tmp_path / "lake"), src, code)


def cfgs(**over: float) -> dict[str, FakeConfig]:
    return {s: FakeConfig(scale=over.get(s, 1.0)) for s in CHAIN}


def test_unchanged_clip_does_no_work(flow: Flow) -> None:
    assert flow.run(cfgs()) == list(CHAIN)
    assert flow.run(cfgs()) == []
    m = mf.read(flow.lake, "c1", "register")
    assert m is not None and m.status == "done" and m.outputs[0].rows == 3
    assert m.outputs[0].checksum and m.outputs[0].checksum.startswith("xxh3_128:")


def test_changed_params_rerun_that_stage_and_later_only(flow: Flow) -> None:
    flow.run(cfgs())
    assert flow.run(cfgs(deskew=2.0)) == ["deskew", "register"]
    assert flow.run(cfgs(deskew=2.0)) == []
    # params that do not change the output bytes stop the cascade (content-addressed inputs)
    assert flow.run(cfgs(deskew=2.0, qa=1.0)) == []


def test_changed_input_or_code_or_missing_output(flow: Flow) -> None:
    flow.run(cfgs())
    flow.src.write_text("1 2 40")  # new size: the (path, size, mtime) hash cache must miss
    assert flow.run(cfgs()) == list(CHAIN)
    (flow.code / "qa.py").write_text("# qa v2\n")
    assert flow.run(cfgs()) == ["qa"]  # same output bytes: deskew's inputs are unchanged
    flow.lake.delete_partition("raw", "deskew", "c1")
    assert flow.run(cfgs()) == ["deskew"]


def test_failed_stage_is_not_current_and_shows_in_catalog(flow: Flow) -> None:
    flow.run(cfgs())
    key = mf.stage_key(flow.lake, "c1", "qa", cfgs()["qa"], ("ingest",),
                       code_paths=[flow.code / "qa.py"])
    mf.record(flow.lake, StageReport(stage="qa", clip_id="c1"), key, status="failed",
              error="boom")
    assert not mf.is_current(flow.lake, "c1", "qa", key)
    # a failed upstream makes every downstream key unique (never current)
    k2 = mf.stage_key(flow.lake, "c1", "deskew", cfgs()["deskew"], ("qa",))
    assert not mf.is_current(flow.lake, "c1", "deskew", k2)
    assert [m.stage for m in mf.load(flow.lake, "c1")] == sorted(CHAIN)
    rows = Catalog(flow.lake).query(
        "SELECT stage, status, error, outputs FROM manifests ORDER BY stage").to_pylist()
    assert [(r["stage"], r["status"]) for r in rows] == [
        ("deskew", "done"), ("ingest", "done"), ("qa", "failed"), ("register", "done")]
    assert rows[2]["error"] == "boom"
    assert json.loads(rows[0]["outputs"])[0]["rows"] == 3
    with pytest.raises(ValueError):
        mf.record(flow.lake, StageReport(stage="qa", clip_id="c1"), key, status="weird")


def test_real_ingest_manifest(tmp_path: Path) -> None:
    clip = write_clip(tmp_path / "clip", MiniClip(seconds=0.2, points=100, cameras=()))
    lake = Lake(tmp_path / "lake")
    cid, files = clip_inputs(clip)
    key = mf.stage_key(lake, cid, "ingest", IngestConfig(), input_files=files)
    assert not mf.is_current(lake, cid, "ingest", key)
    m = mf.record(lake, run_ingest(lake, clip), key)
    assert {o.path.split("/")[1] for o in m.outputs} >= {"lidar_points", "clips", "ins"}
    assert all(o.checksum and o.rows is not None for o in m.outputs)
    assert "file:clip.yaml" in m.inputs and "file:msgs/v2xlake_msgs/msg/InsPva.msg" in m.inputs
    assert sum(k.startswith(("file:red/", "file:black/")) and k.endswith(".db3")
               for k in m.inputs) == 2
    assert mf.is_current(lake, cid, "ingest",
                         mf.stage_key(lake, cid, "ingest", IngestConfig(), input_files=files))
    assert not mf.is_current(lake, cid, "ingest", mf.stage_key(
        lake, cid, "ingest", IngestConfig(png_compression=5), input_files=files))
    assert mf.code_version("ingest").startswith(mf.package_version() + "+")


# ------------------------------------------------------------------ the no-op check's cost
def test_bag_checksums_are_remembered_across_processes(tmp_path: Path,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """A scheduled scan re-checks every clip: bags whose stat is unchanged are not read again
    (the cache file stands for an earlier process), anything else is."""
    import os

    from v2xlake.storage import checksum, statcache

    monkeypatch.setenv(statcache.ENV, str(tmp_path / "sums.sqlite"))
    bag = tmp_path / "bag.db3"
    bag.write_bytes(b"a" * 1000)
    reads: list[str] = []
    real_of_file = checksum.of_file

    def counting(path: str | Path) -> str:
        reads.append(str(path))
        return real_of_file(path)

    monkeypatch.setattr(checksum, "of_file", counting)
    first = statcache.file_checksum(bag)
    assert first == real_of_file(bag) and len(reads) == 1
    statcache._MEMO.clear()  # a new process: only the cache file remembers
    assert statcache.file_checksum(bag) == first and len(reads) == 1
    # same size, new content: the mtime changed
    st = bag.stat()
    bag.write_bytes(b"b" * 1000)
    os.utime(bag, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000))
    statcache._MEMO.clear()
    second = statcache.file_checksum(bag)
    assert second != first and len(reads) == 2
    # replaced by another file with the same size and mtime: another inode
    other = tmp_path / "other.db3"
    other.write_bytes(b"c" * 1000)
    os.utime(other, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000))
    other.replace(bag)
    statcache._MEMO.clear()
    assert statcache.file_checksum(bag) == real_of_file(bag) != second and len(reads) == 3
    # a damaged cache file is ignored, never an error; "off" hashes every time
    statcache._DB.clear()
    (tmp_path / "sums.sqlite").write_bytes(b"not a database" * 100)
    for p in tmp_path.glob("sums.sqlite-*"):
        p.unlink()
    statcache._MEMO.clear()
    assert statcache.file_checksum(bag) == real_of_file(bag) and len(reads) == 4
    monkeypatch.setenv(statcache.ENV, "off")
    statcache._MEMO.clear()
    statcache.file_checksum(bag)
    statcache._MEMO.clear()
    statcache.file_checksum(bag)
    assert len(reads) == 6
    statcache._DB.clear()


def test_code_version_follows_edits_while_remembered(tmp_path: Path) -> None:
    """The code version is remembered per process, yet an edit, a new module in a package or
    a removed one still changes it (their stat is checked on every call)."""
    import os

    pkg = tmp_path / "plugin"
    pkg.mkdir()
    (pkg / "core.py").write_text("X = 1\n")
    os.utime(pkg, ns=(0, 0))  # Linux stamps in ticks of a few ms: as if made long ago
    v1 = mf.code_version("plugin", [pkg])
    assert mf.code_version("plugin", [pkg]) == v1
    st = (pkg / "core.py").stat()
    (pkg / "core.py").write_text("X = 2\n")  # same size
    os.utime(pkg / "core.py", ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000))
    v2 = mf.code_version("plugin", [pkg])
    assert v2 != v1
    (pkg / "extra.py").write_text("Y = 1\n")
    v3 = mf.code_version("plugin", [pkg])
    assert v3 not in (v1, v2)
    (pkg / "extra.py").unlink()
    assert mf.code_version("plugin", [pkg]) == v2
