"""Red-team findings on clip folders (after #16): a symlink that made ``v2xlake query`` read
any file, a clip.yaml nested deep enough to segfault the process, non-finite and absurd
calibration numbers accepted, and an empty frame name taken for a frame called ''. Each
case failed before its fix."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import duckdb
import numpy as np
import pytest
import yaml

from tests.fixtures.minibag import MiniClip, write_clip
from v2xlake.flows.bookkeeping import user_query
from v2xlake.schemas.clip import MAX_YAML_NESTING, load_yaml
from v2xlake.schemas.errors import ClipError
from v2xlake.storage.lake import Lake
from v2xlake.tasks.ingest import run_ingest
from v2xlake.tasks.ingest.calibration import intrinsics_from_camera_info
from v2xlake.tasks.ingest.clipdir import load_clip_config

REPO = Path(__file__).resolve().parents[2]


def _clip(tmp: Path, name: str = "symclip") -> Path:
    return write_clip(tmp / name, MiniClip(seconds=0.2, points=100, cameras=(), clip_id=name))


def _symlinks_under(root: Path) -> list[Path]:
    return [p for p in root.rglob("*") if p.is_symlink()]


def _read_text(lake: Lake, glob: str) -> list[str]:
    """What ``v2xlake query`` gives for ``read_text(glob)`` (contents), or raises."""
    return [str(r["content"]) for r in user_query(
        lake, f"SELECT content FROM read_text('{glob}')").to_pylist()]


# ------------------------------------------------------------------ 1. symlinks
@pytest.mark.parametrize("where", ["notes.txt", "red/zz_extra.txt"])
def test_a_symlink_out_of_the_clip_never_reaches_landing_or_a_query(
        tmp_path: Path, where: str) -> None:
    """/tmp/probe_sec/a1/symlink_extra.sh: a file clip.yaml does not name, a symlink to a
    secret outside the clip folder (at the clip root or inside a bag folder)."""
    secret = tmp_path / "secret.txt"
    secret.write_text("TOP-SECRET")
    clip = _clip(tmp_path)
    os.symlink(secret, clip / where)
    lake = Lake(tmp_path / "lake")
    with pytest.raises(ClipError, match=r"is a symlink to .*outside the clip folder") as e:
        run_ingest(lake, clip)
    assert e.value.path == str(clip / where)
    # refused before the landing copy: nothing of the clip in the lake, no link, no secret
    assert not _symlinks_under(Path(lake.base))
    assert not [f for f in lake.list_files(lake.path()) if "symclip" in f]


def test_a_symlink_inside_the_clip_lands_as_a_plain_file(tmp_path: Path) -> None:
    clip = _clip(tmp_path)
    (clip / "README.txt").write_text("calibration notes")
    os.symlink("README.txt", clip / "notes.txt")  # relative, resolves inside the clip
    os.symlink(clip / "red", clip / "red_again")  # a folder link: the same files, not walked
    lake = Lake(tmp_path / "lake")
    run_ingest(lake, clip)
    landing = Path(lake.path("landing", "symclip"))
    assert not _symlinks_under(landing)
    assert (landing / "notes.txt").read_text() == "calibration notes"
    assert not (landing / "red_again").exists()
    assert (landing / "red").is_dir()


def test_a_symlinked_folder_out_of_the_clip_is_refused(tmp_path: Path) -> None:
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "secret.txt").write_text("TOP-SECRET")
    clip = _clip(tmp_path)
    os.symlink(outside, clip / "extra")
    with pytest.raises(ClipError, match=r"'extra' is a symlink to .*outside the clip folder"):
        run_ingest(Lake(tmp_path / "lake"), clip)


def test_queries_cannot_read_landing_even_when_it_holds_a_symlink(tmp_path: Path) -> None:
    """Defence in depth: a landing copy made before the fix (or by hand) holds a symlink;
    user SQL may read only the folders the catalog's views read, never landing/."""
    secret = tmp_path / "secret.txt"
    secret.write_text("TOP-SECRET")
    lake = Lake(tmp_path / "lake")
    run_ingest(lake, _clip(tmp_path))
    landing = Path(lake.path("landing", "symclip"))
    os.symlink(secret, landing / "notes.txt")
    for glob in (f"{landing}/*.txt", f"{lake.path('landing')}/**/*.txt",
                 f"{lake.path()}/*/symclip/*.txt"):
        with pytest.raises(duckdb.PermissionException, match="disabled by configuration"):
            _read_text(lake, glob)
    assert user_query(lake, "SELECT count(*) AS n FROM clips").to_pylist() == [{"n": 1}]


