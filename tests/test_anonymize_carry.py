"""Key frames and carried detections (``carry.py``), the provenance string, and a clip
without cameras (no guide, no LiDAR clusters)."""

from __future__ import annotations

import pytest
from anonymize_fixtures import CLIP, build_raw_clip
from pydantic import BaseModel

from v2xlake.storage.lake import Lake
from v2xlake.tasks.anonymize import stage as stage_mod
from v2xlake.tasks.anonymize.build import blur_config, build_detector
from v2xlake.tasks.anonymize.carry import (
    CARRIED,
    between,
    full_key_frames,
    key_frames,
    new_regions,
    plate_windows,
)
from v2xlake.tasks.anonymize.config import NOT_PROVENANCE, AnonymizeConfig
from v2xlake.tasks.anonymize.detectors import Detection
from v2xlake.tasks.anonymize.guide import Region
from v2xlake.tasks.anonymize.stage import run_anonymize

MS = 1_000_000
SHAPE = (1080, 1920, 3)


def _stamps(hz: float, n: int) -> list[int]:
    return [round(k * 1e9 / hz) for k in range(n)]


def test_key_frames_every_third_at_30hz_every_frame_at_10hz() -> None:
    keys = key_frames(_stamps(30, 10), 120 * MS)
    assert keys == [True, False, False, True, False, False, True, False, False, True]
    assert all(key_frames(_stamps(10, 6), 120 * MS))
    assert key_frames(_stamps(20, 5), 120 * MS) == [True, False, True, False, True]
    assert all(key_frames(_stamps(30, 7), 0))
    # a gap longer than the interval: both frames around it are key frames
    t = [0, 33 * MS, 66 * MS, 500 * MS, 533 * MS, 566 * MS]
    k = key_frames(t, 120 * MS)
    assert k[2] and k[3] and k[0] and k[-1]


def _head(x: float, expected: float = 30.0, inst: str = "ped-1") -> Region:
    return Region("face", (x - 40, 400, x + 40, 480), expected, inst, part="head",
                  anchor=(x, 440.0))


def test_a_face_found_in_both_key_frames_moves_with_its_region() -> None:
    """Key frames at 0 and 100 ms; the head's region moves 30 px per 33 ms: the frame at
    33 ms gets the face where its region put it, not where the key frames saw it."""
    f0 = Detection("face", (90.0, 425.0, 120.0, 455.0), 0.9, "centerface")
    f1 = Detection("face", (180.0, 425.0, 210.0, 455.0), 0.8, "centerface")
    dets, again = between(([f0], [_head(105)], 0), ([f1], [_head(195)], 100 * MS),
                          [_head(135)], 33 * MS, 0.5, SHAPE)
    assert not again and len(dets) == 1
    d = dets[0]
    assert d.detector == CARRIED and d.kind == "face"
    assert d.box == pytest.approx((120.0, 425.0, 150.0, 455.0), abs=1e-6)


def test_the_key_frames_disagree_the_region_is_searched_again() -> None:
    """Found before, not after: the carried box is not spread (it may be a flicker of a
    false face); the neighbourhood of the carried box goes back to the detector in this
    frame, at the scale of its region."""
    f0 = Detection("face", (90.0, 425.0, 120.0, 455.0), 0.3, "centerface")
    dets, again = between(([f0], [_head(105)], 0), ([], [_head(195)], 100 * MS),
                          [_head(135)], 33 * MS, 0.5, SHAPE)
    assert dets == [] and len(again) == 1
    r = again[0]
    assert r.kind == "face" and r.expected_px == 30.0
    assert r.box == pytest.approx((90.0, 395.0, 180.0, 485.0))  # (120, 425, 150, 455) grown


