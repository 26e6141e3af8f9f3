"""The stage contract (#15): typed stages imported by the flow, one writer per table,
freshness from the checksums of what a stage read, parameters as data.

Each of the defects the issue reproduced is a test here: a broken stage import skipped with
a warning (then a good clip quarantined at the next stage), a re-run of anonymize silently
dropping deskew's columns from ``lidar_frames``, a plausibility finding on an annotation
quarantining a clip, and no way to set a parameter.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import test_flows_fakestages as fakes
import yaml
from pydantic import BaseModel

from tests.test_deskew import Motion
from tests.test_deskew_stage import CLIP, FRAMES, write_agent
from v2xlake.flows import bookkeeping
from v2xlake.flows.params import (
    ParamsError,
    PipelineParams,
    clip_params,
    load_params,
)
from v2xlake.flows.pipeline import STAGES
from v2xlake.schemas import registry
from v2xlake.schemas.stage import Stage
from v2xlake.schemas.tables import LAKE_TABLES, TABLE_OWNERS
from v2xlake.storage import manifest
from v2xlake.storage.catalog import Catalog
from v2xlake.storage.lake import Lake
from v2xlake.tasks.deskew.stage import DESKEW
from v2xlake.tasks.export.exporters import EXPORTERS

REPO = Path(__file__).resolve().parents[1]


# ------------------------------------------------------------------ typed stages
def test_every_stage_is_a_typed_stage_object_in_its_own_package() -> None:
    names = [s.name for s in STAGES]
    assert names == ["ingest", "qa", "anonymize", "deskew", "register", "annotate", "align"]
    for s in STAGES:
        assert isinstance(s, Stage) and issubclass(s.config_model, BaseModel)
        module = sys.modules[s.run.__module__].__name__
        assert module.startswith(f"v2xlake.tasks.{s.name}."), (s.name, module)
        assert (REPO / "v2xlake" / "tasks" / s.name / "stage.py").is_file()
    # the old split modules are gone: one package per stage
    for old in ("deskew.py", "deskew_stage.py", "register.py", "align.py", "qa.py",
                "annotate.py", "registration", "alignment"):
        assert not (REPO / "v2xlake" / "tasks" / old).exists(), old
    assert not (REPO / "v2xlake" / "flows" / "stages.py").exists()  # no module:function registry


def test_broken_stage_import_fails_before_any_clip_is_touched(tmp_path: Path) -> None:
    """A stage module that fails to import must stop the command, not be skipped (then the
    next stage would find its input missing and quarantine a good clip)."""
    clip = fakes.make_fake_clip(tmp_path / "in", "good_clip")
    lake = tmp_path / "lake"
    script = f"""
import sys
class Broken:
    def find_spec(self, name, path=None, target=None):
        if name == "v2xlake.tasks.deskew.stage":
            raise ImportError("simulated: a dependency of deskew is missing")
        return None