# ------------------------------------------------------------------ 2. deep YAML
DEEP = 100_000
DEEP_TEXTS: dict[str, Callable[[], str]] = {
    "flow sequence": lambda: "clip_id: " + "[" * DEEP + "]" * DEEP + "\n",
    "flow mapping": lambda: "clip_id: " + "{a: " * DEEP + "1" + "}" * DEEP + "\n",
    "block sequence": lambda: "clip_id: \n" + "- " * DEEP + "x\n",
}


def _in_a_child(code: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    """Run ``code`` in a fresh interpreter: a segfault must fail the test, not kill pytest."""
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=timeout, env=env, cwd=REPO)


@pytest.mark.parametrize("shape", list(DEEP_TEXTS))
def test_a_deeply_nested_clip_yaml_is_a_clip_error(tmp_path: Path, shape: str) -> None:
    clip = tmp_path / "deep"
    clip.mkdir()
    (clip / "clip.yaml").write_text(DEEP_TEXTS[shape]())
    out = _in_a_child(
        "import sys\nfrom pathlib import Path\n"
        "from v2xlake.schemas.errors import ClipError\n"
        "from v2xlake.tasks.ingest.clipdir import load_clip_config\n"
        f"try:\n    load_clip_config(Path({str(clip)!r}))\n"
        "except ClipError as e:\n    print('CLIPERROR', e)\n")
    assert out.returncode == 0, f"child died ({out.returncode}): {out.stderr[-2000:]}"
    assert "CLIPERROR" in out.stdout and "nesting too deep" in out.stdout, out.stdout


def test_load_yaml_bounds() -> None:
    """Just inside the nesting limit parses (both loaders); just outside, a 16 MB+ text, and
    a RecursionError of the pure-Python loader are ``yaml.YAMLError``."""
    ok = "a: " + "[" * (MAX_YAML_NESTING - 1) + "]" * (MAX_YAML_NESTING - 1)
    assert load_yaml(ok) is not None and load_yaml(ok.encode()) is not None
    with pytest.raises(yaml.YAMLError, match="nesting too deep"):
        load_yaml("a: " + "[" * (MAX_YAML_NESTING + 1) + "]" * (MAX_YAML_NESTING + 1))
    with pytest.raises(yaml.YAMLError, match="too large"):
        load_yaml("a: " + "x" * (16 * 1024 * 1024 + 1))
    normal = (REPO / "tests" / "fixtures" / "ouster" / "clip.yaml")
    if normal.is_file():
        assert load_yaml(normal.read_text()) == yaml.safe_load(normal.read_text())


def test_load_yaml_without_libyaml(monkeypatch: pytest.MonkeyPatch) -> None:
    from v2xlake.schemas import clip as clipschema

    monkeypatch.setattr(clipschema, "_SafeLoader", yaml.SafeLoader)
    assert load_yaml("a: [[1]]\n") == {"a": [[1]]}
    with pytest.raises(yaml.YAMLError, match="nesting too deep"):
        load_yaml("a: " + "[" * 5000 + "]" * 5000)


