"""Adding a stage is one package (docs/architecture.md, "Adding a stage"): a toy stage written
into a temporary folder, registered by an entry point of its own distribution metadata, with
its own table and parameters, and nothing in the repository edited. The real machinery must
then know it: the stage list, the table owners, ``v2xlake params show`` (whole tree and
``--stage``), ``--params`` validation, and ``v2xlake process`` (flow, staged publish,
manifest, no-op check, catalog), which re-runs it when its parameter or its code changes.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import textwrap
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import test_flows_fakestages as fakes
import yaml

from v2xlake.schemas import registry
from v2xlake.storage.lake import Lake

REPO = Path(__file__).resolve().parents[1]
CLI = [sys.executable, "-m", "v2xlake.flows.cli"]

# the whole stage: what a developer writes, and nothing else
TOY = {
    "__init__.py": '''
        """A toy stage: ``config.py`` its parameters, ``classify.py`` the rule on arrays,
        ``tables.py`` its row model, ``stage.py`` the lake I/O and the ``TOY`` Stage object."""

        from v2xlake.schemas.stage import StageDeclaration, tables

        DECLARATION = StageDeclaration(name="toy", owns=tables("clean", "toy_lengths"))
        ''',
    "config.py": '''
        """The toy stage's parameters."""

        from pydantic import Field

        from v2xlake.schemas.config import Section, StageConfig


        class Duration(Section):
            """How a clip's length is judged."""

            min_s: float = Field(1.0, ge=0.0, description="a clip at least this long is long")


        class ToyConfig(StageConfig):
            """Marks long clips."""

            duration: Duration = Field(default_factory=Duration)
        ''',
    "classify.py": '''
        """The rule, on arrays."""

        import numpy as np

        from toy_stage.config import Duration


        def is_long(duration_s: np.ndarray, duration: Duration) -> np.ndarray:
            return np.asarray(duration_s) >= duration.min_s
        ''',
    "tables.py": '''
        """The row model of the table the toy stage owns."""

        from pydantic import BaseModel, ConfigDict


        class ToyLengthRow(BaseModel):
            model_config = ConfigDict(frozen=True, extra="forbid")

            clip_id: str
            duration_s: float
            long: bool
        ''',
    "stage.py": '''
        """The toy stage's lake I/O and its Stage object."""

        from pydantic import BaseModel

        from toy_stage import DECLARATION
        from toy_stage.classify import is_long
        from toy_stage.config import ToyConfig
        from toy_stage.tables import ToyLengthRow
        from v2xlake.schemas.arrow import rows_to_table
        from v2xlake.schemas.stage import OutputFile, Stage, StageReport, tables
        from v2xlake.storage.lake import Lake


        def run_toy(lake: Lake, clip_id: str, config: ToyConfig) -> StageReport:
            clips = lake.read_table("clean", "clips", clip_id=clip_id)
            durations = clips.column("duration_s").to_pylist()
            long = is_long(durations, config.duration)
            rows: list[BaseModel] = [
                ToyLengthRow(clip_id=clip_id, duration_s=d, long=bool(x))
                for d, x in zip(durations, long)]
            path, n = lake.write_table("clean", "toy_lengths",
                                       rows_to_table(ToyLengthRow, rows), clip_id=clip_id)
            return StageReport(stage="toy", clip_id=clip_id,
                               outputs=[OutputFile(path=path, rows=n)],
                               metrics={"long": float(sum(map(bool, long)))})


        TOY = Stage(name=DECLARATION.name, config_model=ToyConfig,
                    reads=tables("clean", "clips"), owns=DECLARATION.owns, run=run_toy)
        ''',
}


def write_toy_stage(root: Path) -> Path:
    """The toy package and the metadata of a distribution that registers it (what ``pip
    install`` of a package declaring the entry point leaves on ``sys.path``)."""
    pkg = root / "toy_stage"
    pkg.mkdir(parents=True)
    for name, text in TOY.items():
        (pkg / name).write_text(textwrap.dedent(text).lstrip())
    meta = root / "toy_stage-0.1.dist-info"
    meta.mkdir()
    (meta / "METADATA").write_text("Metadata-Version: 2.1\nName: toy-stage\nVersion: 0.1\n")
    (meta / "entry_points.txt").write_text("[v2xlake.stages]\ntoy = toy_stage\n")
    return pkg


@pytest.fixture
def toy(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    root = tmp_path / "plugins"
    pkg = write_toy_stage(root)
    monkeypatch.syspath_prepend(str(root))
    registry.refresh()
    yield pkg
    monkeypatch.undo()
    for name in [m for m in sys.modules if m == "toy_stage" or m.startswith("toy_stage.")]:
        del sys.modules[name]
    registry.refresh()


def _env(tmp: Path, plugins: Path, **extra: str) -> dict[str, str]:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(map(str, (plugins, REPO, REPO / "tests"))),
               V2XLAKE_NOOP_CACHE=str(tmp / "noop.json"), COLUMNS="160")
    env.update(extra)
    return env


def _cli(args: list[str], env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*CLI, *args], env=env, capture_output=True, text=True, timeout=600)


def test_the_registry_finds_the_toy_stage_and_its_table(toy: Path) -> None:
    from v2xlake.schemas.tables import table_owner
    from v2xlake.storage import manifest

    names = registry.stage_names()
    assert names[-1] == "toy" and names[:-1] == tuple(
        p.rpartition(".")[2] for p in registry.STAGE_PACKAGES)
    # the no-op check and params show need its code version: its package's files, read
    # without importing it
    version = manifest.code_version("toy")
    assert "toy_stage" not in sys.modules
    (toy / "classify.py").write_text((toy / "classify.py").read_text() + "# edited\n")
    assert manifest.code_version("toy") != version
    assert registry.stage_ref("toy") == ("toy_stage.stage", "TOY")
    assert table_owner("clean", "toy_lengths") == "toy"
    assert "toy_stage.stage" not in sys.modules  # the declaration is the package's __init__


def test_a_second_package_claiming_a_table_is_refused(toy: Path) -> None:
    init = toy / "__init__.py"
    init.write_text(init.read_text().replace('"toy_lengths"', '"registrations"'))
    registry.refresh()
    with pytest.raises(ValueError, match=re.escape(
            "clean.registrations is declared by stages 'register' and 'toy'")):
        registry.table_owners()


def test_params_show_knows_the_toy_section(toy: Path, tmp_path: Path) -> None:
    env = _env(tmp_path, toy.parent)
    one = _cli(["params", "show", "--stage", "toy"], env)
    assert one.returncode == 0, one.stderr[-2000:]
    assert one.stdout.splitlines() == [
        "toy:  # Marks long clips.",
        "  duration:  # How a clip's length is judged.",
        "    min_s: 1.0  # a clip at least this long is long"]
    whole = _cli(["params", "show"], env)
    assert whole.returncode == 0, whole.stderr[-2000:]
    tops = [ln.split(":")[0] for ln in whole.stdout.splitlines() if ln and ln[0] != " "]
    assert tops == [*registry.stage_names(), "export"]
    params = tmp_path / "p.yaml"
    params.write_text(yaml.safe_dump({"toy": {"duration": {"min_s": 5}}}))
    mine = _cli(["params", "show", "--stage", "toy", "--params", str(params)], env)
    assert "    min_s: 5.0  # a clip at least this long is long" in mine.stdout, mine.stderr
    params.write_text(yaml.safe_dump({"toy": {"duration": {"min_seconds": 5}}}))
    bad = _cli(["params", "show", "--stage", "toy", "--params", str(params)], env)
    assert bad.returncode != 0 and "min_seconds" in bad.stdout + bad.stderr


@pytest.mark.slow
def test_process_runs_the_toy_stage(toy: Path, tmp_path: Path, prefect_server: Any) -> None:
    clip = fakes.make_fake_clip(tmp_path / "in", "toy_clip")
    lake = Lake(tmp_path / "lake")
    fakes.fake_ingest(lake, clip)  # the clip's clean.clips row, which the toy stage reads
    env = _env(tmp_path, toy.parent, PREFECT_API_URL=prefect_server.api_url)
    params = tmp_path / "p.yaml"
    cmd = ["process", str(clip), "--lake", lake.uri, "--stages", "toy", "--format", "json",
           "--params", str(params)]

    def run(min_s: float) -> tuple[str, list[dict[str, Any]]]:
        params.write_text(yaml.safe_dump({"toy": {"duration": {"min_s": min_s}}}))
        res = _cli(cmd, env)
        assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
        [doc] = json.loads(res.stdout)
        [stage] = doc["stages"]
        assert stage["stage"] == "toy"
        q = _cli(["query", "SELECT clip_id, duration_s, long FROM clean.toy_lengths",
                  "--lake", lake.uri, "--format", "json"], env)
        assert q.returncode == 0, q.stderr[-2000:]
        return stage["status"], json.loads(q.stdout)

    assert run(1.0) == ("done", [{"clip_id": "toy_clip", "duration_s": 2.0, "long": True}])
    assert run(1.0)[0] == "cached"  # its manifest: nothing it depends on changed
    assert run(5.0) == ("done", [{"clip_id": "toy_clip", "duration_s": 2.0, "long": False}])
    (toy / "classify.py").write_text((toy / "classify.py").read_text() + "# edited\n")
    assert run(5.0)[0] == "done"  # its code is part of its manifest key
    manifest = json.loads((tmp_path / "lake" / "manifests" / "toy_clip" / "toy.json")
                          .read_text())
    assert manifest["params"] == {"duration": {"min_s": 5.0}}
