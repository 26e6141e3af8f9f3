"""The privacy audit reads rosbags and point files: planted leaks in them are found, a
release's own rosbag export passes, and files it cannot read are findings, never skipped."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from tests.export_fixtures import build_clean_clip
from v2xlake.audit import AuditError, AuditReport, audit
from v2xlake.flows.release import build_release
from v2xlake.storage.lake import Lake

EPOCH_NS = 1_700_000_000_123_000_000


def kinds(rep: AuditReport) -> set[str]:
    return {f.kind for f in rep.findings}


def _gnss_bag(dst: Path, storage: StoragePlugin = StoragePlugin.SQLITE3,
              t0_ns: int = EPOCH_NS) -> Path:
    """A ROS 2 bag as a simulator or a car would record it: a NavSatFix with an absolute
    header stamp and log time."""
    ts = get_typestore(Stores.ROS2_HUMBLE)
    fix_t = "sensor_msgs/msg/NavSatFix"
    T = ts.types
    with Writer(dst, version=8, storage_plugin=storage) as w:
        con = w.add_connection("/gnss", fix_t, typestore=ts)
        for k in range(3):
            t = t0_ns + k * 100_000_000
            msg = T[fix_t](
                header=T["std_msgs/msg/Header"](
                    stamp=T["builtin_interfaces/msg/Time"](sec=t // 10**9, nanosec=t % 10**9),
                    frame_id="gnss"),
                status=T["sensor_msgs/msg/NavSatStatus"](status=0, service=1),
                latitude=42.2936 + 1e-5 * k, longitude=-83.7131, altitude=250.0,
                position_covariance=np.zeros(9), position_covariance_type=0)
            w.write(con, t, ts.serialize_cdr(msg, fix_t))
    return dst


def test_planted_ros2_bag_with_navsatfix(tmp_path: Path) -> None:
    rel = tmp_path / "release"
    _gnss_bag(rel / "rosbag" / "leak")
    rep = audit(None, rel, sample_images=0)
    assert {"absolute_time", "latlon"} <= kinds(rep), rep.summary()
    assert any(f.location == "rosbag/leak:/gnss" and f.kind == "latlon" for f in rep.findings)
    assert any("log time" in f.detail for f in rep.findings)


@pytest.mark.parametrize("storage", [StoragePlugin.SQLITE3, StoragePlugin.MCAP])
def test_bare_storage_file_without_metadata(tmp_path: Path, storage: StoragePlugin) -> None:
    """A .db3 / .mcap copied out of its folder (no metadata.yaml) is still read."""
    bag = _gnss_bag(tmp_path / "bag", storage)
    rel = tmp_path / "release"
    rel.mkdir()
    for f in bag.iterdir():
        if f.name != "metadata.yaml":
            shutil.copy(f, rel / f.name)
    rep = audit(None, rel, sample_images=0)
    assert {"absolute_time", "latlon"} <= kinds(rep), rep.summary()


def test_relative_stamps_only_navsatfix_flagged(tmp_path: Path) -> None:
    rel = tmp_path / "release"
    _gnss_bag(rel / "b", t0_ns=100_000_000)
    rep = audit(None, rel, sample_images=0)
    assert kinds(rep) == {"latlon"}, rep.summary()


def test_unreadable_bag_and_unknown_file_are_findings(tmp_path: Path) -> None:
    rel = tmp_path / "release"
    rel.mkdir()
    (rel / "broken.db3").write_bytes(b"not sqlite at all" * 10)
    (rel / "broken.mcap").write_bytes(b"\x89MCAP0\r\n" + b"\x00" * 7)
    (rel / "blob.xyz").write_bytes(b"\x00\x01")
    rep = audit(None, rel, sample_images=0)
    by = {f.location: f.kind for f in rep.findings}
    assert by == {"broken.db3": "unreadable", "broken.mcap": "unreadable",
                  "blob.xyz": "unscannable"}, rep.summary()


def test_point_files(tmp_path: Path) -> None:
    rel = tmp_path / "release"
    rel.mkdir()
    rng = np.random.default_rng(0)
    pts = rng.uniform(-60, 60, (500, 5)).astype("<f4")
    pts[:, 3] = rng.uniform(0, 255, 500)
    pts[:, 4] = rng.integers(0, 32, 500)
    pts.tofile(rel / "ok.pcd.bin")
    leak = pts.copy()
    leak[7, 4] = 1700000000.123  # one float32 value is enough
    leak.tofile(rel / "leak32.pcd.bin")
    np.array([[1.0, 2.0, 3.0, 4.0, 1700000000.123]] * 100, "<f8").tofile(rel / "leak64.bin")
    header = (b"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z timestamp\nSIZE 4 4 4 8\nTYPE F F F F\n"
              b"COUNT 1 1 1 1\nWIDTH 2\nHEIGHT 1\nPOINTS 2\nDATA binary\n")
    rec = np.zeros(2, [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("timestamp", "<f8")])
    rec["timestamp"] = [1.7e9, 1.7e9 + 0.1]
    (rel / "leak.pcd").write_bytes(header + rec.tobytes())
    rec["timestamp"] = [0.0, 0.1]
    (rel / "ok.pcd").write_bytes(header + rec.tobytes())
    np.save(rel / "leak.npy", np.array([1, 2, 1_700_000_000_000_000_000], np.int64))
    rep = audit(None, rel, sample_images=0)
    assert {f.location.split(":")[0] for f in rep.findings} == {
        "leak32.pcd.bin", "leak64.bin", "leak.pcd", "leak.npy"}, rep.summary()
    assert kinds(rep) == {"absolute_time"}


def test_release_rosbag_export_passes(tmp_path: Path) -> None:
    """A freshly built release with the rosbag export: 0 findings, and its camera messages
    are what the detector re-checks."""
    lk = Lake(tmp_path / "lake")
    build_clean_clip(lk, "clip-a", seconds=1.0)
    build_release(lk.uri, "r1", "true", formats=["lake", "rosbag"])
    rep = audit(lk, release="r1", sample_images=4)
    assert rep.ok, rep.summary()
    bags = audit(None, Path(lk.path("releases", "r1", "rosbag")), sample_images=4)
    assert bags.ok and bags.n_images_checked == 4, bags.summary()


def test_release_name_is_checked(tmp_path: Path) -> None:
    lk = Lake(tmp_path / "lake")
    (tmp_path / "lake" / "outside.json").write_text('{"t_ns": 1700000000000000000}')
    for bad in ("../..", "..", "/etc", "a/b", "x" * 240):
        with pytest.raises(AuditError):
            audit(lk, release=bad)
        with pytest.raises(AuditError):
            audit(lk, bad)
    with pytest.raises(AuditError, match="no release"):
        audit(lk, release="clean")  # a release called clean, never the clean zone
