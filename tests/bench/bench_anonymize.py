"""Anonymization benchmark: recall vs object size, real images, and speed against ``deface``.

Run: ``python tests/bench/bench_anonymize.py [--quick]``. Everything runs on one core
(``cv2.setNumThreads(1)`` here, ``taskset -c 0`` for the deface command line) so the figures
are images per second per core.

Recall: real faces (scikit-image astronaut, matplotlib grace_hopper) pasted at several face
heights and simulator-style plates at several widths into rendered street frames; a true box
is found when a detection of its kind has IoU >= 0.3. Also the real street photo's 26 px
plate and the two full photos.

Speed: our pipeline (decode PNG, detect faces + plates, blur, encode PNG without metadata)
against the ``deface`` command line on the same PNG frames (its default: CenterFace at full
resolution, face blur only). If the deface CLI cannot run, deface's ``CenterFace`` class and
an equivalent blur loop are timed in-process instead, and the output says so.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

from v2xlake.tasks.anonymize.detectors import (  # noqa: E402
    CenterFaceDetector,
    ClassicPlateConfig,
    ClassicPlateDetector,
    Detector,
    FaceConfig,
    HaarPlateConfig,
    HaarPlateDetector,
    ScanConfig,
)
from v2xlake.tasks.anonymize.evaluate import match, real_faces, synth_scene  # noqa: E402
from v2xlake.tasks.anonymize.images import anonymize_png  # noqa: E402
from v2xlake.tasks.anonymize.run import AnonymizeConfig  # noqa: E402

STREET = REPO.parent / "shared" / "data" / "real" / "images" / "street_plate_small_pjlab_0.png"
STREET_PLATE = (980.0, 629.0, 1006.0, 640.0)
FACE_SIZES = (12, 16, 20, 24, 32, 48, 64, 96, 128)
PLATE_WIDTHS = (16, 20, 25, 30, 40, 60, 90, 140, 200)


def recall_table(name: str, det, kind: str, sizes, seeds, w: int, h: int) -> None:
    hits: dict[tuple[str, float], list[bool]] = {}
    fps, t_total, n_img = 0, 0.0, 0
    for seed in seeds:
        kw = {"face_sizes": sizes} if kind == "face" else {"plate_widths": sizes}
        img, truth = synth_scene(seed, w, h, **kw)
        t = time.perf_counter()
        dets = [d for d in det.detect(img) if d.kind == kind]
        t_total += time.perf_counter() - t
        n_img += 1
        found, fp = match(truth, dets)
        fps += fp
        for tb, f in zip(truth, found, strict=True):
            hits.setdefault((tb.source, tb.size_px), []).append(bool(f))
    sources = sorted({s for s, _ in hits})
    print(
        f"\n{name} ({kind}, {w}x{h}, {len(seeds)} frames, {t_total / n_img:.2f} s/frame, "
        f"{fps / n_img:.1f} unmatched boxes/frame)"
    )
    print("  size px  " + "  ".join(f"{s:>13}" for s in sources) + "   all")
    for size in sizes:
        row = [hits.get((s, float(size)), []) for s in sources]
        allv = [v for r in row for v in r]
        cells = "  ".join(f"{np.mean(r):>13.2f}" if r else f"{'-':>13}" for r in row)
        print(f"  {size:>7}  {cells}  {np.mean(allv):.2f}")


def real_images(detectors: dict) -> None:
    print("\nReal photos (found at IoU >= 0.3; detections elsewhere counted as extra boxes)")
    street = cv2.imread(str(STREET))
    for name, det in detectors.items():
        cells = []
        for pname, (photo, face) in real_faces().items():
            ds = det.detect(photo)
            f, fp = match([("face", face)], [d for d in ds if d.kind == "face"])
            pl = sum(d.kind == "plate" for d in ds)
            cells.append(
                f"{pname}: face {'found' if f.all() else 'MISSED'} (+{fp} face, +{pl} plate boxes)"
            )
        if street is not None:
            ds = det.detect(street)
            plates = [d for d in ds if d.kind == "plate"]
            f, fp = match([("plate", STREET_PLATE)], plates)
            best = max((d for d in plates), key=lambda d: _iou(d.box, STREET_PLATE), default=None)
            cells.append(
                f"street 26px plate: {'found' if f.all() else 'MISSED'}"
                f"{f' (IoU {_iou(best.box, STREET_PLATE):.2f})' if best else ''}, "
                f"{fp} other plate boxes"
            )
        print(f"  {name}: " + "; ".join(cells))


REAL = REPO.parent / "shared" / "data" / "real"


def real_plates() -> None:
    """Plate detectors on real photos: plates_eu (108 labelled plates; other plates in a photo
    may be unlabelled, so only recall counts) and the labelled street images (recall, false
    plate blurs per image and as a share of the image area)."""
    from v2xlake.tasks.anonymize.evaluate import plates_eu, score_real, street_images
    from v2xlake.tasks.anonymize.textplate import TextPlateConfig, TextPlateDetector

    variants: dict[str, Detector] = {
        "text-plate (PP-OCRv4 DB, native; default)": TextPlateDetector(),
        "text-plate, min aspect 1.3 (two-row plates)": TextPlateDetector(
            TextPlateConfig(min_aspect=1.3)
        ),
        "classic-plate": ClassicPlateDetector(),
    }
    sets = {"plates_eu": plates_eu(REAL / "plates_eu") if (REAL / "plates_eu").is_dir() else [],
            "street": street_images(REAL / "images") if (REAL / "images").is_dir() else []}
    print("\nPlates on real photos (IoU >= 0.3)")
    for name, det in variants.items():
        for sname, items in sets.items():
            if not items:
                continue
            t = time.perf_counter()
            s = score_real(items, det.detect, kinds=("plate",))
            ms = (time.perf_counter() - t) / len(items) * 1000
            print(f"  {name} on {sname}: recall {s.recall:.3f} ({s.n_found}/{s.n_true}), "
                  f"{s.false_per_image:.2f} {'extra' if sname == 'plates_eu' else 'false'} "
                  f"boxes/image, false area mean {100 * np.mean(s.false_area):.2f} % "
                  f"max {100 * max(s.false_area):.2f} %, {ms:.0f} ms/image; missed {s.missed[:6]}")


def _iou(a, b) -> float:
    from v2xlake.tasks.geometry import iou_xyxy as iou_matrix

    return float(iou_matrix(np.array(a), np.array(b))[0, 0])


def write_frames(folder: Path, w: int, h: int, n: int) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i in range(n):
        img, _ = synth_scene(
            1000 + i, w, h, face_sizes=(24, 40, 80, 160), plate_widths=(40, 90, 160)
        )
        p = folder / f"frame_{i:03d}.png"
        cv2.imwrite(str(p), img)
        paths.append(p)
    return paths


def time_ours(paths: list[Path], cfg: AnonymizeConfig) -> float:
    det = cfg.build_detector()
    blur = cfg.blur()
    anonymize_png(paths[0].read_bytes(), det, blur)  # warm-up (net planning)
    t = time.perf_counter()
    for p in paths:
        anonymize_png(p.read_bytes(), det, blur, cfg.png_compression)
    return len(paths) / (time.perf_counter() - t)


def time_deface_cli(paths: list[Path]) -> float | None:
    exe = shutil.which("deface") or str(Path(sys.executable).parent / "deface")
    if not os.path.exists(exe):
        return None
    cmd = (
        ["taskset", "-c", "0", exe, "--backend", "opencv"]
        if shutil.which("taskset")
        else [exe, "--backend", "opencv"]
    )

    def run(files: list[Path]) -> float:
        """One process for all inputs (startup paid once); outputs land next to the inputs."""
        t = time.perf_counter()
        r = subprocess.run([*cmd, *map(str, files)], capture_output=True, text=True)
        if r.returncode != 0:
            raise RuntimeError(r.stderr[-500:])
        return time.perf_counter() - t

    try:
        t1 = run(paths[:1])  # startup + one frame
        tn = run(paths)
    except (RuntimeError, OSError) as e:
        print(f"  deface CLI failed: {e}")
        return None
    per = (tn - t1) / max(len(paths) - 1, 1)
    return 1.0 / per if per > 0 else None


def time_deface_inprocess(paths: list[Path]) -> float:
    """deface's CenterFace (OpenCV backend, full resolution, thr 0.2) + its box-blur loop."""
    from deface.centerface import CenterFace

    cf = CenterFace(in_shape=None, backend="opencv")

    def one(p: Path) -> None:
        img = cv2.imread(str(p))
        assert img is not None
        frame = img[:, :, ::-1].copy()
        dets, _ = cf(frame, threshold=0.2)
        for d in dets:
            x1, y1, x2, y2 = d[:4].astype(int)
            h, w = y2 - y1, x2 - x1
            x1, y1 = max(0, int(x1 - 0.15 * w)), max(0, int(y1 - 0.15 * h))
            x2, y2 = (
                min(frame.shape[1] - 1, int(x2 + 0.15 * w)),
                min(frame.shape[0] - 1, int(y2 + 0.15 * h)),
            )
            if x2 > x1 and y2 > y1:
                frame[y1:y2, x1:x2] = cv2.blur(
                    frame[y1:y2, x1:x2], (max(1, (x2 - x1) // 2), max(1, (y2 - y1) // 2))
                )
        cv2.imwrite(str(p.with_suffix(".anon.png")), frame[:, :, ::-1])

    one(paths[0])
    t = time.perf_counter()
    for p in paths:
        one(p)
    return len(paths) / (time.perf_counter() - t)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="fewer frames")
    ap.add_argument("--sim", type=Path, help="only: recall on this simulated clip folder")
    ap.add_argument("--every", type=int, default=1, help="with --sim: every n-th image")
    ap.add_argument("--speed", action="store_true", help="only the speed comparison")
    ap.add_argument("--real", action="store_true", help="only the real labelled photos")
    args = ap.parse_args()
    if args.real:
        cv2.setNumThreads(1)
        real_plates()
        return
    if args.sim:
        sim_recall(args.sim, args.every)
        return
    cv2.setNumThreads(1)
    if args.speed:
        speed(args.quick)
        return
    seeds = range(2) if args.quick else range(4)

    # ---------------------------------------------------------------- recall
    face_variants: dict[str, Detector] = {
        "centerface coarse 1280 only": CenterFaceDetector(FaceConfig(scan=ScanConfig(1280, None))),
        "centerface coarse 1920 + native fine pass (default)": CenterFaceDetector(
            FaceConfig(scan=ScanConfig())
        ),
        "centerface coarse 1920 + fine pass x2 in 640 tiles": CenterFaceDetector(
            FaceConfig(scan=ScanConfig(1920, 2.0, 640, 128))
        ),
    }
    for name, det in face_variants.items():
        recall_table(name, det, "face", FACE_SIZES, seeds, 1920, 1080)
    recall_table(
        "centerface default on 4K",
        face_variants["centerface coarse 1920 + native fine pass (default)"],
        "face",
        FACE_SIZES,
        range(1),
        3840,
        2160,
    )
    plate_variants: dict[str, Detector] = {
        "classic-plate (default, no upscale)": ClassicPlateDetector(),
        "classic-plate x2 upscale": ClassicPlateDetector(ClassicPlateConfig(upscale=2.0)),
        "classic-plate + tiny-plate rule": ClassicPlateDetector(
            ClassicPlateConfig(tiny_plates=True)
        ),
        "haar russian_plate_number": HaarPlateDetector(),
        "haar license_plate_rus_16stages": HaarPlateDetector(
            HaarPlateConfig(cascade="haarcascade_license_plate_rus_16stages.xml")
        ),
    }
    for name, det in plate_variants.items():
        recall_table(name, det, "plate", PLATE_WIDTHS, seeds, 1920, 1080)
    real_images(
        {
            "default (centerface + classic-plate)": AnonymizeConfig().build_detector(),
            **{k: v for k, v in plate_variants.items() if k.startswith("haar")},
        }
    )

    speed(args.quick)


def speed(quick: bool) -> None:
    print("\nSpeed, one core (images/s), our default pipeline vs deface on the same PNG frames")
    n = 3 if quick else 6
    with tempfile.TemporaryDirectory() as tmp:
        for w, h in ((640, 360), (1920, 1080), (3840, 2160)):
            paths = write_frames(Path(tmp) / f"{w}", w, h, n)
            cli = time_deface_cli(paths)
            ref, how = (
                (cli, "deface CLI")
                if cli
                else (time_deface_inprocess(paths), "deface CenterFace in-process")
            )
            print(f"  {w}x{h}: {how} {ref:.3f} img/s (full-resolution CenterFace, faces only)")
            variants = {
                "default (faces x2 fine pass + plates)": AnonymizeConfig(),
                "default, faces only": AnonymizeConfig(plate_detector="none"),
                "fast (native pass) + plates": AnonymizeConfig(face_fine_scale=1.0, face_tile=0),
                "fast, faces only": AnonymizeConfig(
                    face_fine_scale=1.0, face_tile=0, plate_detector="none"
                ),
            }
            for vname, cfg in variants.items():
                ips = time_ours(paths, cfg)
                print(f"    ours {vname}: {ips:.3f} img/s, ratio to deface {ips / ref:.2f}")


# -------------------------------------------------------------------- simulator clips
def sim_recall(clip_dir: Path, every: int = 1, workers: int = 2) -> None:
    """Recall on a simulated clip's visible face/plate boxes (truth/boxes2d.parquet), per size
    bin and on the documented reliable population (``evaluate.FACE_MIN_PX_*``, ``PLATE_MIN_PX``).

    The clip is ingested into a temporary lake with the project's ingest stage (so the images
    are exactly what the anonymizer sees), then the default detector runs on every ``every``-th
    image; truth and images are matched by (agent, camera, stamp); ``occluded`` truth is left
    out (a person could not identify it either).
    """
    from concurrent.futures import ThreadPoolExecutor

    import pyarrow.parquet as pq

    from v2xlake.storage.lake import Lake
    from v2xlake.tasks.anonymize.detectors import scan_plan
    from v2xlake.tasks.anonymize.evaluate import (
        PLATE_MIN_PX,
        face_min_px,
        lake_image_keys,
        recall_by_size,
        sim_hits,
    )
    from v2xlake.tasks.anonymize.images import decode_image, to_bgr8
    from v2xlake.tasks.ingest import run_ingest

    truth = pq.read_table(clip_dir / "truth" / "boxes2d.parquet").to_pydict()
    cfg = AnonymizeConfig()
    det = cfg.build_detector()
    scan = det.detectors[0].config.scan  # type: ignore[attr-defined]
    with tempfile.TemporaryDirectory() as tmp:
        lake = Lake(tmp)
        clip = run_ingest(lake, clip_dir).clip_id
        keys = sorted(lake_image_keys(lake, clip).items())[::every]
        finest: dict[tuple[str, str, int], float] = {}

        def one(item: tuple) -> tuple:
            key, (blob, _f) = item
            img = to_bgr8(decode_image(lake.read_blob("raw", blob)))
            finest[key] = max(p.scale for p in scan_plan(img.shape[0], img.shape[1], scan))
            return key, det.detect(img)

        t = time.perf_counter()
        with ThreadPoolExecutor(workers) as pool:
            dets = dict(pool.map(one, keys))
        dt = time.perf_counter() - t
    hits = sim_hits(truth, dets)
    print(f"\nSimulator clip {clip_dir.name}: {len(dets)} images in {dt:.0f} s ({workers} threads)")
    for kind in ("face", "plate"):
        for label, n, r in recall_by_size(hits, kind):
            print(f"  {kind} {'height' if kind == 'face' else 'width'} {label} px: {r:.2f} ({n})")
    pop = [
        h
        for h in hits
        if (h.kind == "face" and h.size_px >= face_min_px(finest[(h.agent, h.camera, h.stamp_ns)]))
        or (h.kind == "plate" and h.size_px >= PLATE_MIN_PX)
    ]
    for kind in ("face", "plate"):
        v = [h.found for h in pop if h.kind == kind]
        if v:
            print(f"  reliable population {kind}: recall {np.mean(v):.3f} ({sum(v)}/{len(v)})")
    if pop:
        print(f"  reliable population overall: recall {np.mean([h.found for h in pop]):.3f}")


if __name__ == "__main__":
    main()