def test_a_detection_without_a_region_is_kept_and_grown() -> None:
    """A safety-pass plate (no 3D box) seen only in the key frame before: kept in place and
    grown by carry_grow x the time distance (a third of the interval here)."""
    p = Detection("plate", (1000.0, 600.0, 1090.0, 620.0), 0.7, "text-plate")
    dets, again = between(([p], [], 0), ([], [], 99 * MS), [], 33 * MS, 0.5, SHAPE)
    assert not again and len(dets) == 1
    x0, _y0, x1, _y1 = dets[0].box
    assert x0 == pytest.approx(1000 - 0.5 / 3 * 90, rel=0.02)
    assert x1 - x0 == pytest.approx(90 * (1 + 2 * 0.5 / 3), rel=0.02)


def test_new_regions_are_those_not_in_both_key_frames() -> None:
    here = [_head(135), _head(600, inst="ped-2"), Region("face", (0, 0, 50, 50), 20.0, "")]
    fresh = new_regions(here, [_head(105), _head(590, inst="ped-2")], [_head(195)], SHAPE)
    assert {r.instance for r in fresh} == {"ped-2", ""}
    assert new_regions(here, None, [_head(195)], SHAPE) == here
    # without an anchor, a region cut by the frame edge is searched again
    edge = Region("face", (0, 400, 60, 480), 30.0, "ped-3", part="head")
    assert new_regions([edge], [edge], [edge], SHAPE) == [edge]


def test_a_small_face_found_in_both_key_frames_is_carried_not_searched() -> None:
    """Small faces (under ``min_face_px``) are searched in every frame, because they flicker;
    one that both key frames found is there, and is carried (interpolated) like a large
    one. Found in only one key frame, or in none: searched here."""
    f0 = Detection("face", (95.0, 430.0, 107.0, 442.0), 0.5, "centerface")
    f1 = Detection("face", (185.0, 430.0, 197.0, 442.0), 0.4, "centerface")
    small = lambda x: _head(x, expected=12.0)  # noqa: E731
    before, after, here = [small(105)], [small(195)], [small(135)]
    assert new_regions(here, before, after, SHAPE, 16.0) == here  # no detections given
    assert new_regions(here, before, after, SHAPE, 16.0, ([f0], [f1])) == []
    assert new_regions(here, before, after, SHAPE, 16.0, ([f0], [])) == here
    assert new_regions(here, before, after, SHAPE, 16.0, ([], [f1])) == here
    # a face of another region (another person) does not vouch for this one
    other = Detection("face", (595.0, 430.0, 607.0, 442.0), 0.5, "centerface")
    assert new_regions(here, [*before, _head(600, 12.0, "ped-2")], after, SHAPE, 16.0,
                       ([other], [f1])) == here
    dets, again = between(([f0], before, 0), ([f1], after, 100 * MS), here, 33 * MS, 0.5,
                          SHAPE, new_regions(here, before, after, SHAPE, 16.0, ([f0], [f1])))
    assert not again and len(dets) == 1 and dets[0].detector == CARRIED


def test_onnx_sessions_are_built_once_per_model_file(tmp_path) -> None:
    """Each ``run_anonymize`` builds its detector; the onnxruntime sessions behind it (the
    costly part: graph optimisation) are shared within the process, per model file and
    version of that file (``quantize.py`` rewrites the int8 copy in place)."""
    import os
    import shutil

    from v2xlake.tasks.anonymize.detectors import centerface_onnx_path, ort_session

    src = centerface_onnx_path().parent / "centerface_int8.onnx"
    a, b = build_detector(AnonymizeConfig()), build_detector(AnonymizeConfig())
    assert a.face is not None and b.face is not None and a.plate is not None
    assert a.face._session is b.face._session and a.plate._session is b.plate._session
    copy = tmp_path / "m.onnx"
    shutil.copy(src, copy)
    s1 = ort_session(str(copy))
    assert ort_session(str(copy)) is s1
    st = copy.stat()
    os.utime(copy, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000_000))
    assert ort_session(str(copy)) is not s1



