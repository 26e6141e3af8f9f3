"""Anonymization: detectors on real photos, irreversible blur, clean PNGs, time and space."""

from __future__ import annotations

import itertools
import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pyarrow.compute as pc
import pytest

from tests.fixtures.real import requires_real_data
from v2xlake.tasks.anonymize.blur import BlurConfig, grow_box
from v2xlake.tasks.anonymize.detectors import (
    CenterFaceDetector,
    ClassicPlateDetector,
    FaceConfig,
    ScanConfig,
    UnionDetector,
)
from v2xlake.tasks.anonymize.evaluate import match, real_faces, synth_scene
from v2xlake.tasks.anonymize.images import (
    anonymize_array,
    encode_png,
    png_chunks,
    strip_png_metadata,
)
from v2xlake.tasks.anonymize.timespace import (
    T0_OFFSET_NS,
    clip_t0_abs,
    ins_to_ego_poses,
    shift_times,
)

REPO = Path(__file__).resolve().parents[1]
STREET = REPO.parent / "shared" / "data" / "real" / "images" / "street_plate_small_pjlab_0.png"
STREET_PLATE = (980.0, 629.0, 1006.0, 640.0)  # the one small (26 x 11 px) blue plate, found by eye


@pytest.fixture(scope="module")
def detector() -> UnionDetector:
    return UnionDetector([CenterFaceDetector(), ClassicPlateDetector()])


def hf_energy(img: np.ndarray) -> float:
    g = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY).astype(np.float64)
    return float(np.mean(cv2.Laplacian(g, cv2.CV_64F) ** 2))


def assert_only_boxes_changed(before: np.ndarray, after: np.ndarray, dets: list) -> None:
    """Pixels outside every detection's box grown by its kind's blur margins are unchanged."""
    mask = np.zeros(before.shape[:2], bool)
    for d in dets:
        x0, y0, x1, y1 = grow_box(d.box, before.shape, BlurConfig(), d.kind)
        mask[y0:y1, x0:x1] = True
    changed = np.any(before != after, axis=-1)
    assert not changed[~mask].any(), "pixels outside the blurred boxes changed"


@pytest.mark.parametrize("name", ["astronaut", "grace_hopper"])
def test_real_face_is_blurred_irreversibly(
    name: str, detector: UnionDetector, tmp_path: Path
) -> None:
    photo, face = real_faces()[name]
    out, dets = anonymize_array(photo, detector)
    cv2.imwrite(str(tmp_path / f"{name}_before.png"), photo)
    cv2.imwrite(str(tmp_path / f"{name}_after.png"), out)
    faces = [d for d in dets if d.kind == "face"]
    found, _ = match([("face", face)], faces)
    assert found.all()
    x0, y0, x1, y1 = (int(v) for v in face)
    drop = 1 - hf_energy(out[y0:y1, x0:x1]) / hf_energy(photo[y0:y1, x0:x1])
    assert drop > 0.9, f"high-frequency energy in the face dropped only {drop:.1%}"
    assert_only_boxes_changed(photo, out, dets)


@requires_real_data("images/street_plate_small_pjlab_0.png")
def test_real_street_small_plate(tmp_path: Path) -> None:
    img = cv2.imread(str(STREET))
    assert img is not None, STREET
    out, dets = anonymize_array(img, ClassicPlateDetector())
    cv2.imwrite(str(tmp_path / "street_before.png"), img)
    cv2.imwrite(str(tmp_path / "street_after.png"), out)
    found, _ = match([("plate", STREET_PLATE)], [d for d in dets if d.kind == "plate"])
    assert found.all(), "the 26 px plate on the real street image was missed"
    x0, y0, x1, y1 = (int(v) for v in STREET_PLATE)
    drop = 1 - hf_energy(out[y0:y1, x0:x1]) / hf_energy(img[y0:y1, x0:x1])
    assert drop > 0.9, f"plate detail dropped only {drop:.1%}"
    assert_only_boxes_changed(img, out, dets)


