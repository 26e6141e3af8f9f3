"""The wheel: what a deployment runs must version its stages exactly as the checkout does.

Stage code versions (``storage.manifest.code_version``) hash each stage's source files found
through the import system. Resolved by path arithmetic they once came out as the hash of
nothing from an installed wheel, so a deployment of changed code skipped every stage as
unchanged. Here the working tree is built into a wheel (setuptools, no build isolation: no
registry needed), installed ``--no-deps`` into a fresh venv outside the repository whose
dependencies are the test venv's own (a path entry, so the checkout's editable install is not
seen), and run from a folder outside the repository:

- every stage's code version is the checkout's, and none is the hash of nothing;
- editing one stage's module in the installed copy re-runs that stage (its recorded manifest
  is no longer current) and leaves another stage current;
- every data file the package holds (message definitions, configs, images, the detector
  models) is in the wheel, and the detectors find their models inside the install.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
import textwrap
import zipfile
from pathlib import Path

import pytest

from v2xlake.storage import manifest

REPO = Path(__file__).resolve().parents[1]
EMPTY_HASH = "e3b0c44298fc1c14"  # sha256 of no bytes, first 16 hex digits
DATA_SUFFIXES = {".msg", ".yaml", ".yml", ".json", ".png", ".onnx", ".npz"}
SKIP_DIRS = {".git", ".venv", "build", "dist", "__pycache__", ".mypy_cache", ".pytest_cache",
             ".ruff_cache", "out", "lake", "demo-lake", ".v2xlake"}

# run inside the installed venv: record a manifest per stage (phase "record"), or say which
# stages are still current (phase "check"); prints JSON
PROBE = textwrap.dedent("""
    import json, sys
    from pathlib import Path
    import v2xlake
    from v2xlake.schemas.stage import StageReport
    from v2xlake.storage import manifest as m
    from v2xlake.storage.lake import Lake
    from v2xlake.tasks.anonymize.detectors import centerface_onnx_path
    from v2xlake.tasks.anonymize.plateread import rec_onnx_path
    from v2xlake.tasks.anonymize.textplate import text_det_onnx_path

    phase, lake_dir, stages = sys.argv[1], sys.argv[2], sys.argv[3].split(",")
    lake = Lake(lake_dir)
    out = {"file": v2xlake.__file__, "root": str(m.PACKAGE_ROOT),
           "versions": {s: m.code_version(s) for s in m.STAGE_MODULES},
           "models": [str(centerface_onnx_path()), str(text_det_onnx_path()),
                      str(rec_onnx_path()),
                      str(centerface_onnx_path().parent / "centerface_int8.onnx")],
           "closures": {s: [str(p) for p in m.module_closure(mod)]
                        for s, mod in m.STAGE_MODULES.items()}}
    current = {}
    for s in stages:
        key = m.stage_key(lake, "clip-a", s, {"p": 1})
        if phase == "record":
            m.record(lake, StageReport(stage=s, clip_id="clip-a"), key)
        current[s] = m.is_current(lake, "clip-a", s, key)
    out["current"] = current
    print(json.dumps(out))
""")


def _clean_env() -> dict[str, str]:
    """This process's environment without PYTHONPATH / PYTHONHOME: other tests put the
    checkout on PYTHONPATH for their subprocesses, and pip, seeing the checkout's
    ``v2xlake.egg-info`` there, would call the wheel "already satisfied" and skip it."""
    return {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}


def _copy_source(dst: Path) -> Path:
    """The working tree as it is (tracked or not), without venvs, caches and build output."""
    def ignore(folder: str, names: list[str]) -> set[str]:
        return {n for n in names if n in SKIP_DIRS or n.endswith(".egg-info")}

    shutil.copytree(REPO, dst, ignore=ignore, symlinks=True)
    return dst


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Build the wheel and install it into a fresh venv outside the repository."""
    base = tmp_path_factory.mktemp("wheel")
    src = _copy_source(base / "src")
    dist = base / "dist"
    build = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
         "--disable-pip-version-check", "-v", "-w", str(dist), str(src)],
        capture_output=True, text=True, cwd=base, env=_clean_env())
    assert build.returncode == 0, build.stdout[-3000:] + build.stderr[-3000:]
    wheels = list(dist.glob("v2xlake-*.whl"))
    assert len(wheels) == 1, wheels
    venv = base / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True,
                   env=_clean_env())
    py = venv / "bin" / "python"
    subprocess.run([sys.executable, "-m", "pip", "--python", str(py), "install", "--no-deps",
                    "--no-index", "--disable-pip-version-check", "-q", str(wheels[0])],
                   check=True, cwd=base, env=_clean_env())
    site = Path(subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()"
                                "['purelib'])"], check=True, capture_output=True,
                               text=True).stdout.strip())
    # the dependencies: the test venv's site-packages as a plain path entry after the wheel's
    # (its .pth files, the checkout's editable install among them, are not processed)
    deps = {sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]}
    (site / "zz_v2xlake_test_deps.pth").write_text("\n".join(sorted(deps)) + "\n")
    log = base / "build.log"
    log.write_text(build.stdout + build.stderr)
    return {"base": base, "src": src, "wheel": wheels[0], "py": py, "site": site,
            "build_log": log}


