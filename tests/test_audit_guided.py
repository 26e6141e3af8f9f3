"""The audit does not share the blur's blind spots.

A simulated clip is processed (ingest -> guided anonymize); the fresh clean zone passes the
audit, with its projected head / plate locations accounted for (blurred, or nothing the
audit's own detector finds there). Then a real face (scikit-image's astronaut) and a plate are
pasted, unblurred, at a projected head and a projected vehicle face of one clean image (the
blur "missed" them): the audit reports both. A missing or empty lake is an error, and a
diagnostic plot outside the dataset's images is never re-checked.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from v2xlake.audit import AuditConfig, AuditError, audit
from v2xlake.audit.run import _guides, _lake_frames
from v2xlake.storage.lake import Lake
from v2xlake.tasks.anonymize.build import build_detector
from v2xlake.tasks.anonymize.config import AnonymizeConfig
from v2xlake.tasks.anonymize.evaluate import paste_face, real_faces, render_plate
from v2xlake.tasks.anonymize.images import decode_image, encode_png
from v2xlake.tasks.anonymize.stage import run_anonymize
from v2xlake.tasks.ingest import run_ingest


@pytest.fixture(scope="module")
def lake(tmp_path_factory: pytest.TempPathFactory) -> tuple[Lake, str]:
    from v2xlake.tasks.simulate import SimConfig, simulate

    root = tmp_path_factory.mktemp("audit_sim")
    cfg = SimConfig.preset("small", seconds=1.0, cameras=("CAM_FRONT", "CAM_BACK_RIGHT"),
                           camera_hz=2.0, image_width=1280, seed=0)
    clip = simulate(root / "clip", cfg)
    lk = Lake(root / "lake")
    clip_id = run_ingest(lk, clip).clip_id
    run_anonymize(lk, clip_id, AnonymizeConfig())
    return lk, clip_id


def test_fresh_lake_passes(lake: tuple[Lake, str]) -> None:
    lk, _ = lake
    rep = audit(lk, "clean", sample_images=100)
    assert rep.ok, rep.summary()
    assert rep.n_images_checked == 8
    assert rep.n_regions > 0
    assert rep.n_regions == rep.n_regions_blurred + rep.n_regions_not_visible


def test_planted_missed_face_and_plate_are_caught(lake: tuple[Lake, str], tmp_path: Path
                                                  ) -> None:
    lk, clip_id = lake
    frames = _lake_frames(lk, "clean", None)  # type: ignore[arg-type]
    assert frames
    guide = _guides(lk, "clean", {clip_id}, AuditConfig())[clip_id]
    # the image with the largest projected head and plate locations
    best = None
    for rel, m in sorted(frames.items()):
        regs = guide.regions(m.agent, m.sensor, m.stamp_ns) or []
        head = max((r for r in regs if r.part == "head"), key=lambda r: r.expected_px,
                   default=None)
        plate = max((r for r in regs if r.kind == "plate"), key=lambda r: r.expected_px,
                    default=None)
        if head and plate and (best is None or min(head.expected_px, plate.expected_px) >
                               min(best[1].expected_px, best[2].expected_px)):
            best = (rel, head, plate)
    assert best is not None
    rel, head, plate = best
    key = rel.removeprefix("blobs/")
    img = decode_image(lk.read_blob("clean", key))
    photo, face_box = real_faces()["astronaut"]
    fh = int(max(20, min(head.expected_px, 40)))
    hx = int((head.box[0] + head.box[2]) / 2 - fh / 2)
    face = paste_face(img, photo, face_box, fh, hx, int(head.box[1]) + 2, body_max=0)
    pw = int(max(40, min(plate.expected_px, 90)))
    tag = render_plate(np.random.default_rng(3), pw)
    px = int((plate.box[0] + plate.box[2]) / 2 - pw / 2)
    py = int((plate.box[1] + plate.box[3]) / 2)
    img[py : py + tag.shape[0], px : px + tag.shape[1]] = tag
    lk.write_blob("clean", key, encode_png(img))
    rep = audit(lk, "clean", sample_images=100)
    found = {(f.kind, f.location) for f in rep.findings}
    assert ("unblurred_face", rel) in found, (face, rep.summary())
    assert ("unblurred_plate", rel) in found, rep.summary()
    assert {f.location for f in rep.findings} == {rel}, rep.summary()


def test_missing_or_empty_lake_is_an_error(tmp_path: Path) -> None:
    with pytest.raises(AuditError):
        audit(Lake(tmp_path / "nowhere"), "clean")
    (tmp_path / "empty").mkdir()
    with pytest.raises(AuditError):
        audit(None, tmp_path / "empty")


def test_plots_are_not_dataset_images(tmp_path: Path) -> None:
    """A diagnostic figure with a plate-like text and a face next to the release images."""
    rel = tmp_path / "release"
    (rel / "plots").mkdir(parents=True)
    photo, _ = real_faces()["astronaut"]
    img = photo.copy()
    cv2.putText(img, "AB 1234", (20, 480), cv2.FONT_HERSHEY_SIMPLEX, 2.0, (0, 0, 0), 5)
    ok, buf = cv2.imencode(".png", img)
    assert ok
    (rel / "plots" / "registration.png").write_bytes(buf.tobytes())
    (rel / "bev_0001.png").write_bytes(buf.tobytes())
    rep = audit(None, rel, sample_images=10)
    assert rep.ok and rep.n_images_checked == 0, rep.summary()


def test_face_behind_a_window_is_found_by_the_blur(lake: tuple[Lake, str]) -> None:
    """A real face pasted (16-24 px, the reliable range) into a vehicle's projected window
    band: the anonymizer's guided plan finds it there."""
    from v2xlake.tasks.anonymize.evaluate import match

    lk, clip_id = lake
    frames = _lake_frames(lk, "clean", None)  # type: ignore[arg-type]
    assert frames
    guide = _guides(lk, "clean", {clip_id}, AuditConfig())[clip_id]
    guide.config = replace(guide.config, windows=True)
    det = build_detector(AnonymizeConfig())
    photo, face_box = real_faces()["grace_hopper"]
    tried = 0
    for rel, m in sorted(frames.items()):
        regs = guide.regions(m.agent, m.sensor, m.stamp_ns) or []
        for r in (r for r in regs if r.part == "window" and 16 <= r.expected_px <= 40):
            img = decode_image(lk.read_blob("clean", rel.removeprefix("blobs/")))
            fh = int(max(16, min(r.expected_px, 24)))
            x = int((r.box[0] + r.box[2]) / 2 - fh / 2)
            y = int((r.box[1] + r.box[3]) / 2 - fh / 2)
            truth = paste_face(img, photo, face_box, fh, x, y, body_max=0)
            found, _ = match([("face", truth)], det.detect(img, regs))
            assert found.all(), (rel, r, truth)
            tried += 1
            if tried >= 3:
                return
    assert tried > 0, "no window band of the expected size in the clip"
