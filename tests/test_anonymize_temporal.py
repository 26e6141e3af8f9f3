"""Temporal consistency (a face / plate missed in one frame between two that have it) and the
clean zone's image format (PNG, or JPEG at a set quality, as settings of AnonymizeConfig)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from anonymize_fixtures import CLIP, build_raw_clip

from v2xlake.audit.rules import jpeg_metadata
from v2xlake.storage.lake import Lake
from v2xlake.tasks.anonymize.config import AnonymizeConfig
from v2xlake.tasks.anonymize.detectors import Detection
from v2xlake.tasks.anonymize.stage import run_anonymize
from v2xlake.tasks.anonymize.temporal import TEMPORAL, fill_gaps

MS = 1_000_000


def face(x: float, score: float = 0.8) -> Detection:
    return Detection("face", (x, 100.0, x + 20.0, 124.0), score, "centerface")


def test_a_miss_between_two_hits_is_filled_at_its_own_time() -> None:
    dets = [[face(100)], [], [face(112, 0.6)]]
    add = fill_gaps(dets, [0, 10 * MS, 33 * MS], max_gap_ns=100 * MS)
    assert add[0] == [] and add[2] == []
    (d,) = add[1]
    assert d.kind == "face" and d.detector == TEMPORAL and d.score == 0.6
    assert d.box == pytest.approx((100 + 12 * 10 / 33, 100, 120 + 12 * 10 / 33, 124))


def test_no_fill_when_found_too_far_apart_or_different() -> None:
    t = [0, 33 * MS, 66 * MS]
    assert fill_gaps([[face(100)], [face(101)], [face(102)]], t, 100 * MS)[1] == []  # found
    assert fill_gaps([[face(100)], [], [face(102)]], t, 50 * MS)[1] == []  # too far in time
    assert fill_gaps([[face(100)], [], [face(300)]], t, 100 * MS)[1] == []  # another object
    plate = Detection("plate", (100, 100, 140, 110), 0.9, "text-plate")
    assert fill_gaps([[face(100)], [], [plate]], t, 100 * MS)[1] == []  # another kind


@pytest.fixture(scope="module")
def jpeg_lake(tmp_path_factory: pytest.TempPathFactory) -> Lake:
    lk = Lake(tmp_path_factory.mktemp("lake_jpeg"))
    build_raw_clip(lk)
    run_anonymize(lk, CLIP, AnonymizeConfig(output={"image_format": "jpeg", "jpeg_quality": 90}))
    return lk


def test_jpeg_clean_zone(jpeg_lake: Lake) -> None:
    cf = jpeg_lake.read_table("clean", "camera_frames", clip_id=CLIP).to_pydict()
    assert cf["blob"] and all(b.endswith(".jpg") for b in cf["blob"])
    for key, anonymizer in zip(cf["blob"], cf["anonymizer"], strict=True):
        data = jpeg_lake.read_blob("clean", key)
        assert data.startswith(b"\xff\xd8") and jpeg_metadata(data) == []
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        assert img is not None and img.shape[:2] == (cf["height"][0], cf["width"][0])
        assert "centerface@" in anonymizer and "text-plate@" in anonymizer


def test_chunking_does_not_change_the_result(tmp_path_factory: pytest.TempPathFactory) -> None:
    """Frames of a camera go in chunks with one frame of look-ahead: one frame per chunk and
    one chunk for all give the same images, blurs and counts."""
    out = []
    for n in (1, 16):
        lk = Lake(tmp_path_factory.mktemp(f"lake_chunk{n}"))
        build_raw_clip(lk, n_images=3)
        rep = run_anonymize(lk, CLIP, AnonymizeConfig(work={"frames_per_chunk": n}))
        cf = lk.read_table("clean", "camera_frames", clip_id=CLIP).to_pydict()
        out.append((sorted(cf["sha256"]), rep.metrics["n_images_guided"],
                    rep.metrics["n_faces"], rep.metrics["n_plates"]))
    assert out[0] == out[1]