def _probe(installed: dict[str, Path], phase: str, stages: list[str],
           checkout: bool = False) -> dict:
    """Run PROBE in the wheel's venv, or (``checkout``) with the test venv's Python on the
    copied source tree, the checkout the wheel was built from (the live working tree may
    change under a running test)."""
    run_dir = installed["base"] / "run"  # outside the repository: no checkout on sys.path
    run_dir.mkdir(exist_ok=True)
    env = _clean_env()
    env["V2XLAKE_HOME"] = str(installed["base"] / "home")
    py = str(installed["py"])
    if checkout:
        py, env["PYTHONPATH"] = sys.executable, str(installed["src"])
    r = subprocess.run([py, "-c", PROBE, phase,
                        str(installed["base"] / "lake"), ",".join(stages)],
                       capture_output=True, text=True, cwd=run_dir, env=env)
    assert r.returncode == 0, r.stderr[-4000:]
    return dict(json.loads(r.stdout.strip().splitlines()[-1]))


def test_build_has_no_warnings_of_our_making(installed: dict[str, Path]) -> None:
    log = installed["build_log"].read_text()
    bad = [line for line in log.splitlines()
           if "Warning" in line or "deprecat" in line.lower()]
    assert not bad, "\n".join(bad[:20])


def test_wheel_holds_every_data_file(installed: dict[str, Path]) -> None:
    src = installed["src"]
    want = sorted(p.relative_to(src).as_posix() for p in (src / "v2xlake").rglob("*")
                  if p.suffix in DATA_SUFFIXES and "__pycache__" not in p.parts)
    with zipfile.ZipFile(installed["wheel"]) as z:
        have = set(z.namelist())
    assert any(w.endswith(".onnx") for w in want), "the detector models are package data"
    assert [w for w in want if w not in have] == []
    # no second top-level import name, no tests or scripts in the wheel
    assert {n.split("/")[0] for n in have if not n.startswith("v2xlake-")} == {"v2xlake"}


def test_installed_code_versions_match_the_checkout(installed: dict[str, Path]) -> None:
    out = _probe(installed, "check", [])
    src = _probe(installed, "check", [], checkout=True)
    assert Path(src["file"]).is_relative_to(installed["src"]), src["file"]
    site = installed["site"]
    assert Path(out["file"]).is_relative_to(site), out["file"]
    assert Path(out["root"]) == site / "v2xlake"
    assert all(Path(p).is_relative_to(site) and Path(p).is_file() for p in out["models"]), \
        out["models"]
    for stage, version in out["versions"].items():
        digest = version.split("+", 1)[1]
        assert digest != EMPTY_HASH, f"{stage}: code version of no files ({version})"
        # the package version may differ (an uninstalled checkout says 0+unknown); the
        # hash of the stage's files, by path relative to the package, may not
        assert digest == src["versions"][stage].split("+", 1)[1], stage
        assert len(out["closures"][stage]) >= 2, (stage, out["closures"][stage])


def test_changed_stage_reruns_and_unchanged_stage_does_not(
        installed: dict[str, Path]) -> None:
    before = _probe(installed, "record", list(manifest.STAGE_MODULES))
    assert all(before["current"].values()), before["current"]
    closures = {s: set(files) for s, files in before["closures"].items()}
    changed = "qa"
    others = set().union(*(f for s, f in closures.items() if s != changed))
    unique = sorted(closures[changed] - others)
    assert unique, f"no module belongs to {changed} alone"
    target = Path(unique[0])
    assert target.is_relative_to(installed["site"])
    target.write_text(target.read_text() + "\n# a deployment changed this stage\n")
    after = _probe(installed, "check", list(manifest.STAGE_MODULES))
    assert after["versions"][changed] != before["versions"][changed]
    assert after["current"][changed] is False
    assert after["versions"][changed].split("+")[0] == before["versions"][changed].split("+")[0]
    for stage in manifest.STAGE_MODULES:
        if stage != changed:
            assert after["versions"][stage] == before["versions"][stage], stage
            assert after["current"][stage] is True, stage