def test_recall_on_pasted_faces_and_rendered_plates(detector: UnionDetector) -> None:
    """Faces of 24-96 px and plates of 25-120 px wide: recall >= 0.95 at IoU >= 0.3."""
    found_all = []
    for seed in range(2):
        img, truth = synth_scene(
            seed, 1280, 720, face_sizes=(24, 32, 48, 64, 96), plate_widths=(25, 30, 40, 60, 90, 120)
        )
        found, _fp = match(truth, detector.detect(img))
        found_all.extend(found.tolist())
    assert np.mean(found_all) >= 0.95, found_all


def test_4k_small_faces_need_the_fine_pass() -> None:
    """Faces of 22-28 px on a 3840x2160 frame vanish in a 1280 px pass; the default finds them."""
    img, truth = synth_scene(7, 3840, 2160, face_sizes=(22, 28, 300), plate_widths=())
    small = [t for t in truth if t.size_px < 100]
    coarse = CenterFaceDetector(FaceConfig(scan=ScanConfig(max_side=1280, fine_scale=None)))
    found_coarse, _ = match(small, coarse.detect(img))
    native = CenterFaceDetector(FaceConfig(scan=ScanConfig(max_side=1920, fine_scale=1.0)))
    found, extra = match(truth, native.detect(img))
    assert not found_coarse.any()
    assert found.all() and extra == 0


def test_tiled_fine_pass_matches_whole_view() -> None:
    """Tiles (with objects on the seams) find the same faces as one whole native view."""
    img, truth = synth_scene(3, 1280, 720, face_sizes=(24, 40, 64, 96), plate_widths=())
    whole = CenterFaceDetector(FaceConfig(scan=ScanConfig(max_side=640, fine_scale=1.0)))
    tiled = CenterFaceDetector(
        FaceConfig(scan=ScanConfig(max_side=640, fine_scale=1.0, tile=384, tile_overlap=192))
    )
    f_whole, x_whole = match(truth, whole.detect(img))
    f_tiled, x_tiled = match(truth, tiled.detect(img))
    assert f_whole.all() and f_tiled.all()
    assert x_tiled == x_whole == 0


def test_png_output_has_no_metadata_chunks() -> None:
    img = np.full((8, 8, 3), 127, np.uint8)
    png = encode_png(img)
    # plant text and EXIF chunks before IEND, as a camera driver might
    chunks = png_chunks(png)

    def chunk(t: bytes, p: bytes) -> tuple[bytes, bytes]:
        return (t, p)

    planted = [
        *chunks[:-1],
        chunk(b"tEXt", b"Comment\x00GPS 31.23N 121.47E"),
        chunk(b"eXIf", b"MM\x00*"),
        chunk(b"tIME", struct.pack(">HBBBBB", 2024, 1, 2, 3, 4, 5)),
        chunks[-1],
    ]
    raw = b"\x89PNG\r\n\x1a\n" + b"".join(
        struct.pack(">I", len(p)) + t + p + struct.pack(">I", zlib.crc32(t + p) & 0xFFFFFFFF)
        for t, p in planted
    )
    clean = strip_png_metadata(raw)
    assert [t for t, _ in png_chunks(clean)] == [b"IHDR", b"IDAT", b"IEND"]
    decoded = cv2.imdecode(np.frombuffer(clean, np.uint8), cv2.IMREAD_UNCHANGED)
    assert decoded is not None and np.array_equal(decoded, img)
    assert {t for t, _ in png_chunks(png)} <= {b"IHDR", b"IDAT", b"IEND"}