def test_folded_text_detector_is_the_shipped_graph() -> None:
    """``fold_scalar_affine`` (PP-OCRv4's scalar affine steps and four-node hard-swish folded
    into its convolutions, ~1.4x faster on one core) computes the shipped detector's text
    probabilities, padded borders included; a model without those steps is left alone."""
    import cv2
    import numpy as np
    import onnx

    from v2xlake.tasks.anonymize.detectors import (
        _new_ort_session,
        centerface_onnx_path,
        fold_scalar_affine,
    )
    from v2xlake.tasks.anonymize.textplate import text_det_onnx_path

    path = str(text_det_onnx_path())
    folded = fold_scalar_affine(path)
    assert folded is not None
    ops = [n.op_type for n in onnx.load_from_string(folded).graph.node]
    shipped = [n.op_type for n in onnx.load(path).graph.node if n.op_type != "Constant"]
    assert "Div" not in ops and "Clip" not in ops and len(ops) < 0.6 * len(shipped)
    rng = np.random.default_rng(0)
    view = rng.integers(90, 200, (96, 256, 3), dtype=np.uint8)
    cv2.putText(view, "AB 1234", (20, 64), cv2.FONT_HERSHEY_SIMPLEX, 1.4, (10, 10, 10), 3)
    blob = cv2.dnn.blobFromImage(view, 1 / 127.5, (256, 96), (127.5,) * 3, swapRB=True)
    ref = _new_ort_session(path).run(None, {"x": blob})[0]
    out = _new_ort_session(folded).run(None, {"x": blob})[0]
    assert ref.max() > 0.5  # the text is there
    assert np.abs(out - ref).max() < 1e-4  # float rounding (2e-5 at steep text edges)
    assert fold_scalar_affine(str(centerface_onnx_path())) is None

def test_each_image_is_decoded_once(tmp_path, monkeypatch) -> None:
    """The look-ahead frames a chunk detects (the next key frame, the carried frames before
    it) are decoded there and kept for the next chunk, not decoded again (a PNG decode costs
    about what the encode does)."""
    from v2xlake.tasks.anonymize import images as images_mod

    calls: list[int] = []
    real = images_mod.decode_image

    def counting(data: bytes) -> object:
        calls.append(len(data))
        return real(data)

    monkeypatch.setattr(images_mod, "decode_image", counting)
    lk = Lake(tmp_path / "lake")
    build_raw_clip(lk, n_images=5)
    rep = run_anonymize(lk, CLIP, AnonymizeConfig(work={"frames_per_chunk": 1, "workers": 1}))
    assert rep.metrics["n_images"] >= 5 and len(calls) == rep.metrics["n_images"]