sys.meta_path.insert(0, Broken())
from v2xlake.flows.cli import main
sys.exit(main(["process", {str(clip)!r}, "--lake", {str(lake)!r}]))
"""
    env = {**os.environ, "PYTHONPATH": f"{REPO}{os.pathsep}{REPO / 'tests'}"}
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         env=env, timeout=300)
    assert res.returncode == 2, res.stdout + res.stderr
    assert "deskew" in res.stdout + res.stderr
    # nothing of the clip was touched: no landing copy, no raw zone, no quarantine
    for zone in ("landing", "raw", "clean", "quarantine", "manifests"):
        assert not (lake / zone).exists(), zone


# ------------------------------------------------------------------ one writer per table
def test_each_table_has_exactly_one_owning_stage() -> None:
    owned: dict[tuple[str, str], str] = {}
    for s in STAGES:
        for t in s.owns:
            key = (t.zone, t.name)
            assert key not in owned, f"{key} owned by {owned[key]} and {s.name}"
            owned[key] = s.name
            assert TABLE_OWNERS.get(key) == s.name, (key, TABLE_OWNERS.get(key), s.name)
        # the Stage object and its package's declaration (what the registry reads without
        # importing the stage) name the same tables
        assert s.owns == registry.declaration(s.name).owns, s.name
    pipeline_tables = {k for k, v in TABLE_OWNERS.items() if v != "export"}
    assert set(owned) == pipeline_tables
    for s in STAGES:  # a stage reads only tables some stage owns
        for t in s.reads:
            assert (t.zone, t.name) in TABLE_OWNERS, (s.name, t)
    assert set(LAKE_TABLES) - {"manifests"} <= {name for _, name in TABLE_OWNERS}


def test_a_stage_cannot_write_another_stages_table(tmp_path: Path) -> None:
    lake = Lake(tmp_path / "lake")
    write_agent(lake, "red", Motion(), (100_000_000, 600_000_000))
    frames = lake.read_table("clean", "lidar_frames", clip_id=CLIP, agent_id="red")
    deskew = lake.for_stage("deskew", [(t.zone, t.name) for t in DESKEW.owns])
    with pytest.raises(PermissionError, match="belongs to stage 'anonymize'"):
        deskew.write_table("clean", "lidar_frames", frames, clip_id=CLIP, agent_id="red")
    with pytest.raises(PermissionError, match="belongs to stage 'anonymize'"):
        deskew.delete_partition("clean", "lidar_points", CLIP)
    with pytest.raises(PermissionError, match="belongs to stage 'anonymize'"):
        lake.for_stage("deskew", [(t.zone, t.name) for t in DESKEW.owns],
                       atomic_clip=CLIP).write_table("clean", "lidar_frames", frames,
                                                     clip_id=CLIP)


def _deskew_key(lake: Lake) -> manifest.StageKey:
    return bookkeeping.stage_key(lake, CLIP, DESKEW, DESKEW.config(), None)


def _run_deskew(lake: Lake) -> None:
    writer = lake.for_stage("deskew", [(t.zone, t.name) for t in DESKEW.owns])
    report = DESKEW.run(writer, CLIP, DESKEW.config())
    bookkeeping.record(lake, report, _deskew_key(lake))


def test_upstream_rewrite_keeps_deskew_columns_and_reruns_deskew(tmp_path: Path) -> None:
    """Defect 2: anonymize re-ran (a comment-only change) and rewrote ``lidar_frames``;
    deskew was skipped as unchanged and its per-frame columns were gone. Now deskew writes
    its own table, and its freshness is decided by the checksums of the files it read."""
    lake = Lake(tmp_path / "lake")
    write_agent(lake, "red", Motion(), (100_000_000, 600_000_000))
    _run_deskew(lake)
    assert bookkeeping.cached_report(lake, CLIP, "deskew", _deskew_key(lake)) is not None

    # anonymize rewrites lidar_frames byte for byte: deskew stays current, nothing lost
    path = lake.list_files(lake.table_dir("clean", "lidar_frames", CLIP), ".parquet")[0]
    data = lake.read_bytes(path)
    lake.write_bytes(path, data)
    assert bookkeeping.cached_report(lake, CLIP, "deskew", _deskew_key(lake)) is not None
    # ... and with different bytes (another row order): deskew must run again
    frames = lake.read_table("clean", "lidar_frames", clip_id=CLIP, agent_id="red")
    lake.write_table("clean", "lidar_frames", frames.take([2, 1, 0]), clip_id=CLIP,
                     agent_id="red")
    assert bookkeeping.cached_report(lake, CLIP, "deskew", _deskew_key(lake)) is None
    # either way the catalog's lidar_frames shows deskew's figures for every frame
    with Catalog(lake) as cat:
        rows = cat.query("SELECT frame_idx, deskew_ref_ns, n_uncovered FROM lidar_frames "
                         "ORDER BY frame_idx").to_pylist()
    assert [r["deskew_ref_ns"] for r in rows] == list(FRAMES)
    assert [r["n_uncovered"] for r in rows] == [0, 0, 0]


# ------------------------------------------------------------------ parameters as data
def test_every_parameter_section_is_strict() -> None:
    p = PipelineParams()
    for s in STAGES:
        assert type(getattr(p, s.name)) is s.config_model
        assert s.config_model.model_config.get("extra") == "forbid", s.name
    for name, exporter in EXPORTERS.items():
        assert type(p.export.section(name)) is exporter.config_model
        assert exporter.config_model.model_config.get("extra") == "forbid", name


def test_params_file_clip_block_and_precedence(tmp_path: Path) -> None:
    f = tmp_path / "p.yaml"
    f.write_text(yaml.safe_dump({"qa": {"stream": {"max_dropped_fraction": 0.2},
                                        "tolerance_ms": {"lidar": 2.0}},
                                 "export": {"nuscenes": {}}}))
    run = load_params(f)
    clip = fakes.make_fake_clip(tmp_path / "in", "c1")
    meta = yaml.safe_load((clip / "clip.yaml").read_text())
    meta["params"] = {"qa": {"max_dropped_fraction": 0.1}}  # a flat key of earlier versions
    (clip / "clip.yaml").write_text(yaml.safe_dump(meta))
    qa = next(s for s in STAGES if s.name == "qa")
    with pytest.warns(DeprecationWarning, match="'max_dropped_fraction' is now "
                      "'stream.max_dropped_fraction'"):
        eff = run.for_stage(qa, clip_params(clip))
    assert eff.stream.max_dropped_fraction == 0.1  # type: ignore[attr-defined]  # the clip's own block wins
    assert eff.tolerance_ms.lidar == 2.0  # type: ignore[attr-defined]  # then the run's
    assert eff.tolerance_ms.camera == 1.0  # type: ignore[attr-defined]  # then the default
    f.write_text(yaml.safe_dump({"qa": {"camera_fsp": 20}}))
    with pytest.raises(ParamsError, match="camera_fsp"):
        load_params(f)
    with pytest.raises(ParamsError, match=r"params\.qa"):
        run.for_stage(qa, {"qa": {"tolerance_ms": {"lidar": -1}}})


@pytest.mark.slow
def test_a_parameter_reaches_the_stage_and_its_manifest(prefect_server: Any, tmp_path: Path,
                                                        capsys: pytest.CaptureFixture[str]
                                                        ) -> None:
    """Set from the CLI (--params FILE) and from the clip (params: block): the stage runs
    with it, the manifest records it, and a change re-runs the stage."""
    from v2xlake.flows.cli import main

    lake = tmp_path / "lake"
    clip = fakes.make_fake_clip(tmp_path / "in", "pclip", n_objects=12)
    meta = yaml.safe_load((clip / "clip.yaml").read_text())
    meta["params"] = {"annotate": {"n_objects": 5}}
    (clip / "clip.yaml").write_text(yaml.safe_dump(meta))
    assert main(["process", str(clip), "--lake", str(lake), "--pipeline", fakes.FAKES]) == 0
    m = json.loads((lake / "manifests" / "pclip" / "annotate.json").read_text())
    assert m["params"] == {"n_objects": 5}
    l_ = Lake(lake)
    assert l_.read_table("clean", "annotations", clip_id="pclip").num_rows == 5
    # the real pipeline's sections from a file, shown by `params show`
    pfile = tmp_path / "run.yaml"
    pfile.write_text(yaml.safe_dump({"deskew": {"pose_gaps": {"max_ns": 30_000_000}}}))
    capsys.readouterr()
    assert main(["params", "show", "--params", str(pfile), "--stage", "deskew"]) == 0
    shown = yaml.safe_load(capsys.readouterr().out)
    assert shown["deskew"]["pose_gaps"] == {"max_ns": 30_000_000, "periods": 2.5}
    pfile.write_text(yaml.safe_dump({"deskew": {"max_pose_gap": 1}}))
    assert main(["params", "show", "--params", str(pfile)]) == 2  # a usage error, no trace
    assert "max_pose_gap" in capsys.readouterr().err


def test_a_stage_output_becomes_visible_together(tmp_path: Path) -> None:
    """The flow stages a stage's Parquet output and publishes it when run returns: until
    then readers see the previous run's files whole; a failed run leaves nothing."""
    lake = Lake(tmp_path / "lake")
    write_agent(lake, "red", Motion(), (100_000_000, 600_000_000))
    owns = [(t.zone, t.name) for t in DESKEW.owns]
    DESKEW.run(lake.for_stage("deskew", owns), CLIP, DESKEW.config())
    root = lake.table_dir("clean", "lidar_points_deskewed", CLIP)
    before = {f: lake.read_bytes(f) for f in lake.list_files(root, ".parquet")}
    inodes = {os.stat(f).st_ino for f in before}
    assert before

    staged = lake.for_stage("deskew", owns, atomic_clip=CLIP)
    report = DESKEW.run(staged, CLIP, DESKEW.config())
    # mid-run (a kill here): the old output is intact and complete, nothing new is visible
    assert {f: lake.read_bytes(f) for f in lake.list_files(root, ".parquet")} == before
    assert all("/_staging/clipA/deskew-p" in o.path for o in report.outputs)
    moved = staged.publish_stage()
    after = {f: lake.read_bytes(f) for f in lake.list_files(root, ".parquet")}
    assert after == before and moved  # same result, but the files were swapped in
    assert not inodes & {os.stat(f).st_ino for f in after}
    assert not lake.list_files(lake.path("_staging"))

    failed = lake.for_stage("deskew", owns, atomic_clip=CLIP)
    DESKEW.run(failed, CLIP, DESKEW.config())
    failed.discard_stage()  # what the flow does when run raises
    assert {f: lake.read_bytes(f) for f in lake.list_files(root, ".parquet")} == after
    assert not lake.list_files(lake.path("_staging"))