@pytest.mark.slow
def test_the_flow_quarantines_a_deeply_nested_clip_yaml(prefect_server: object,
                                                        tmp_path: Path) -> None:
    clip = tmp_path / "in" / "deep"
    clip.mkdir(parents=True)
    (clip / "clip.yaml").write_text(DEEP_TEXTS["flow sequence"]())
    lake = tmp_path / "lake"
    out = _in_a_child(
        "from v2xlake.flows.pipeline import process_clip\n"
        f"s = process_clip({str(clip)!r}, {str(lake)!r}, ['ingest'], return_state=True)\n"
        "print('FAILED' if s.is_failed() else 'NOT-FAILED', s.message)\n", timeout=300)
    assert out.returncode == 0, f"child died ({out.returncode}): {out.stderr[-2000:]}"
    assert "FAILED" in out.stdout and "NOT-FAILED" not in out.stdout, out.stdout
    report = json.loads((lake / "quarantine" / "_unreadable-deep" / "report.json").read_text())
    assert "nesting too deep" in report["reason"]


# ------------------------------------------------------------------ 3. numbers
def _cfg(tmp: Path) -> tuple[Path, dict[str, Any]]:
    clip = _clip(tmp, "nums")
    return clip, yaml.safe_load((clip / "clip.yaml").read_text())


def _camera(cfg: dict[str, Any]) -> dict[str, Any]:
    cam = {"name": "CAM_FRONT", "modality": "camera", "topic": "/red/camera/front",
           "msg_type": "sensor_msgs/msg/CompressedImage", "rate_hz": 30,
           "intrinsics": {"width": 1920, "height": 1080, "fx": 1000.0, "fy": 1000.0,
                          "cx": 960.0, "cy": 540.0, "distortion_model": "plumb_bob",
                          "distortion": [0.1, -0.05, 0.0, 0.0, 0.01]}}
    cfg["agents"][0]["sensors"].append(cam)
    return cam


def _set(cfg: dict[str, Any], path: str, value: Any) -> None:
    """Set ``path`` (``intrinsics.*``: a new camera's; ``dimensions.*``: the first agent's
    body box; ``sensor.*``: its first sensor, LIDAR_TOP) to ``value``."""
    where, *keys = path.split(".")
    node: Any
    if where == "intrinsics":
        node = _camera(cfg)["intrinsics"]
    elif where == "dimensions":
        node = cfg["agents"][0].setdefault(
            "dimensions", {"length_m": 4.6, "width_m": 1.9, "height_m": 1.6})
    else:
        node = cfg["agents"][0]["sensors"][0]
    for key in keys[:-1]:
        node = node[int(key)] if isinstance(node, list) else node[key]
    node[int(keys[-1]) if isinstance(node, list) else keys[-1]] = value


NAN, INF = float("nan"), float("inf")
BAD_NUMBERS = [
    ("intrinsics.fx", INF, "CAM_FRONT", "intrinsics.fx: Input should be a finite number"),
    ("intrinsics.fx", 1e308, "CAM_FRONT", "intrinsics.fx: Input should be less than"),
    ("intrinsics.fy", 1e-300, "CAM_FRONT", "intrinsics.fy: Input should be greater than"),
    ("intrinsics.distortion.1", NAN, "CAM_FRONT",
     "intrinsics.distortion[1]: Input should be a finite"),
    ("sensor.rate_hz", INF, "LIDAR_TOP", "rate_hz: Input should be a finite number"),
    ("sensor.rate_hz", 1e9, "LIDAR_TOP", "rate_hz: Input should be less than"),
    ("sensor.extrinsic", {"translation": [5000.0, 0.0, 1.8], "rotation": [1.0, 0, 0, 0]},
     "LIDAR_TOP", "extrinsic: Value error, extrinsic translation is 5000 m"),
    ("dimensions.center_in_ego", [NAN, 0.0, 0.0], None,
     "dimensions.center_in_ego[0]: Input should be a finite number"),
    ("dimensions.center_in_ego", [1e6, 0.0, 0.0], None,
     "dimensions.center_in_ego[0]: Input should be less than"),
]


@pytest.mark.parametrize("path,value,sensor,match", BAD_NUMBERS,
                         ids=[f"{p}={v}" for p, v, _, _ in BAD_NUMBERS])
