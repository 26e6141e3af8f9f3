"""A release's files: writing them with their checksums, the seal, publishing a local build
in one rename, verifying, listing, and the catalog statistics its notes show.

A release is ``releases/<name>/`` in the lake: copies (never links) of clean-zone files and
export outputs, ``checksums.json`` and ``SHA256SUMS`` (written last: the seal). The build
itself, which clips and which formats, is ``flows/release.py``.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from v2xlake.storage.lake import Lake, checked_clip_id

if TYPE_CHECKING:
    from v2xlake.storage.catalog import Catalog

SEAL_FILES = ("checksums.json", "SHA256SUMS")


class ReleaseError(RuntimeError):
    """A release that cannot be built or named as asked (the CLI shows the message)."""


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


def release_root(lake: Lake, name: str) -> str:
    return lake.path("releases", name)


def release_exists(lake: Lake, name: str) -> bool:
    root = release_root(lake, name)
    return lake.exists(root) and bool(lake.list_files(root))


MAX_NAME_LEN = 100  # well under NAME_MAX (255) with the ``.NAME.building-<owner>-<id>`` staging


def check_release_name(name: str) -> None:
    """A release name is a single folder name: never ``..``, a path or a hidden name, and
    short enough that its staging folder name still fits the filesystem's limit (the
    privacy audit checks ``--release`` names with this too)."""
    if len(name) > MAX_NAME_LEN:
        raise ReleaseError(f"release name of {len(name)} characters: at most {MAX_NAME_LEN}")
    if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._\-]*", name) or ".." in name:
        raise ReleaseError(f"release name {name!r}: use letters, digits, '.', '_' and '-'")



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


def release_statistics(lake: Lake, clip_ids: Sequence[str]) -> dict[str, Any]:
    """What the release notes tabulate and plot, from the catalog: clips per condition and
    location, objects per class, and the boxes' distances (``_distances``, for the plot
    only: keys starting with ``_`` stay out of statistics.json)."""
    from v2xlake.storage.catalog import Catalog

    with Catalog(lake, read_only=True) as cat:
        return _statistics(cat, clip_ids)


def _statistics(cat: Catalog, clip_ids: Sequence[str]) -> dict[str, Any]:
    ids = ", ".join("'" + c.replace("'", "''") + "'" for c in clip_ids)
    stats: dict[str, Any] = {}
    stats["conditions"] = cat.query(
        f"SELECT weather, lighting, count(*) AS clips FROM clips WHERE clip_id IN ({ids}) "
              "GROUP BY 1, 2 ORDER BY 1, 2").to_pylist()
    stats["locations"] = cat.query(
        f"SELECT location, count(*) AS clips FROM clips WHERE clip_id IN ({ids}) "
              "GROUP BY 1 ORDER BY 1").to_pylist()
    try:
        stats["objects"] = cat.query(
            "SELECT category, count(DISTINCT instance_id) AS objects, count(*) AS boxes "
                  f"FROM annotations WHERE clip_id IN ({ids}) GROUP BY 1 ORDER BY 2 DESC, 1"
        ).to_pylist()
        dist = cat.query(
            "SELECT category, sqrt(cx * cx + cy * cy) AS distance_m FROM annotations "
                  f"WHERE clip_id IN ({ids})")
        stats["_distances"] = dist.to_pydict()
    except Exception as exc:  # no annotations table in this lake
        stats["objects"] = []
        stats["_distances"] = {"category": [], "distance_m": []}
        stats["objects_note"] = f"no annotations ({type(exc).__name__})"
    return stats


def seal(writer: ReleaseWriter) -> None:
    """List every file written with its size and SHA-256 (``checksums.json``), then
    ``SHA256SUMS``, last: on an object store (no rename) a release without it is incomplete."""
    files = dict(sorted(writer.files.items()))
    sums = "".join(f"{v['sha256']}  {k}\n" for k, v in files.items())
    body = json.dumps({"algorithm": "sha256", "files": files}, indent=2, sort_keys=True)
    writer.lake.write_bytes(f"{writer.root}/checksums.json", body.encode())
    writer.lake.write_bytes(f"{writer.root}/SHA256SUMS", sums.encode())  # last: marks complete


def publish_local(staging: str, final_root: str, name: str) -> None:
    """Move a local release assembled in ``staging`` into place in one rename; refuses when
    a release of that name appeared meanwhile (releases are never replaced)."""
    final = Path(final_root)
    if final.exists() and any(final.iterdir()):
        raise ReleaseError(f"release {name!r} appeared while building; not replacing it")
    if final.exists():
        final.rmdir()
    os.rename(staging, final_root)


def discard_local(staging: str) -> None:
    """Remove a local release's staging folder after a failed build."""
    shutil.rmtree(staging, ignore_errors=True)


@dataclass
class VerifyResult:
    name: str
    checked: int
    problems: list[str]

    @property
    def ok(self) -> bool:
        return not self.problems


def verify(lake: Lake, name: str) -> VerifyResult:
    """Recompute every checksum; list missing, changed, unlisted files (empty list = intact)."""
    check_release_name(name)
    root = release_root(lake, name)
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


def list_releases(lake: Lake) -> list[str]:
    """The sealed releases of the lake (building ones, hidden, are not releases yet)."""
    root = lake.path("releases")
    names = {f[len(root):].strip("/").split("/", 1)[0] for f in lake.list_files(root, "SHA256SUMS")}
    return sorted(n for n in names if not n.startswith("."))
