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

This module is the orchestration only: the release's files (writer, seal, publish, verify,
list, the catalog statistics) are ``storage/releases.py``, its notes and figures
``tasks/release_notes.py``.
"""

from __future__ import annotations

import datetime as dt
import json
import tempfile
import uuid
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from prefect import flow, get_run_logger
from pydantic import BaseModel

from v2xlake.storage.lake import Lake, checked_clip_id, run_tag
from v2xlake.storage.releases import (
    MAX_NAME_LEN,
    SEAL_FILES,
    ReleaseError,
    ReleaseWriter,
    VerifyResult,
    check_release_name,
    copy_clean_zone,
    discard_local,
    publish_local,
    release_exists,
    release_root,
    release_statistics,
    seal,
    verify,
)
from v2xlake.storage.releases import list_releases as _list_releases
from v2xlake.tasks import release_notes
from v2xlake.tasks.export.exporters import EXPORTERS, FormatExporter
from v2xlake.tasks.release_split import SPLITS, SceneKey, SplitConfig, assign_splits, split_counts


def load_export(fmt: str) -> FormatExporter:
    """The exporter of a format name (``tasks.export.exporters.EXPORTERS``)."""
    if fmt not in EXPORTERS:
        raise ReleaseError(f"unknown export format {fmt!r}; known: lake, {', '.join(EXPORTERS)}")
    return EXPORTERS[fmt]


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


# ---------------------------------------------------------------- build / verify
def build_release(lake_uri: str, name: str, where: str,
                  formats: Sequence[str] = ("lake",), seed: int = SplitConfig().seed,
                  fractions: tuple[float, float, float] = SplitConfig().fractions
                  ) -> dict[str, Any]:
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
    final_root = release_root(lake, name)
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
        stats = release_statistics(lake, clip_ids)
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
        for rel, png in release_notes.plots(stats).items():
            writer.write(rel, png)
        public_stats = {k: v for k, v in stats.items() if not k.startswith("_")}
        writer.write("statistics.json", json.dumps(public_stats, indent=2, default=str).encode())
        writer.write("RELEASE.md", release_notes.notes(meta, stats, exports).encode())
        writer.write("release.json", json.dumps(meta, indent=2, default=str).encode())
        seal(writer)
        if lake.is_local:
            publish_local(staging, final_root, name)
    except BaseException:
        if lake.is_local:
            discard_local(staging)
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


def verify_release(lake_uri: str, name: str) -> VerifyResult:
    """Recompute every checksum of release NAME (``storage.releases.verify``)."""
    check_release_name(name)
    return verify(Lake(lake_uri, create=False), name)


def list_releases(lake_uri: str) -> list[str]:
    """The sealed releases of the lake at ``lake_uri``."""
    return _list_releases(Lake(lake_uri))


# re-exported: the CLI and tests import them from here
__all__ = ["MAX_NAME_LEN", "SEAL_FILES", "ReleaseError", "ReleaseWriter", "VerifyResult",
           "build_release", "call_export", "check_fractions", "check_release_name",
           "copy_clean_zone", "list_releases", "load_export", "release_build",
           "select_scenes", "verify_release"]
