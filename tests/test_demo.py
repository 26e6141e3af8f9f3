"""The newcomer's path, for real: ``v2xlake demo`` in a fresh process (temporary Prefect
server, every real stage), then the CLI commands on the lake it made."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

from v2xlake.flows.pipeline import STAGE_NAMES


def _run(args: list[str], env: dict[str, str], cwd: Path,
         timeout: float = 420) -> subprocess.CompletedProcess[str]:
    exe = Path(sys.executable).with_name("v2xlake")
    return subprocess.run([str(exe), *args], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=timeout)


@pytest.mark.slow
def test_demo_then_cli(tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
    env.update(V2XLAKE_HOME=str(tmp_path / "home"), COLUMNS="120")
    t0 = time.monotonic()
    demo = _run(["demo", "--out", str(tmp_path / "d"), "--seconds", "1", "--cameras", "1"],
                env, tmp_path)
    elapsed = time.monotonic() - t0
    out = demo.stdout
    assert demo.returncode == 0, out[-4000:] + demo.stderr[-4000:]
    for stage in STAGE_NAMES:
        assert re.search(rf"│ {stage}\s+│ done", out), stage
    assert "LiDAR points per agent" in out and "Registration quality" in out
    assert re.search(r"│ black\s+│\s+\d{4,}", out) and re.search(r"│ red\s+│\s+\d{4,}", out)
    assert "pictures:" in out and ".png" in out
    assert "demo finished in" in out
    print(f"demo (1 s clip, 1 camera) took {elapsed:.1f} s")
    lake = tmp_path / "d" / "lake"
    clip_dir = next((tmp_path / "d" / "clips").iterdir())
    clip_id = clip_dir.name

    q = _run(["query", "SELECT stage, status FROM manifests ORDER BY stage", "--lake", str(lake),
              "--format", "csv"], env, tmp_path, 120)
    assert q.returncode == 0, q.stderr
    assert q.stdout.splitlines()[0] == "stage,status"
    assert sorted(line.split(",")[0] for line in q.stdout.splitlines()[1:]) == sorted(STAGE_NAMES)

    png = tmp_path / "reg.png"
    p = _run(["plot", "registration", "--lake", str(lake), "--clip", clip_id, "--out", str(png)],
             env, tmp_path, 120)
    assert p.returncode == 0, p.stdout + p.stderr
    assert png.read_bytes()[:4] == b"\x89PNG"  # the clip's registration over time
    assert (tmp_path / "reg_bev.png").read_bytes()[:4] == b"\x89PNG"  # one frame's BEV

    rb = _run(["release", "build", "demo-r1", "--lake", str(lake), "--where", "true",
               "--formats", "nuscenes"], env, tmp_path, 240)
    assert rb.returncode == 0, rb.stdout + rb.stderr
    sums = (lake / "releases" / "demo-r1" / "SHA256SUMS").read_text()
    assert "nuscenes/v1.0-v2xlake/sample.json" in sums or "/sample.json" in sums
    rv = _run(["release", "verify", "demo-r1", "--lake", str(lake)], env, tmp_path, 120)
    assert rv.returncode == 0 and "files OK" in rv.stdout, rv.stdout + rv.stderr
    again = _run(["release", "build", "demo-r1", "--lake", str(lake), "--where", "true"],
                 env, tmp_path, 120)
    assert again.returncode == 2 and "immutable" in again.stderr

    bag = next(p for p in clip_dir.iterdir() if p.is_dir() and p.name == "red")
    ros1 = tmp_path / "red.bag"
    cb = _run(["convert-bag", str(bag), str(ros1), "--to", "ros1"], env, tmp_path, 120)
    assert cb.returncode == 0, cb.stdout + cb.stderr
    from rosbags.highlevel import AnyReader

    with AnyReader([bag]) as r2, AnyReader([ros1]) as r1:
        assert r1.message_count == r2.message_count > 0
        assert {c.topic for c in r1.connections} == {c.topic for c in r2.connections}