def test_a_lidar_only_clip_is_carried_by_cluster_track(tmp_path, monkeypatch) -> None:
    """Regions from LiDAR clusters (here the fixture's annotated boxes, given the clusters'
    source: the fixture's scans hold no objects) are carried with ``clusters.carry`` (on by
    default; false: every frame in full): the frames between key frames go through
    ``carry.between_tracked``, those after the second key frame with the key frame before
    that (the image velocity of a detection leaving the view); with
    ``clusters.full_frame_every`` 2 the key frames between two with the full-frame plan get
    the shrunk safety pass and ``carry.key_windows`` around the key frame before's finds;
    the provenance tells carried from every frame in full."""
    import dataclasses

    from v2xlake.tasks.anonymize import carry as carry_mod
    from v2xlake.tasks.anonymize.context import ClipGuide
    from v2xlake.tasks.anonymize.guided import GuidedDetector

    calls: list[bool] = []
    real = carry_mod.between_tracked

    def spy(*a: object, **k: object) -> object:
        calls.append(len(a) > 8 and a[8] is not None)
        return real(*a, **k)  # type: ignore[arg-type]

    windows: list[tuple[int, bool]] = []  # (stamp of the key frame before, one before that)
    real_w = carry_mod.key_windows

    def spy_w(*a: object, **k: object) -> object:
        windows.append((a[0][2], a[1] is not None))  # type: ignore[index]
        return real_w(*a, **k)  # type: ignore[arg-type]

    plans: list[str] = []  # the safety passes, stubbed: the scheduling does not depend on
    # what they find (run for real, the full-frame plan made the test twice as long)
    monkeypatch.setattr(GuidedDetector, "full_frame",
                        lambda self, img, plates=True: plans.append("full") or [])
    monkeypatch.setattr(GuidedDetector, "safety", lambda self, img: plans.append("shrunk")
                        or [])
    build = stage_mod.build_guide
    monkeypatch.setattr(carry_mod, "between_tracked", spy)
    monkeypatch.setattr(carry_mod, "key_windows", spy_w)
    # the fixture's boxes project into no image: every frame guided by no region (a frame
    # without guidance gets the full-frame plan whatever the key frame)
    regions = ClipGuide.regions
    monkeypatch.setattr(ClipGuide, "regions", lambda self, *a: regions(self, *a) or [])
    monkeypatch.setattr(stage_mod, "build_guide", lambda *a, **k: dataclasses.replace(
        build(*a, **k), source="lidar clusters"))
    lk = Lake(tmp_path / "lake")
    build_raw_clip(lk, n_images=7)  # 30 Hz: key frames 0, 3 and 6
    # every 2nd key frame of a camera with the full-frame plan (clusters.full_frame_every):
    # 0 and 6; 3 gets the shrunk safety pass and windows around key frame 0's detections
    light = {"carry": True, "carry_safety": False, "full_frame_every": 2}
    rep = run_anonymize(lk, CLIP, AnonymizeConfig(work={"workers": 1}, clusters=light))
    assert "anonymize: regions from lidar clusters" in rep.notes
    assert rep.metrics["n_images"] == 14
    assert len(calls) == 8 and calls.count(True) == 4, calls  # 2 agents x frames 1-2, 4-5
    assert plans.count("full") == 4 and plans.count("shrunk") == 2, plans
    t0 = sorted({t for t, _ in windows})
    assert len(windows) == 2 and len(t0) == 1 and not any(e for _, e in windows), windows
    # every frame in full is one setting away from carried (the default), and the
    # provenance tells the two apart
    off = AnonymizeConfig(clusters={"carry": False})
    assert "clusters.carry=True" in AnonymizeConfig().provenance("d")
    assert "clusters.carry=False" in off.provenance("d")


def test_the_provenance_names_every_setting_that_changes_what_is_blurred() -> None:
    base = AnonymizeConfig()
    det = build_detector(base)
    s = base.provenance(det.version)
    for name in type(base).model_fields:
        sub = getattr(base, name)
        keys = ([f"{name}.{k}" for k in type(sub).model_fields] if isinstance(sub, BaseModel)
                else [name])
        for key in keys:
            assert (f"{key}=" in s) == (name not in NOT_PROVENANCE), key
    for update in ({"faces": {"fine_scale": 1.5}}, {"plates": {"full_fine_scale": 2.0}},
                   {"carry": {"key_interval_ms": 0.0}}, {"blur": {"plate_margin": 0.3}},
                   {"temporal": {"fill": False}}, {"plates": {"read": False}},
                   {"plates": {"read_min_digits": 0}}, {"plates": {"read_min_conf": 0.6}},
                   {"faces": {"int8": True}}, {"blur": {"face_margin_x": 0.2}},
                   {"blur": {"face_margin_top": 0.2}}, {"blur": {"face_margin_bottom": 0.2}},
                   {"full_proposals": False}, {"faces": {"first_int8": False}},
                   {"faces": {"proposal_threshold": 0.1}}, {"plates": {"proposal_scale": 0.75}},
                   {"plates": {"edge_threshold": 60.0}}, {"clusters": {"gap_deg": 0.0}}):
        assert AnonymizeConfig(**update).provenance(det.version) != s, update
    # the models themselves: the int8 face model and the plate reader are in the version
    assert det.version.count("onnx-sha256:") >= 3 and "ppocrv4-rec@" in det.version
    q = build_detector(AnonymizeConfig(faces={"int8": True})).version
    assert ":int8" in q.split("|")[0] and ":int8" not in det.version.split("|")[0]
    # the full-frame plan's proposing first pass runs the int8 copy: its version says so
    assert "full-proposals:first@" in det.version and ":int8:" in det.version
    assert "full-proposals" not in build_detector(AnonymizeConfig(full_proposals=False)).version
    assert build_detector(AnonymizeConfig(plates={"read": False})).version != det.version
    same: tuple[dict[str, dict[str, object]], ...] = (
        {"work": {"workers": 3}}, {"output": {"png_compression": 6}},
        {"work": {"frames_per_chunk": 4}}, {"work": {"progress_log_images": 7}},
        {"work": {"progress_log_s": 1.0}}, {"output": {"image_format": "jpeg"}})
    for upd in same:
        assert AnonymizeConfig(**upd).provenance(det.version) == s, upd  # type: ignore[arg-type]


