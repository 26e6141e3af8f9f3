"""Release builds: selection, balanced scene-level splits, immutability, checksums."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import pytest
import test_flows_fakestages as fakes

from v2xlake.flows.release import ReleaseError, build_release, list_releases, verify_release
from v2xlake.storage.lake import Lake
from v2xlake.tasks.release_split import SceneKey, SplitConfig, assign_splits, split_counts


def _scenes(n_per: dict[tuple[str, str, str], int]) -> list[SceneKey]:
    out = []
    for (loc, w, li), n in n_per.items():
        out += [SceneKey(f"{loc}-{w}-{li}-{i:03d}", loc, w, li) for i in range(n)]
    return out


def test_splits_deterministic_complete_and_balanced() -> None:
    strata = {("ann_arbor", "clear", "day"): 40, ("ann_arbor", "rain", "night"): 20,
              ("detroit", "clear", "dusk"): 20, ("detroit", "snow", "day"): 7,
              ("ypsilanti", "fog", "night"): 1, ("ypsilanti", "clear", "day"): 2}
    scenes = _scenes(strata)
    a = assign_splits(scenes)
    assert set(a) == {s.clip_id for s in scenes}
    assert assign_splits(list(reversed(scenes))) == a  # order of the query does not matter
    counts = split_counts(a)
    n = len(scenes)
    for name, frac in zip(("train", "val", "test"), (0.7, 0.15, 0.15), strict=True):
        assert abs(counts[name] - frac * n) <= 1.0 + 1e-9, counts
    for key, size in strata.items():
        got = Counter(a[s.clip_id] for s in scenes if s.stratum == key)
        for name, frac in zip(("train", "val", "test"), (0.7, 0.15, 0.15), strict=True):
            assert abs(got[name] - frac * size) < 2.0, (key, got)
    # every big stratum appears in every split: conditions are balanced, not just totals
    for key in [k for k, v in strata.items() if v >= 7]:
        assert {a[s.clip_id] for s in scenes if s.stratum == key} == {"train", "val", "test"}
    other = assign_splits(scenes, SplitConfig(seed=1))
    assert other != a and split_counts(other) == counts
    assert assign_splits(scenes, SplitConfig(seed=1)) == other
    with pytest.raises(ValueError):
        SplitConfig(fractions=(0.5, 0.5, 0.5))
    with pytest.raises(ValueError):
        assign_splits([scenes[0], scenes[0]])


def _fake_lake(tmp: Path, n: int = 8) -> Lake:
    lake = Lake(tmp / "lake")
    conds = [("clear", "day"), ("rain", "night"), ("clear", "dusk"), ("snow", "day")]
    for i in range(n):
        w, li = conds[i % len(conds)]
        clip = fakes.make_fake_clip(tmp / "in", f"clip{i:02d}", location=f"loc{i % 2}",
                                    weather=w, lighting=li, n_objects=10 + i)
        rep = fakes.fake_ingest(lake, clip)
        fakes.fake_annotate(lake, rep.clip_id)
    return lake


def test_release_build_verify_immutable(tmp_path: Path) -> None:
    lake = _fake_lake(tmp_path)
    meta = build_release(lake.uri, "r1", "weather IN ('clear', 'rain')")
    root = Path(lake.path("releases", "r1"))
    assert meta["clip_ids"] == ["clip00", "clip01", "clip02", "clip04", "clip05", "clip06"]
    assert sum(meta["split_counts"].values()) == 6
    splits = json.loads((root / "splits.json").read_text())
    assert sorted(c for ids in splits.values() for c in ids) == meta["clip_ids"]
    for png in ("objects_per_class", "distance_density_per_class", "clips_weather_lighting"):
        assert (root / "plots" / f"{png}.png").read_bytes()[:4] == b"\x89PNG"
    notes = (root / "RELEASE.md").read_text()
    assert "| pedestrian |" in notes and "clips (scenes)" in notes
    copied = root / "lake" / "clean" / "annotations" / "clip_id=clip01" / "agent_id=red"
    assert (copied / "part.parquet").is_file() and not (copied / "part.parquet").is_symlink()
    assert not (root / "lake" / "clean" / "clips" / "clip_id=clip03").exists()
    sums = (root / "SHA256SUMS").read_text().splitlines()
    assert len(sums) == len(json.loads((root / "checksums.json").read_text())["files"])
    res = verify_release(lake.uri, "r1")
    assert res.ok and res.checked == len(sums)
    assert list_releases(lake.uri) == ["r1"]
    assert not [p for p in (root.parent).iterdir() if p.name.startswith(".")]  # no staging left

    with pytest.raises(ReleaseError, match="already exists"):
        build_release(lake.uri, "r1", "true")
    with pytest.raises(ReleaseError, match="no clip matches"):
        build_release(lake.uri, "r2", "weather = 'hail'")
    with pytest.raises(ReleaseError, match="unknown export"):
        build_release(lake.uri, "r3", "true", formats=["lake", "kitti"])
    assert not Path(lake.path("releases", "r2")).exists()

    # the lake moves on: a clip changes, another arrives, one is deleted: the release does not
    before = {p: p.read_bytes() for p in root.rglob("*") if p.is_file()}
    fakes.fake_annotate(lake, "clip01")  # rewrites clip01's annotations in place
    lake.write_table("clean", "annotations",
                     lake.read_table("clean", "annotations", clip_id="clip02").slice(0, 1),
                     clip_id="clip02", agent_id="red")
    lake.delete_partition("clean", "annotations", "clip04")
    fakes.fake_ingest(lake, fakes.make_fake_clip(tmp_path / "in", "clip99", weather="clear"))
    assert verify_release(lake.uri, "r1").ok
    assert {p: p.read_bytes() for p in root.rglob("*") if p.is_file()} == before

    # a flipped byte is found and named
    victim = root / "lake" / "clean" / "annotations" / "clip_id=clip02" / "agent_id=red" / \
        "part.parquet"
    data = bytearray(victim.read_bytes())
    data[len(data) // 2] ^= 0x01
    victim.write_bytes(bytes(data))
    bad = verify_release(lake.uri, "r1")
    assert not bad.ok
    assert any("clip_id=clip02" in p and "sha256" in p for p in bad.problems)
    # an added file and a missing file are found too
    victim.write_bytes(before[victim])
    (root / "extra.txt").write_text("sneaked in")
    (root / "plots" / "objects_per_class.png").unlink()
    probs = verify_release(lake.uri, "r1").problems
    assert any(p.startswith("extra.txt") for p in probs)
    assert any(p.startswith("plots/objects_per_class.png: missing") for p in probs)


def test_release_stable_selection(tmp_path: Path) -> None:
    """Two releases of the same predicate over an unchanged lake hold identical data."""
    lake = _fake_lake(tmp_path, n=4)
    a = build_release(lake.uri, "a", "location = 'loc0'")
    b = build_release(lake.uri, "b", "location = 'loc0'")
    assert a["clip_ids"] == b["clip_ids"] == ["clip00", "clip02"]
    assert a["splits"] == b["splits"]
    ca = json.loads(Path(lake.path("releases", "a", "checksums.json")).read_text())["files"]
    cb = json.loads(Path(lake.path("releases", "b", "checksums.json")).read_text())["files"]
    same = {k for k in ca if k.startswith(("lake/", "plots/", "splits.json"))}
    assert all(ca[k] == cb[k] for k in same)
