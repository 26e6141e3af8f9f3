"""Release builds: an immutable, versioned, checksummed selection of clips.

``build_release`` selects clips with a SQL predicate on the catalog's ``clips`` view,
assigns scene-level splits (:mod:`v2xlake.tasks.release_split`), copies the clips' clean-zone
Parquet files and blobs (format ``lake``, always the baseline) and runs the requested
exports (``v2xlake.tasks.export``), then writes release notes with statistics and plots, and
seals the release with ``checksums.json`` + ``SHA256SUMS``. Files are copied, never
linked, so later changes to the lake cannot reach into a release; an existing name is
refused. A local release is assembled under a hidden temporary directory and renamed into
place in one step; on S3 (no rename) ``SHA256SUMS`` is written last and a release without
it is incomplete.

``verify_release`` recomputes every checksum and reports any missing, changed or extra file
(hidden ones included). A build killed half-way leaves ``releases/.NAME.building-<owner>-*``,
which the next build's sweep removes (``Lake.sweep``).
"""

from __future__ import annotations

import datetime as dt
import hashlib
import io
import json
import os
import shutil
import tempfile
import uuid
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from prefect import flow, get_run_logger
from pydantic import BaseModel

from v2xlake.flows import bookkeeping
from v2xlake.storage.lake import Lake, checked_clip_id, run_tag
from v2xlake.tasks.export.exporters import EXPORTERS, FormatExporter
from v2xlake.tasks.release_split import SPLITS, SceneKey, SplitConfig, assign_splits, split_counts

SEAL_FILES = ("checksums.json", "SHA256SUMS")


class ReleaseError(RuntimeError):
    pass


def load_export(fmt: str) -> FormatExporter:
    """The exporter of a format name (``tasks.export.exporters.EXPORTERS``)."""
    if fmt not in EXPORTERS:
        raise ReleaseError(f"unknown export format {fmt!r}; known: lake, {', '.join(EXPORTERS)}")
    return EXPORTERS[fmt]


# ---------------------------------------------------------------- writing into a release
@dataclass
class ReleaseWriter:
    """Writes files under one release root and remembers their size and SHA-256."""

    lake: Lake
    root: str  # full path in lake.fs
    files: dict[str, dict[str, Any]] = field(default_factory=dict)

    def write(self, rel: str, data: bytes) -> None:
        rel = rel.strip("/")
        if rel in self.files:
            raise ReleaseError(f"{rel} written twice")
        self.lake.write_bytes(f"{self.root}/{rel}", data)
        self.files[rel] = {"sha256": hashlib.sha256(data).hexdigest(), "size": len(data)}

    def copy_from_lake(self, src: str, rel: str) -> None:
        self.write(rel, self.lake.read_bytes(src))

    def copy_tree(self, local_dir: Path, prefix: str) -> int:
        n = 0
        for f in sorted(p for p in Path(local_dir).rglob("*") if p.is_file()):
            self.write(f"{prefix}/{f.relative_to(local_dir).as_posix()}", f.read_bytes())
            n += 1
        return n


def _release_root(lake: Lake, name: str) -> str:
    return lake.path("releases", name)


def release_exists(lake: Lake, name: str) -> bool:
    root = _release_root(lake, name)
    return lake.exists(root) and bool(lake.list_files(root))


MAX_NAME_LEN = 100  # well under NAME_MAX (255) with the ``.NAME.building-<owner>-<id>`` staging


def check_release_name(name: str) -> None:
    """A release name is a single folder name: never ``..``, a path or a hidden name, and
    short enough that its staging folder name still fits the filesystem's limit (the
    privacy audit checks ``--release`` names with this too)."""
    import re

    if len(name) > MAX_NAME_LEN:
        raise ReleaseError(f"release name of {len(name)} characters: at most {MAX_NAME_LEN}")
    if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._\-]*", name) or ".." in name:
        raise ReleaseError(f"release name {name!r}: use letters, digits, '.', '_' and '-'")



