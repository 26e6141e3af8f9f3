"""Release names, fractions and a tampered seal: clear errors and findings, no tracebacks,
and verify never follows a link out of the release."""

from __future__ import annotations

import json
import math
import os
import shutil
from pathlib import Path

import pytest
from test_release import _fake_lake

from v2xlake.flows.release import ReleaseError, build_release, verify_release
from v2xlake.storage.lake import Lake


@pytest.fixture(scope="module")
def built(tmp_path_factory: pytest.TempPathFactory) -> Lake:
    lake = _fake_lake(tmp_path_factory.mktemp("rel"), n=2)
    build_release(lake.uri, "base", "true")
    return lake


def _copy(lake: Lake, name: str) -> Path:
    dst = Path(lake.path("releases", name))
    shutil.rmtree(dst, ignore_errors=True)
    shutil.copytree(lake.path("releases", "base"), dst, symlinks=True)
    return dst


def test_long_name_and_bad_fractions_refused(built: Lake) -> None:
    with pytest.raises(ReleaseError, match="at most 100"):
        build_release(built.uri, "x" * 240, "true")
    with pytest.raises(ReleaseError, match="at most 100"):
        verify_release(built.uri, "x" * 101)
    for fr in ((math.nan, 0.5, 0.5), (math.inf, 0.0, 0.0), (0.5, 0.5, 0.5), (1.2, -0.1, -0.1)):
        with pytest.raises(ReleaseError, match="fractions"):
            build_release(built.uri, "f", "true", fractions=fr)
    assert not Path(built.path("releases", "f")).exists()


@pytest.mark.parametrize("seal", [b"{}", b"[]", b"{not json", b'{"files": {"a": 1}}'])
def test_broken_checksums_json_is_a_problem(built: Lake, seal: bytes) -> None:
    root = _copy(built, "tamper-seal")
    (root / "checksums.json").write_bytes(seal)
    res = verify_release(built.uri, "tamper-seal")
    assert not res.ok and "seal cannot be read" in res.problems[0]


def test_non_utf8_sums_is_a_problem(built: Lake) -> None:
    root = _copy(built, "tamper-sums")
    (root / "SHA256SUMS").write_bytes(b"\xff\xfe\n")
    assert not verify_release(built.uri, "tamper-sums").ok


def test_symlinks_are_findings_and_never_followed(built: Lake, tmp_path: Path) -> None:
    assert verify_release(built.uri, "base").ok
    root = _copy(built, "tamper-link")
    outside = tmp_path / "splits.json"
    shutil.copy(root / "splits.json", outside)
    (root / "splits.json").unlink()
    os.symlink(outside, root / "splits.json")  # identical bytes, but a link
    os.symlink("/", root / "rootlink")  # following it would walk /proc
    res = verify_release(built.uri, "tamper-link")
    assert sorted(res.problems) == [
        "rootlink: a symlink (a release is copied, never linked)",
        "splits.json: a symlink (a release is copied, never linked)"], res.problems
    listed = json.loads((root / "checksums.json").read_text())["files"]
    assert res.checked == len(listed) - 1