def test_relative_time_and_local_enu() -> None:
    import pyarrow as pa

    from v2xlake.tasks.geodesy import LocalFrame

    t0 = 1_735_000_000_000_000_000
    tables = {
        "imu": pa.table({"t_ns": pa.array([t0 + 5, t0 + 9], pa.int64())}),
        "lidar_frames": pa.table(
            {
                "t_start_ns": pa.array([t0 + 2], pa.int64()),
                "stamp_ns": pa.array([t0 + 3], pa.int64()),
            }
        ),
    }
    assert clip_t0_abs(tables) == t0 + 2
    shifted = shift_times(tables["imu"], "imu", t0 + 2)
    assert shifted.column("t_ns").to_pylist() == [T0_OFFSET_NS + 3, T0_OFFSET_NS + 7]
    frame = LocalFrame(31.2, 121.5)
    ins = pa.table(
        {
            "t_ns": pa.array([t0 + 2, t0 + 8_000_002], pa.int64()),
            "lat": [31.2, 31.2001],
            "lon": [121.5, 121.5],
            "alt": [10.0, 10.0],
            "roll": [0.0, 0.0],
            "pitch": [0.0, 0.0],
            "azimuth": [0.0, np.pi / 2],
            "ve": [0.0, 1.0],
            "vn": [1.0, 0.0],
            "vu": [0.0, 0.0],
            "rtk_status": [2, 2],
        }
    )
    ego = ins_to_ego_poses(ins, frame, t0 + 2)
    assert ego.column("t_ns").to_pylist() == [T0_OFFSET_NS, T0_OFFSET_NS + 8_000_000]
    x, y, z = (ego.column(c).to_numpy() for c in "xyz")
    assert abs(x[0]) < 1e-6 and abs(y[0]) < 1e-6 and abs(z[0] - 10.0) < 1e-6
    assert 11.0 < y[1] < 11.2 and abs(x[1]) < 1e-3  # 1e-4 deg of latitude ~ 11.09 m north
    # azimuth 0 (north) -> body x along +y: yaw +90 deg; azimuth 90 (east) -> identity
    q = np.stack([ego.column(c).to_numpy() for c in ("qw", "qx", "qy", "qz")], -1)
    assert np.allclose(q[0], [np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)], atol=1e-9)
    assert np.allclose(np.abs(q[1]), [1, 0, 0, 0], atol=1e-5)
    assert np.allclose(
        [ego.column("vx")[0].as_py(), ego.column("vy")[0].as_py()], [0, 1], atol=1e-9
    )
    assert pc.min(ego.column("t_ns")).as_py() == T0_OFFSET_NS


def test_free_text_times_become_relative() -> None:
    from v2xlake.tasks.anonymize.timespace import relative_number, relative_text

    t0 = 1_700_000_000_000_000_000
    text = "late [+0.100 s] (abs 1700000000000000000..1700000000900000000 ns) at 1700000000.25 s"
    out = relative_text(text, t0)
    assert out == "late [+0.100 s] (abs 100000000..1000000000 ns) at 0.35 s"
    assert relative_number(1_700_000_000_500_000.0, t0) == 600_000.0  # microseconds
    assert relative_number(42.0, t0) == 42.0
    assert relative_text("frame 000123 sha 12ab1700000000000000000cd", t0).endswith("cd")


def test_scan_plan_scales_with_the_image() -> None:
    """The full-frame plan: a cheap coarse pass + equal x2 tiles on every frame size (640 px
    cameras have 16 px faces too); ``face_upscale_min_side`` can spare small frames."""
    from v2xlake.tasks.anonymize.build import full_face_scan
    from v2xlake.tasks.anonymize.config import AnonymizeConfig
    from v2xlake.tasks.anonymize.detectors import scan_plan

    scan = full_face_scan(AnonymizeConfig())
    small = scan_plan(360, 640, scan)
    assert [(p.scale, p.tiles) for p in small] == [
        (0.5, ((0, 0, 320, 180),)), (2.0, ((0, 0, 1280, 720),))]
    native = scan_plan(360, 640, full_face_scan(AnonymizeConfig(faces={"upscale_min_side": 1280})))
    assert [(p.scale, p.tiles) for p in native] == [(1.0, ((0, 0, 640, 360),))]
    for h, w, n_tiles in ((1080, 1920, 4), (2160, 3840, 12)):
        coarse, fine = scan_plan(h, w, scan)
        assert coarse.scale == 0.5 and len(coarse.tiles) == 1
        assert fine.scale == 2.0 and len(fine.tiles) == n_tiles
        sizes = {(x1 - x0, y1 - y0) for x0, y0, x1, y1 in fine.tiles}
        assert len(sizes) == 1  # one input size: one cached net
        tw, th = sizes.pop()
        assert tw <= scan.tile and th <= scan.tile and tw % 32 == 0 and th % 32 == 0
        covered = np.zeros((fine.height, fine.width), bool)
        for x0, y0, x1, y1 in fine.tiles:
            covered[y0:y1, x0:x1] = True
        assert covered.all()
        xs = sorted({t[0] for t in fine.tiles})
        assert all(b - a <= tw - scan.tile_overlap for a, b in itertools.pairwise(xs))