def check_fractions(fractions: Sequence[float]) -> tuple[float, float, float]:
    """train/val/test fractions: three finite numbers in [0, 1] summing to 1. NaN slips
    through ``SplitConfig``'s sum check (every comparison with NaN is false), and inf or
    NaN would end up in release.json and the notes."""
    import math

    fr = tuple(float(f) for f in fractions)
    shown = ",".join(str(f) for f in fr)  # no brackets: the CLI prints through rich markup
    if len(fr) != 3 or not all(math.isfinite(f) and 0.0 <= f <= 1.0 for f in fr):
        raise ReleaseError(f"fractions {shown}: need three finite numbers from 0 to 1")
    if abs(sum(fr) - 1.0) > 1e-6:
        raise ReleaseError(f"fractions {shown} sum to {sum(fr)}, not 1")
    return fr[0], fr[1], fr[2]


# ---------------------------------------------------------------- steps
def select_scenes(lake: Lake, where: str) -> list[SceneKey]:
    """The clips a user predicate selects. The predicate is checked to be one expression over
    ``clips`` and runs on a read-only, locked-down connection (``Catalog.select_clips``);
    every clip id that comes back is checked before a path is built from it."""
    from v2xlake.storage.catalog import Catalog

    with Catalog(lake, read_only=True) as cat:
        rows = cat.select_clips(where, ["clip_id", "location", "weather", "lighting"])
    seen: dict[str, SceneKey] = {}
    for r in rows.to_pylist():
        cid = checked_clip_id(lake, str(r["clip_id"]))
        seen.setdefault(cid, SceneKey(cid, str(r["location"]), str(r["weather"]),
                                      str(r["lighting"])))
    return list(seen.values())


def copy_clean_zone(lake: Lake, writer: ReleaseWriter, clip_ids: Sequence[str]) -> int:
    """Format ``lake``: the selected clips' clean-zone tables and blobs, same layout."""
    clip_ids = [checked_clip_id(lake, c) for c in clip_ids]
    n = 0
    for table in lake.tables("clean"):
        for cid in clip_ids:
            src_dir = lake.table_dir("clean", table, cid)
            for f in lake.list_files(src_dir, ".parquet"):
                rel = f[len(lake.path("clean")):].strip("/")
                writer.copy_from_lake(f, f"lake/clean/{rel}")
                n += 1
    for cid in clip_ids:
        blob_dir = lake.path("clean", "blobs", cid)
        for f in lake.list_files(blob_dir):
            rel = f[len(lake.path("clean")):].strip("/")
            writer.copy_from_lake(f, f"lake/clean/{rel}")
            n += 1
    return n


def call_export(fmt: str, lake: Lake, clip_ids: Sequence[str], out_dir: Path,
                splits: dict[str, str] | None = None,
                config: BaseModel | None = None) -> dict[str, float]:
    """Run one export format over clips into a local folder; returns merged metrics."""
    exporter = load_export(fmt)
    reports = exporter.export(lake, list(clip_ids), out_dir,
                              config if config is not None else exporter.config_model(), splits)
    metrics: dict[str, float] = {}
    for rep in reports:
        for k, v in (rep.metrics or {}).items():
            metrics[k] = metrics.get(k, 0.0) + float(v) if len(reports) > 1 else float(v)
    return metrics


def run_export(lake: Lake, writer: ReleaseWriter, fmt: str, clip_ids: Sequence[str],
               splits: dict[str, str]) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix=f"v2xlake-{fmt}-") as tmp:
        metrics = call_export(fmt, lake, clip_ids, Path(tmp), splits)
        n = writer.copy_tree(Path(tmp), fmt)
    return {"format": fmt, "files": n, "metrics": metrics}


def _statistics(lake: Lake, clip_ids: Sequence[str]) -> dict[str, Any]:
    ids = ", ".join("'" + c.replace("'", "''") + "'" for c in clip_ids)
    stats: dict[str, Any] = {}
    stats["conditions"] = bookkeeping.query(
        lake, f"SELECT weather, lighting, count(*) AS clips FROM clips WHERE clip_id IN ({ids}) "
              "GROUP BY 1, 2 ORDER BY 1, 2").to_pylist()
    stats["locations"] = bookkeeping.query(
        lake, f"SELECT location, count(*) AS clips FROM clips WHERE clip_id IN ({ids}) "
              "GROUP BY 1 ORDER BY 1").to_pylist()
    try:
        stats["objects"] = bookkeeping.query(
            lake, "SELECT category, count(DISTINCT instance_id) AS objects, count(*) AS boxes "
                  f"FROM annotations WHERE clip_id IN ({ids}) GROUP BY 1 ORDER BY 2 DESC, 1"
        ).to_pylist()
        dist = bookkeeping.query(
            lake, "SELECT category, sqrt(cx * cx + cy * cy) AS distance_m FROM annotations "
                  f"WHERE clip_id IN ({ids})")
        stats["_distances"] = dist.to_pydict()
    except Exception as exc:  # no annotations table in this lake
        stats["objects"] = []
        stats["_distances"] = {"category": [], "distance_m": []}
        stats["objects_note"] = f"no annotations ({type(exc).__name__})"
    return stats


