"""The privacy audit catches each kind of planted leak and passes a properly cleaned lake."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pyarrow as pa
import pytest
from anonymize_fixtures import CLIP, build_raw_clip

from v2xlake.audit import AuditReport, audit
from v2xlake.audit.rules import jpeg_metadata, png_metadata, scan_structured, scan_table
from v2xlake.storage.lake import Lake
from v2xlake.tasks.anonymize.config import AnonymizeConfig
from v2xlake.tasks.anonymize.evaluate import real_faces
from v2xlake.tasks.anonymize.stage import run_anonymize


@pytest.fixture(scope="module")
def lake(tmp_path_factory: pytest.TempPathFactory) -> Lake:
    lk = Lake(tmp_path_factory.mktemp("lake"))
    build_raw_clip(lk)
    run_anonymize(lk, CLIP, AnonymizeConfig())
    return lk


def kinds(rep: AuditReport) -> set[str]:
    return {f.kind for f in rep.findings}


def test_clean_zone_passes(lake: Lake) -> None:
    rep = audit(lake, "clean", sample_images=4)
    assert rep.ok, rep.summary()
    assert rep.n_images_checked == 4 and rep.n_tables > 10


def test_raw_zone_fails_on_time_latlon_faces(lake: Lake) -> None:
    rep = audit(lake, "raw", sample_images=2)
    assert {"absolute_time", "latlon", "unblurred_face", "unblurred_plate"} <= kinds(rep)
    # epoch times hidden in free text (a QA detail string) are found too
    assert any(
        f.location.endswith("qa_checks/clip_id=clip_test_0001/part.parquet:detail")
        for f in rep.findings
    ), rep.summary()


def _release(tmp_path: Path, lake: Lake) -> Path:
    """A copy of the clean zone as a release folder, to plant leaks in."""
    import shutil

    dst = tmp_path / "release"
    shutil.copytree(lake.path("clean"), dst)
    return dst


def test_planted_absolute_time_column(lake: Lake, tmp_path: Path) -> None:
    rel = _release(tmp_path, lake)
    import pyarrow.parquet as pq

    pq.write_table(
        pa.table({"frame": [1, 2], "timestamp_us": [1_700_000_000_000_000, 1_700_000_000_100_000]}),
        rel / "leak_time.parquet",
    )
    rep = audit(None, rel, sample_images=0)
    assert [f.location for f in rep.findings] == ["leak_time.parquet:timestamp_us"]


def test_planted_latlon_by_name_and_by_value(lake: Lake, tmp_path: Path) -> None:
    import pyarrow.parquet as pq

    rel = _release(tmp_path, lake)
    rng = np.random.default_rng(0)
    pq.write_table(pa.table({"latitude": [31.2] * 3, "x": [1.0, 2.0, 3.0]}), rel / "named.parquet")
    # the same ~10 m drive as the clip, as degrees with 1 cm noise, in columns not named lat/lon
    pq.write_table(
        pa.table(
            {
                "a": 31.230412 + np.linspace(0, 8e-5, 50) + rng.normal(0, 1e-7, 50),
                "b": 121.473701 + np.linspace(0, 5e-5, 50) + rng.normal(0, 1e-7, 50),
            }
        ),
        rel / "unnamed.parquet",
    )
    rep = audit(None, rel, sample_images=0)
    locs = sorted(f.location for f in rep.findings)
    assert locs == ["named.parquet:latitude", "unnamed.parquet:a,b"], rep.summary()


@pytest.mark.parametrize("noise", [0.0, 1e-7, 0.005, 0.02, 0.1])
def test_no_latlon_false_positive_on_local_metres_and_velocities(noise: float) -> None:
    """A 300 m drive's ego poses, a cruising car's velocity (noise in m/s), fixed calibration."""
    from v2xlake.audit import AuditConfig

    rng = np.random.default_rng(1)
    n = 500
    t = pa.table(
        {
            "x": np.linspace(-5, 300, n) + rng.normal(0, 0.01, n),
            "y": np.linspace(2, 80, n),
            "z": 12.5 + rng.normal(0, 0.002, n),
            "vx": 8.66 + rng.normal(0, noise, n),
            "vy": 5.0 + rng.normal(0, noise, n),
            "vz": rng.normal(0, noise, n),
            "tz": np.full(n, 1.6),
            "qw": np.ones(n),
        }
    )
    cfg = AuditConfig()
    assert scan_table(t, "ego", cfg) == []
    assert scan_table(t, "ego", cfg, span_range=(0.2 * 305, 5 * 305)) == []


def _png_with_chunk(img: np.ndarray, ctype: bytes, payload: bytes) -> bytes:
    ok, buf = cv2.imencode(".png", img)
    assert ok
    data = buf.tobytes()
    iend = data.rindex(b"IEND") - 4
    chunk = (
        struct.pack(">I", len(payload))
        + ctype
        + payload
        + struct.pack(">I", zlib.crc32(ctype + payload))
    )
    return data[:iend] + chunk + data[iend:]


def test_planted_image_metadata(lake: Lake, tmp_path: Path) -> None:
    rel = _release(tmp_path, lake)
    img = np.full((16, 16, 3), 90, np.uint8)
    (rel / "text.png").write_bytes(
        _png_with_chunk(img, b"tEXt", b"Comment\x00taken 2024-06-01 at 31.2N")
    )
    (rel / "exif.png").write_bytes(_png_with_chunk(img, b"eXIf", b"MM\x00*\x00\x00\x00\x08"))
    ok, jpg = cv2.imencode(".jpg", img)
    assert ok
    j = jpg.tobytes()
    exif = b"Exif\x00\x00MM\x00*\x00\x00\x00\x08\x00\x00"
    (rel / "exif.jpg").write_bytes(
        j[:2] + b"\xff\xe1" + struct.pack(">H", len(exif) + 2) + exif + j[2:]
    )
    assert png_metadata((rel / "text.png").read_bytes()) == ["tEXt"]
    assert jpeg_metadata((rel / "exif.jpg").read_bytes()) == ["APP1 EXIF"]
    rep = audit(None, rel, sample_images=0)
    assert sorted((f.kind, f.location) for f in rep.findings) == [
        ("image_metadata", "exif.jpg"),
        ("image_metadata", "exif.png"),
        ("image_metadata", "text.png"),
    ]


def test_planted_unblurred_face(lake: Lake, tmp_path: Path) -> None:
    rel = _release(tmp_path, lake)
    photo, _ = real_faces()["astronaut"]
    ok, buf = cv2.imencode(".png", photo)
    assert ok
    (rel / "blobs" / "face.png").write_bytes(buf.tobytes())
    rep = audit(None, rel, sample_images=100)
    assert ("unblurred_face", "blobs/face.png") in {(f.kind, f.location) for f in rep.findings}
    assert {f.location for f in rep.findings} == {"blobs/face.png"}, rep.summary()


def test_release_json_timestamps_and_text() -> None:
    doc = {
        "sample": [
            {"token": "a", "timestamp": 1_700_000_000_123_456},
            {"token": "b", "timestamp": 100_000},
        ],
        "ego_pose": [{"translation": [1.0, 2.0, 3.0], "timestamp": 100_000}],
    }
    found = scan_structured(doc, "sample.json")
    assert [f.kind for f in found] == ["absolute_time"]
    assert scan_structured({"sample": [{"timestamp": 100_000, "x": 31.23}]}, "ok.json") == []
    assert scan_structured({"gps": {"lat": 31.2}}, "g.json")[0].kind == "latlon"