def test_flat_keys_of_earlier_versions_still_work() -> None:
    """A parameter file written for the flat keys keeps working: each key lands in its
    section, with a warning that names the new key."""
    from v2xlake.schemas.config import RenamedParameterWarning

    with pytest.warns(RenamedParameterWarning, match="faces.int8"):
        cfg = AnonymizeConfig.model_validate({"face_int8": True, "workers": 2,
                                              "lidar_clusters": False})
    assert cfg.faces.int8 and cfg.work.workers == 2 and not cfg.clusters.enabled
    assert cfg == AnonymizeConfig(faces={"int8": True}, work={"workers": 2},
                                  clusters={"enabled": False})


def test_a_clip_without_cameras_builds_no_guide(tmp_path, monkeypatch) -> None:
    """No image to blur: neither the guide nor the LiDAR clusters nor the detector are
    computed, also when ingest wrote (empty) camera_frames files for the agents, as it
    does for every agent; the clean zone still mirrors those files (0 rows)."""
    from v2xlake.tasks.anonymize import build as build_mod

    lake = Lake(tmp_path)
    build_raw_clip(lake, n_images=0)
    assert lake.list_files(lake.table_dir("raw", "camera_frames", CLIP), ".parquet")

    def boom(*_a: object, **_k: object) -> None:
        raise AssertionError("computed for a clip without cameras")

    monkeypatch.setattr(stage_mod, "lidar_clusters", boom)
    monkeypatch.setattr(stage_mod, "build_guide", boom)
    monkeypatch.setattr(build_mod, "build_detector", boom)
    rep = run_anonymize(lake, CLIP, AnonymizeConfig(work={"workers": 1}))
    assert rep.metrics["n_images"] == 0
    assert any("no camera images" in n for n in rep.notes)
    for table in ("camera_frames", "anonymization_audit"):
        files = lake.list_files(lake.table_dir("clean", table, CLIP), ".parquet")
        assert len(files) == 2, (table, files)  # one per agent, as in raw
        t = lake.read_table("clean", table, clip_id=CLIP)
        assert t.num_rows == 0
    assert "anonymizer" in lake.read_table("clean", "camera_frames", clip_id=CLIP).column_names


def test_a_found_face_is_blurred_whole() -> None:
    """Real faces (two photos, whole face hand-labelled hairline to chin and ear to ear)
    pasted at 16-96 px into a street frame: every face the full-frame plan finds has at
    least 80 % of its whole face under the blur (the detector's box grown by the margin)."""
    import numpy as np

    from v2xlake.tasks.anonymize.blur import blur_boxes
    from v2xlake.tasks.anonymize.evaluate import blurred_share, match, synth_scene, whole_face

    cfg = AnonymizeConfig()
    det = build_detector(cfg)
    img, truth = synth_scene(3, 1280, 720, face_sizes=(16, 24, 32, 48, 64, 96))
    dets = [d for d in det.detect(img) if d.kind == "face"]
    done = blur_boxes(np.zeros_like(img), [d.box for d in dets], blur_config(cfg),
                      [d.kind for d in dets])
    found, _ = match(truth, dets)
    assert found.all()
    shares = [blurred_share(whole_face(t), done, img.shape) for t in truth]
    assert min(shares) >= 0.8, shares