def _plots(stats: dict[str, Any]) -> dict[str, bytes]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    out: dict[str, bytes] = {}

    def save(fig: Any, name: str) -> None:
        buf = io.BytesIO()
        fig.tight_layout()
        # no timestamps in PNG metadata: a rebuild of the same selection gives the same bytes
        fig.savefig(buf, format="png", dpi=100, metadata={"Software": None})
        plt.close(fig)
        out[name] = buf.getvalue()

    objs = stats["objects"]
    fig, ax = plt.subplots(figsize=(6, 3.5))
    if objs:
        ax.barh([o["category"] for o in objs][::-1], [o["objects"] for o in objs][::-1])
    ax.set_xlabel("objects (distinct instances)")
    ax.set_title("Objects per class")
    save(fig, "plots/objects_per_class.png")

    d = stats["_distances"]
    cats = np.asarray(d["category"], dtype=object)
    dist = np.asarray(d["distance_m"], dtype=float)
    fig, ax = plt.subplots(figsize=(6, 3.5))
    if dist.size:
        bins = np.linspace(0.0, max(float(dist.max()), 1.0), 25)
        for c in sorted(set(cats.tolist())):
            ax.hist(dist[cats == c], bins=bins, density=True, histtype="step", label=str(c))  # type: ignore[arg-type]
        ax.legend(fontsize=7)
    ax.set_xlabel("distance from the agent's LiDAR [m]")
    ax.set_ylabel("density")
    ax.set_title("Distance density per class")
    save(fig, "plots/distance_density_per_class.png")

    cond = stats["conditions"]
    weathers = sorted({c["weather"] for c in cond})
    lightings = sorted({c["lighting"] for c in cond})
    grid = np.zeros((len(weathers), len(lightings)))
    for c in cond:
        grid[weathers.index(c["weather"]), lightings.index(c["lighting"])] = c["clips"]
    fig, ax = plt.subplots(figsize=(5, 3.5))
    ax.imshow(grid if grid.size else np.zeros((1, 1)), cmap="Blues")
    ax.set_xticks(range(len(lightings)), lightings)
    ax.set_yticks(range(len(weathers)), weathers)
    for i in range(len(weathers)):
        for j in range(len(lightings)):
            ax.text(j, i, str(int(grid[i, j])), ha="center", va="center")
    ax.set_title("Clips per weather x lighting")
    save(fig, "plots/clips_weather_lighting.png")
    return out


def _notes(meta: dict[str, Any], stats: dict[str, Any], exports: list[dict[str, Any]]) -> str:
    counts = meta["split_counts"]
    lines = [
        f"# Release {meta['name']}", "",
        f"Built {meta['created_utc']} from lake `{meta['lake']}`.", "",
        f"Selection: `SELECT clip_id FROM clips WHERE status = 'ok' AND ({meta['where']})`", "",
        f"{len(meta['clip_ids'])} clips (scenes); splits (seed {meta['seed']}, fractions "
        f"{'/'.join(str(f) for f in meta['fractions'])}): "
        + ", ".join(f"{s} {counts[s]}" for s in SPLITS), "",
        "| split | clips |", "|---|---|",
        *[f"| {s} | {', '.join(c for c, v in meta['splits'].items() if v == s) or '-'} |"
          for s in SPLITS], "",
        "## Conditions", "", "| weather | lighting | clips |", "|---|---|---|",
        *[f"| {c['weather']} | {c['lighting']} | {c['clips']} |" for c in stats["conditions"]],
        "", "| location | clips |", "|---|---|",
        *[f"| {c['location']} | {c['clips']} |" for c in stats["locations"]], "",
        "## Objects", "",
    ]
    if stats["objects"]:
        lines += ["| class | objects | boxes |", "|---|---|---|",
                  *[f"| {o['category']} | {o['objects']} | {o['boxes']} |"
                    for o in stats["objects"]]]
    else:
        lines.append(stats.get("objects_note", "no annotations"))
    lines += ["", "![objects per class](plots/objects_per_class.png)",
              "![distance density per class](plots/distance_density_per_class.png)",
              "![clips per weather x lighting](plots/clips_weather_lighting.png)", "",
              "## Contents", "", "| format | files |", "|---|---|",
              *[f"| {e['format']} | {e['files']} |" for e in exports], "",
              "Verify with `v2xlake release verify " + meta["name"] + "` (every file is listed "
              "with its SHA-256 in `SHA256SUMS` and `checksums.json`)."]
    return "\n".join(lines) + "\n"