def test_non_finite_and_absurd_numbers_are_refused(
        tmp_path: Path, path: str, value: Any, sensor: str | None, match: str) -> None:
    clip, cfg = _cfg(tmp_path)
    _set(cfg, path, value)
    (clip / "clip.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    with pytest.raises(ClipError) as e:
        load_clip_config(clip)
    msg = str(e.value)
    assert e.value.clip_id == "nums" and e.value.agent_id == "red", msg
    assert match in msg, msg
    if sensor:
        assert f"sensors[{sensor}]" in msg, msg


def test_large_world_poses_stay_accepted(tmp_path: Path) -> None:
    """Only sensor offsets and body sizes are bounded: a roadside unit's fixed pose in UTM
    or another large local map is a world pose."""
    clip, cfg = _cfg(tmp_path)
    cfg["agents"][1].update(kind="roadside", pose={"kind": "fixed", "local": {
        "translation": [690_123.4, 5_330_456.7, 520.0], "rotation": [1.0, 0.0, 0.0, 0.0]}})
    (clip / "clip.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    assert load_clip_config(clip).agents[1].effective_pose.kind == "fixed"


def test_a_camera_info_with_nan_distortion_is_refused() -> None:
    """CameraInfo from the bag goes through the same model (ingest turns the error into a
    ClipError naming the camera: ``_calibration``), no longer reaching anonymize."""
    msg = type("CameraInfo", (), dict(
        width=640, height=480, distortion_model="plumb_bob",
        k=np.array([500.0, 0, 320, 0, 500, 240, 0, 0, 1]), d=[0.1, NAN, 0.0, 0.0, 0.0]))()
    with pytest.raises(ValueError, match="finite"):
        intrinsics_from_camera_info(msg)


# ------------------------------------------------------------------ 4. empty frame names
def _blank_frames(kind: str) -> Callable[[str, Any], list[tuple[str, str, int, Any]]]:
    """``pose_messages`` of test_pose_sources with every frame name of the pose messages
    empty (header.frame_id of NavSatFix / Imu; child_frame_id of Odometry)."""
    from tests import test_pose_sources as tps

    original = tps.pose_messages

    def messages(kind_: str, ts: Any) -> list[tuple[str, str, int, Any]]:
        out = []
        for topic, typ, t, msg in original(kind_, ts):
            if typ == "nav_msgs/msg/Odometry":
                msg = dataclasses.replace(msg, child_frame_id="")
            elif typ in ("sensor_msgs/msg/NavSatFix", "sensor_msgs/msg/Imu"):
                msg = dataclasses.replace(msg, header=dataclasses.replace(msg.header,
                                                                          frame_id=""))
            out.append((topic, typ, t, msg))
        return out
    return messages


@pytest.mark.parametrize("kind", ["odometry", "split"])
def test_an_empty_frame_name_means_the_ego_frame(tmp_path: Path, kind: str,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    """/tmp/probe_ingest/p6_frames.py emptychild / emptyframe: the track is the one read
    with the ego frame named explicitly (before: "pose is of frame '' but no static
    transform connects it to ego frame")."""
    from tests import test_pose_sources as tps

    monkeypatch.setattr(tps, "pose_messages", _blank_frames(kind))
    tables = []
    for explicit in (False, True):
        d = tps.write_clip(tmp_path / str(explicit), kind)
        if explicit:
            def name_ego(c: dict[str, Any]) -> None:
                c["agents"][0]["pose"]["body_frame"] = "base_link"
                if kind == "split":
                    c["agents"][0]["pose"]["position_frame"] = "base_link"
            tps._edit(d, name_ego)
        lake = Lake(tmp_path / f"lake-{explicit}")
        cid = run_ingest(lake, d).clip_id
        ins = lake.read_table("raw", "ins", clip_id=cid).sort_by("t_ns")
        assert ins.num_rows > 10
        tables.append(ins.select(["t_ns", "lat", "lon", "alt", "roll", "pitch", "azimuth"]))
    assert tables[0].equals(tables[1])