def test_carrying_finds_what_detecting_every_frame_finds(tmp_path) -> None:
    """A 30 Hz simulated clip (640 px, 0.5 s): the default (key frames + carry) finds the
    visible faces from 16 px and plates from 20 px that detecting every frame finds (one
    object of slack: a box interpolated a pixel off can fall just under IoU 0.3), and the
    small faces (8-16 px, searched every frame) as often."""
    import pyarrow.parquet as pq

    from v2xlake.tasks.anonymize.evaluate import sim_hits
    from v2xlake.tasks.anonymize.stage import audit_detections
    from v2xlake.tasks.ingest import run_ingest
    from v2xlake.tasks.simulate import SimConfig, simulate

    clip = simulate(tmp_path / "clip", SimConfig.preset(
        "small", seed=0, seconds=0.5, camera_hz=30.0, image_width=640,
        cameras=("CAM_FRONT_NARROW", "CAM_FRONT_RIGHT", "CAM_BACK_RIGHT")))
    truth = pq.read_table(clip / "truth" / "boxes2d.parquet").to_pydict()
    lake = Lake(tmp_path / "lake")
    cid = run_ingest(lake, clip).clip_id
    found = {}
    for name, upd in (("every", {"carry": {"key_interval_ms": 0.0}}), ("carry", {})):
        run_anonymize(lake, cid, AnonymizeConfig(work={"workers": 1}, **upd))
        hits = sim_hits(truth, audit_detections(lake, cid))
        found[name] = (
            sum(h.found for h in hits if h.kind == "face" and h.size_px >= 16),
            sum(h.found for h in hits if h.kind == "plate" and h.size_px >= 20),
            sum(h.found for h in hits if h.kind == "face" and 8 <= h.size_px < 16))
    (f0, p0, s0), (f1, p1, s1) = found["every"], found["carry"]
    assert f0 + p0 >= 20, found
    assert f1 >= f0 - 1 and p1 >= p0 - 1 and s1 >= s0 - 1, found


def test_light_key_frames_search_plates_only_around_the_plates_found() -> None:
    """Every second key frame is light: its full key frame is the one before it. On a light
    key frame a vehicle face with a plate found by the full key frame is narrowed to the
    rectified part around the carried plate; a face without one, and heads, stay whole."""
    assert full_key_frames([True, False, True, False, True, True, False, True], 2) == [
        0, -1, 0, -1, 4, 4, -1, 7]
    assert full_key_frames([True, True, True], 1) == [0, 1, 2]

    def car(x: float, inst: str) -> Region:
        quad = ((x - 200, 500.0), (x + 200, 500.0), (x + 200, 700.0), (x - 200, 700.0))
        return Region("plate", (x - 200, 500, x + 200, 700), 104.0, inst, quad, (2.0, 1.0),
                      "rear", (x, 600.0))

    before = [car(400, "car-1"), car(1200, "car-2"), _head(1700)]
    here = [car(430, "car-1"), car(1230, "car-2"), _head(1730)]
    plate = Detection("plate", (350.0, 620.0, 450.0, 650.0), 0.9, "ppocr")
    out = plate_windows([plate], before, here, SHAPE)
    assert out[1:] == here[1:]  # car-2 (no plate found) and the head: whole
    sub = out[0]
    assert sub.kind == "plate" and sub.quad is not None and sub.size_m is not None
    # the plate moved with its face (+30 px), 0.4 m / 0.2 m of face around it (200 px / m)
    assert sub.box == pytest.approx((300.0, 580.0, 560.0, 690.0))
    assert sub.size_m == pytest.approx((1.3, 0.55))
    # no plate found: every region as it is
    assert plate_windows([], before, here, SHAPE) == here