def _seal(writer: ReleaseWriter) -> None:
    files = dict(sorted(writer.files.items()))
    sums = "".join(f"{v['sha256']}  {k}\n" for k, v in files.items())
    body = json.dumps({"algorithm": "sha256", "files": files}, indent=2, sort_keys=True)
    writer.lake.write_bytes(f"{writer.root}/checksums.json", body.encode())
    writer.lake.write_bytes(f"{writer.root}/SHA256SUMS", sums.encode())  # last: marks complete


# ---------------------------------------------------------------- build / verify
def build_release(lake_uri: str, name: str, where: str,
                  formats: Sequence[str] = ("lake",), seed: int = 0,
                  fractions: tuple[float, float, float] = (0.7, 0.15, 0.15)) -> dict[str, Any]:
    """Build release NAME; returns its release.json content. Refuses an existing name."""
    check_release_name(name)
    fractions = check_fractions(fractions)
    lake = Lake(lake_uri)
    lake.sweep()  # builds (and staging, temporary files) of killed runs
    if release_exists(lake, name):
        raise ReleaseError(f"release {name!r} already exists in {lake.uri}; releases are "
                           "immutable, pick a new name")
    fmts = list(dict.fromkeys(["lake", *[f for f in formats if f]]))
    for f in fmts:
        if f != "lake":
            load_export(f)  # fail before copying anything
    scenes = select_scenes(lake, where)
    if not scenes:
        raise ReleaseError(f"no clip matches: {where}")
    clip_ids = [s.clip_id for s in scenes]
    splits = assign_splits(scenes, SplitConfig(fractions=fractions, seed=seed))
    final_root = _release_root(lake, name)
    # the owner tag lets the next build's sweep remove this folder if this process dies
    staging = (lake.path("releases", f".{name}.building-{run_tag()}-{uuid.uuid4().hex[:8]}")
               if lake.is_local else final_root)
    writer = ReleaseWriter(lake, staging)
    try:
        exports = [{"format": "lake", "files": copy_clean_zone(lake, writer, clip_ids),
                    "metrics": {}}]
        for f in fmts:
            if f != "lake":
                exports.append(run_export(lake, writer, f, clip_ids, splits))
        stats = _statistics(lake, clip_ids)
        meta = {
            "name": name, "created_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
            "lake": lake.uri, "where": where, "clip_ids": clip_ids, "splits": splits,
            "split_counts": split_counts(splits), "seed": seed, "fractions": list(fractions),
            "formats": fmts, "exports": exports,
            "scenes": [s.__dict__ for s in scenes],
        }
        writer.write("splits.json", json.dumps(
            {s: sorted(c for c, v in splits.items() if v == s) for s in SPLITS},
            indent=2).encode())
        for rel, png in _plots(stats).items():
            writer.write(rel, png)
        public_stats = {k: v for k, v in stats.items() if not k.startswith("_")}
        writer.write("statistics.json", json.dumps(public_stats, indent=2, default=str).encode())
        writer.write("RELEASE.md", _notes(meta, stats, exports).encode())
        writer.write("release.json", json.dumps(meta, indent=2, default=str).encode())
        _seal(writer)
        if lake.is_local:
            if Path(final_root).exists() and any(Path(final_root).iterdir()):
                raise ReleaseError(f"release {name!r} appeared while building; not replacing it")
            if Path(final_root).exists():
                Path(final_root).rmdir()
            os.rename(staging, final_root)
    except BaseException:
        if lake.is_local:
            shutil.rmtree(staging, ignore_errors=True)
        raise
    return meta