# ------------------------------------------------------------------ one geometry vocabulary
def test_num_lidar_pts_has_one_definition(tmp_path: Path) -> None:
    """Defect 3: the catalog summed 3,238 points on 80 boxes and the nuScenes export 645
    (two points_in_boxes, one with a 5 cm margin). Now annotate counts once, and box by box
    the catalog's annotations view and the export's sample_annotation.json carry the same
    number (test_export_nuscenes checks it against the devkit's points_in_box)."""
    from tests.export_fixtures import build_clean_clip
    from v2xlake.tasks.export.common import token
    from v2xlake.tasks.export.nuscenes import NuScenesExportConfig, export_nuscenes

    lake = Lake(tmp_path / "lake")
    build_clean_clip(lake, "clip-a", with_cameras=False, seconds=1.0)  # runs annotate
    out = tmp_path / "nus"
    export_nuscenes(lake, ["clip-a"], out, NuScenesExportConfig())
    version = next(p.name for p in out.iterdir() if (p / "sample.json").is_file())
    anns = json.loads((out / version / "sample_annotation.json").read_text())
    with Catalog(lake) as cat:
        rows = cat.query("SELECT agent_id, frame_idx, instance_id, num_lidar_pts "
                         "FROM annotations").to_pylist()
        world = cat.query("SELECT sum(num_lidar_pts) AS n FROM clean.annotations_world")
    catalog = {(token("sample", "clip-a", r["agent_id"], r["frame_idx"]),
                token("instance", "clip-a", r["agent_id"], r["instance_id"])): r["num_lidar_pts"]
               for r in rows}
    exported = {(a["sample_token"], a["instance_token"]): a["num_lidar_pts"] for a in anns}
    assert len(exported) == len(anns) >= 10 and set(exported) <= set(catalog)
    assert exported == {k: catalog[k] for k in exported}
    assert sum(exported.values()) > 0
    assert sum(catalog.values()) == world.column(0)[0].as_py()


# ------------------------------------------------------------------ retries
def test_only_transient_failures_are_retried() -> None:
    """A retry of bad input, a full disk or a bug reproduces the same failure (and triples
    the time to the error); a connection lost to a worker or a timeout may not."""
    import errno

    from v2xlake.flows.pipeline import _no_retry_on_bad_input
    from v2xlake.schemas.errors import ClipError
    from v2xlake.storage.lake import LakeWriteError

    class Failed:
        def __init__(self, exc: BaseException | None) -> None:
            self.exc = exc

        def result(self) -> None:
            if self.exc is not None:
                raise self.exc

    def retried(exc: BaseException | None) -> bool:
        return _no_retry_on_bad_input(None, None, Failed(exc))

    for bad in (ClipError("clip-a", "no LiDAR topic"), ValueError("x must be finite"),
                KeyError("frame_idx"), ZeroDivisionError(), TypeError("None"),
                LakeWriteError(errno.ENOSPC, "no space left on the device")):
        assert not retried(bad), type(bad).__name__
    for transient in (ConnectionError("worker lost"), TimeoutError(), OSError(errno.EIO, "io")):
        assert retried(transient), type(transient).__name__
    assert not retried(None)