@flow(name="release-build")
def release_build(lake: str, name: str, where: str, formats: list[str] | None = None,
                  seed: int = 0) -> dict[str, Any]:
    """Prefect flow around :func:`build_release` (the deployment's entry point)."""
    logger = get_run_logger()
    meta = build_release(lake, name, where, formats or ["lake"], seed)
    logger.info("release %s: %d clips %s", name, len(meta["clip_ids"]), meta["split_counts"])
    return {k: meta[k] for k in ("name", "clip_ids", "split_counts", "formats")}


@dataclass
class VerifyResult:
    name: str
    checked: int
    problems: list[str]

    @property
    def ok(self) -> bool:
        return not self.problems


def verify_release(lake_uri: str, name: str) -> VerifyResult:
    """Recompute every checksum; list missing, changed, unlisted files (empty list = intact)."""
    check_release_name(name)
    lake = Lake(lake_uri, create=False)
    root = _release_root(lake, name)
    if not lake.exists(f"{root}/SHA256SUMS") or not lake.exists(f"{root}/checksums.json"):
        return VerifyResult(name, 0, [f"release {name!r} is missing or incomplete "
                                      f"(no SHA256SUMS/checksums.json under {root})"])
    try:
        listed = _listed(lake.read_bytes(f"{root}/checksums.json"))
        sums: dict[str, str] = {}
        for line in lake.read_bytes(f"{root}/SHA256SUMS").decode("utf-8").splitlines():
            if line.strip():
                digest, _, rel = line.partition("  ")
                sums[rel] = digest
    except (ValueError, OSError) as e:  # JSONDecodeError and UnicodeDecodeError included
        return VerifyResult(name, 0, [f"release {name!r}: its seal cannot be read ({e})"])
    problems: list[str] = []
    if sums != {k: v["sha256"] for k, v in listed.items()}:
        problems.append("SHA256SUMS and checksums.json disagree")
    if lake.is_local:
        regular, links = _walk_local(root)
        problems += [f"{rel}: a symlink (a release is copied, never linked)" for rel in links]
        present = regular
    else:  # object stores have no links
        present = {f[len(root):].strip("/") for f in lake.list_files(root, hidden=True)}
    for rel in sorted(present - set(listed) - set(SEAL_FILES)):
        problems.append(f"{rel}: not listed in the release (added after build)")
    checked = 0
    for rel, want in sorted(listed.items()):
        path = f"{root}/{rel}"
        if rel not in present:
            if not (lake.is_local and rel in links):
                problems.append(f"{rel}: missing")
            continue
        data = lake.read_bytes(path)
        checked += 1
        if len(data) != want["size"]:
            problems.append(f"{rel}: size {len(data)} != {want['size']}")
        digest = hashlib.sha256(data).hexdigest()
        if digest != want["sha256"]:
            problems.append(f"{rel}: sha256 {digest[:12]}... != {want['sha256'][:12]}...")
    return VerifyResult(name, checked, problems)


def _listed(raw: bytes) -> dict[str, dict[str, Any]]:
    """``checksums.json``'s file table, checked for shape: a hand-edited or truncated seal
    is a verify problem, not a KeyError."""
    doc = json.loads(raw)
    files = doc.get("files") if isinstance(doc, dict) else None
    if not isinstance(files, dict):
        raise ValueError("checksums.json has no 'files' table")
    for rel, v in files.items():
        if not (isinstance(v, dict) and isinstance(v.get("sha256"), str)
                and isinstance(v.get("size"), int)):
            raise ValueError(f"checksums.json entry {rel!r} lacks sha256/size")
    return files


def _walk_local(root: str) -> tuple[set[str], list[str]]:
    """(regular files, symlinks) under a local release, relative to it. Links, to files or
    to folders, are listed and never followed: a release's promise is that its files are
    copies, and following a link to ``/`` would walk the whole machine (``/proc`` loops)."""
    files: set[str] = set()
    links: list[str] = []
    for d, dirs, names in os.walk(root, followlinks=False):
        for n in sorted(dirs + names):
            p = os.path.join(d, n)
            rel = os.path.relpath(p, root).replace(os.sep, "/")
            if os.path.islink(p):
                links.append(rel)
            elif n in names and os.path.isfile(p):
                files.add(rel)
    return files, sorted(links)


def list_releases(lake_uri: str) -> list[str]:
    lake = Lake(lake_uri)
    root = lake.path("releases")
    names = {f[len(root):].strip("/").split("/", 1)[0] for f in lake.list_files(root, "SHA256SUMS")}
    return sorted(n for n in names if not n.startswith("."))
