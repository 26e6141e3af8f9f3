"""Per-clip, per-stage manifests: what went in, which code and parameters ran, what came out.

One JSON file per clip and stage at ``manifests/<clip_id>/<stage>.json`` (written atomically).
A stage is *current* when its last run finished, and the three hashes of its key are unchanged:

- ``inputs_hash``: for ingest, the checksum (``storage.checksum``) of every input file (bags,
  clip.yaml, .msg files, annotation file); for later stages, the hash of the upstream
  stages' recorded outputs (their checksums). A stage that re-runs and produces different
  bytes therefore changes the key of every stage after it, and only of those: changing
  deskew's parameters re-runs deskew, register, align... but not ingest or qa.
- ``code_version``: package version + hash of the stage's own source files (and schemas/).
- ``params_hash``: sha256 of the stage config's canonical JSON.

Output files are checked to still exist, so deleting a table re-runs the stage that made it.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.util
import json
import os
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any

from pydantic import BaseModel, Field

from v2xlake.schemas.registry import STAGE_PACKAGES
from v2xlake.schemas.stage import OutputFile, StageReport
from v2xlake.schemas.tables import ManifestRow
from v2xlake.storage import checksum
from v2xlake.storage.lake import Lake
from v2xlake.storage.statcache import file_checksum


def _package_root() -> Path:
    """The ``v2xlake`` folder the import system uses (checkout, editable install or wheel
    alike); file names in a code hash are relative to the folder above it."""
    spec = importlib.util.find_spec("v2xlake")
    if spec is None or not spec.submodule_search_locations:
        raise RuntimeError("the v2xlake package cannot be found by the import system")
    return Path(next(iter(spec.submodule_search_locations))).resolve()


PACKAGE_ROOT = _package_root()

# The module of each stage; its source and every project module it imports (transitively,
# ``tasks.*`` and ``schemas.*``) make the stage's code version, so editing a helper that a
# stage uses re-runs that stage, and editing another stage's code does not. The standard
# stages come from the one stage list (schemas/registry.py); for a stage an entry point adds,
# see ``_added_stage_paths``.
STAGE_MODULES: dict[str, str] = {
    **{package.rpartition(".")[2]: package for package in STAGE_PACKAGES},
    "export": "v2xlake.tasks.export",
}
CODE_PACKAGES = ("v2xlake.tasks", "v2xlake.schemas")


@dataclass(frozen=True)
class StageKey:
    """Everything that decides whether a stage's recorded result is still valid."""

    stage: str
    code_version: str
    params_hash: str
    inputs_hash: str
    inputs: tuple[tuple[str, str], ...] = ()  # (name, checksum) detail for the manifest
    params: dict[str, Any] | None = None  # the effective parameters, recorded for people


class Manifest(BaseModel):
    """Contents of ``manifests/<clip>/<stage>.json``; ``to_row()`` gives the catalog row."""

    clip_id: str
    stage: str
    status: str  # done | not_applicable | failed
    reason: str | None = None  # why a stage was not applicable
    code_version: str
    params_hash: str
    params: dict[str, Any] = Field(default_factory=dict)  # effective values of this run
    inputs_hash: str
    inputs: dict[str, str] = Field(default_factory=dict)
    outputs: list[OutputFile] = Field(default_factory=list)
    metrics: dict[str, float] = Field(default_factory=dict)
    notes: list[str] = Field(default_factory=list)
    error: str | None = None
    recorded_at: str = ""

    def to_row(self) -> ManifestRow:
        return ManifestRow(
            clip_id=self.clip_id, stage=self.stage, status=self.status,
            code_version=self.code_version, params_hash=self.params_hash,
            inputs_hash=self.inputs_hash,
            outputs=json.dumps([o.model_dump() for o in self.outputs]), error=self.error)


# --------------------------------------------------------------------------- hashing
def lake_file_checksum(lake: Lake, path: str) -> str:
    with lake.fs.open_input_stream(path) as f:
        return checksum.of_stream(f)


def _params_data(config: Any) -> Any:
    if isinstance(config, BaseModel):
        return config.model_dump(mode="json")
    return {} if config is None else config


def params_hash(config: Any) -> str:
    """sha256 of the config's canonical JSON (pydantic model, dataclass-like or plain data)."""
    data = _params_data(config)
    text = json.dumps(data, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()


@functools.cache
def package_version() -> str:
    try:
        return metadata.version("v2xlake")
    except metadata.PackageNotFoundError:
        return "0+unknown"


def _code_files(paths: Iterable[str | Path]) -> list[Path]:
    files: list[Path] = []
    for p in paths:
        p = Path(p)
        p = p if p.is_absolute() else PACKAGE_ROOT.parent / p
        if p.is_dir():
            files.extend(f for f in p.rglob("*") if f.suffix in (".py", ".msg") and f.is_file())
        elif p.is_file():
            files.append(p)
    return sorted(set(files))


def code_hash(paths: Iterable[str | Path]) -> str:
    """Hash of every ``.py`` (and ``.msg``) file under the given files/folders, by relative path."""
    return _hash_files(_code_files(paths))


def _hash_files(files: Iterable[Path]) -> str:
    h = hashlib.sha256()
    for f in files:
        top = PACKAGE_ROOT.parent
        rel = f.relative_to(top).as_posix() if f.is_relative_to(top) else f.name
        h.update(rel.encode() + b"\0" + f.read_bytes() + b"\0")
    return h.hexdigest()[:16]


def _module_file(name: str) -> Path | None:
    """The source file of module ``name`` under the package folder the import system found
    (``PACKAGE_ROOT``); nothing is imported, so a name below a module (``pkg.mod.func``)
    simply has no file."""
    top, _, rest = name.partition(".")
    if top != PACKAGE_ROOT.name:
        return None
    base = PACKAGE_ROOT.joinpath(*rest.split(".")) if rest else PACKAGE_ROOT
    for cand in (base.with_suffix(".py"), base / "__init__.py"):
        if cand.is_file():
            return cand
    return None


def module_closure(module: str) -> list[Path]:
    """Source files of ``module`` and of every ``tasks.*`` / ``schemas.*`` module it imports,
    transitively (static: parsed with ``ast``, nothing is imported)."""
    import ast

    seen: dict[str, Path] = {}
    todo = [module]
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        path = _module_file(name)
        if path is None:
            continue
        seen[name] = path
        if path.name == "__init__.py" and "." in name:  # a stage package: all its modules
            todo.extend(f"{name}.{p.stem}" for p in path.parent.glob("*.py")
                        if p.name != "__init__.py")
        for node in ast.walk(ast.parse(path.read_text())):
            names: list[str] = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
            todo.extend(n for n in names if n.startswith(CODE_PACKAGES))
    return sorted(set(seen.values()))


def _added_stage_paths(stage: str) -> list[str | Path]:
    """The code of a stage that a package outside the standard list adds (an entry point,
    ``schemas.registry``): its package's folder and the schemas it is written against.
    Without the folder, editing that stage would not re-run it. An unknown name: the
    schemas only."""
    from v2xlake.schemas.registry import stage_packages

    package = stage_packages().get(stage)
    spec = importlib.util.find_spec(package) if package else None
    folders = list(spec.submodule_search_locations or ()) if spec else []
    return [*(Path(f) for f in folders), PACKAGE_ROOT / "schemas"]


_Stamp = tuple[tuple[str, int, int], ...]
_CODE_MEMO: dict[tuple[str, tuple[str, ...] | None], tuple[list[Path], _Stamp, str]] = {}


def _stamp(files: Sequence[Path]) -> _Stamp:
    """(mtime, size) of the files and of their folders: an edit changes a file's, a module
    added to or removed from a package changes its folder's."""
    out = []
    for p in sorted({*files, *(f.parent for f in files)}):
        try:
            st = p.stat()
            out.append((str(p), st.st_mtime_ns, st.st_size))
        except OSError:
            out.append((str(p), -1, -1))
    return tuple(out)


def code_version(stage: str, code_paths: Sequence[str | Path] | None = None) -> str:
    """``<package version>+<hash of the stage's source closure>``; ``code_paths`` overrides
    (a stage outside the registry hashes its own file).

    Remembered per process while none of the closure's files and folders changed their stat:
    parsing the closure with ``ast`` for every stage of every clip was 80 % of a no-op re-run
    check (docs/scale.md); a re-stat costs ~1 ms per stage."""
    memo_key = (stage, None if code_paths is None else tuple(map(str, code_paths)))
    hit = _CODE_MEMO.get(memo_key)
    if hit is not None and _stamp(hit[0]) == hit[1]:
        return hit[2]
    if code_paths is not None:
        paths: list[str | Path] = list(code_paths)
    elif stage in STAGE_MODULES:
        paths = list(module_closure(STAGE_MODULES[stage]))
    else:
        paths = _added_stage_paths(stage)
    files = _code_files(paths)
    stamp = _stamp(files)
    version = f"{package_version()}+{_hash_files(files)}"
    _CODE_MEMO[memo_key] = (files, stamp, version)
    return version


# --------------------------------------------------------------------------- API
def manifest_path(lake: Lake, clip_id: str, stage: str) -> str:
    return lake.path("manifests", clip_id, f"{stage}.json")


def read(lake: Lake, clip_id: str, stage: str) -> Manifest | None:
    path = manifest_path(lake, clip_id, stage)
    if not lake.exists(path):
        return None
    return _parse(lake, path)


_PARSED: dict[str, tuple[tuple[int, int, int, int], Manifest]] = {}


def _parse(lake: Lake, path: str) -> Manifest:
    """The manifest at ``path``; on a local lake remembered per process while its (device,
    inode, size, mtime) stay the same: manifests are only ever replaced by rename, so a new
    one is a new inode, and every stage's no-op check reads all of its clip's manifests.
    Callers must not modify what they get. On S3 (second-resolution mtimes, no inode) it
    is read every time."""
    if not lake.is_local:
        return Manifest.model_validate(lake.read_json(path))
    try:
        st = os.stat(path)
    except OSError:
        return Manifest.model_validate(lake.read_json(path))
    stamp = (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)
    hit = _PARSED.get(path)
    if hit is not None and hit[0] == stamp:
        return hit[1]
    m = Manifest.model_validate(lake.read_json(path))
    if len(_PARSED) > 100_000:
        _PARSED.clear()
    _PARSED[path] = (stamp, m)
    return m


def stage_key(
    lake: Lake,
    clip_id: str,
    stage: str,
    config: Any,
    upstream_stages: Sequence[str] = (),
    *,
    input_files: Sequence[str | Path] | None = None,
    read_tables: Sequence[tuple[str, str]] = (),
    code_paths: Sequence[str | Path] | None = None,
) -> StageKey:
    """The key a run of ``stage`` on ``clip_id`` would have now.

    Inputs are what the stage actually reads:

    - ``input_files`` (local paths; ingest passes ``tasks.ingest.clip_inputs(dir)[1]``) are
      hashed by content;
    - ``read_tables`` (``(zone, table)`` pairs, the stage's declared reads) contribute every
      file of those tables in this clip's partitions, with the checksum its writer recorded
      in its manifest (read from the file only when no manifest names it). So an upstream
      re-run that rewrites a table re-runs everything that reads it, and one that rewrites
      it byte for byte re-runs nothing;
    - ``upstream_stages`` (plugins that declare no tables) contribute the checksums of those
      stages' recorded outputs; a missing or failed upstream manifest makes the key unique.

    ``code_paths`` overrides the source files hashed into ``code_version`` (tests, plugins).
    """
    inputs: list[tuple[str, str]] = []
    if input_files:
        paths = [Path(p) for p in input_files]
        common = Path(*_common_parts(paths)) if len(paths) > 1 else paths[0].parent
        for p in sorted(paths):
            name = p.relative_to(common).as_posix() if p.is_relative_to(common) else str(p)
            inputs.append((f"file:{name}", file_checksum(p)))
    if read_tables:
        known = recorded_checksums(lake, clip_id)
        for zone, table in read_tables:
            root = lake.table_dir(zone, table, clip_id)
            for f in lake.list_files(root, ".parquet"):
                rel = f[len(lake.base) + 1:]
                digest = known.get(rel) or lake_file_checksum(lake, f)
                inputs.append((f"table:{rel}", digest))
    for up in upstream_stages:
        m = read(lake, clip_id, up)
        if m is None or m.status != "done":
            inputs.append((f"stage:{up}", f"missing-{time.time_ns()}"))
            continue
        h = hashlib.sha256()
        for o in sorted(m.outputs, key=lambda o: o.path):
            h.update(f"{o.path}\0{o.rows}\0{o.checksum}\n".encode())
        inputs.append((f"stage:{up}", h.hexdigest()))
    h = hashlib.sha256()
    for name, digest in inputs:
        h.update(f"{name}\0{digest}\n".encode())
    return StageKey(stage=stage, code_version=code_version(stage, code_paths),
                    params_hash=params_hash(config), inputs_hash=h.hexdigest(),
                    inputs=tuple(inputs), params=_params_data(config))


def recorded_checksums(lake: Lake, clip_id: str) -> dict[str, str]:
    """Lake-relative path -> checksum of every output the clip's manifests record."""
    out: dict[str, str] = {}
    for m in load(lake, clip_id):
        for o in m.outputs:
            if o.checksum:
                out[o.path] = o.checksum
    return out


def _common_parts(paths: list[Path]) -> list[str]:
    parts = [p.parent.parts for p in paths]
    out: list[str] = []
    for group in zip(*parts, strict=False):
        if len(set(group)) != 1:
            break
        out.append(group[0])
    return out or ["/"]


def current(lake: Lake, clip_id: str, stage: str, key: StageKey) -> Manifest | None:
    """The recorded run of ``stage`` when it finished with the same key and its outputs
    still exist (None: the stage must run)."""
    m = read(lake, clip_id, stage)
    if m is None or m.status not in ("done", "not_applicable"):
        return None
    if (m.code_version, m.params_hash, m.inputs_hash) != (
            key.code_version, key.params_hash, key.inputs_hash):
        return None
    return m if all(lake.exists(_abs(lake, o.path)) for o in m.outputs) else None


def is_current(lake: Lake, clip_id: str, stage: str, key: StageKey) -> bool:
    return current(lake, clip_id, stage, key) is not None


def _abs(lake: Lake, path: str) -> str:
    """Outputs are recorded relative to the lake root; accept absolute ones too."""
    if path.startswith(lake.base):
        return path
    return lake.path(path)


def record(lake: Lake, report: StageReport, key: StageKey, status: str = "done",
           error: str | BaseException | None = None) -> Manifest:
    """Write the manifest of one finished (or failed) stage run; fills missing output checksums
    and row counts from the files themselves."""
    if status not in ("done", "not_applicable", "failed"):
        raise ValueError(f"status must be done, not_applicable or failed, got {status!r}")
    outputs = []
    for o in report.outputs:
        path = _abs(lake, o.path)
        rel = path[len(lake.base) + 1:] if path.startswith(lake.base + "/") else o.path
        digest = o.checksum
        rows = o.rows
        if lake.exists(path):
            digest = digest or lake_file_checksum(lake, path)
            if rows is None and path.endswith(".parquet"):
                import pyarrow.parquet as pq
                with lake.fs.open_input_file(path) as f:
                    rows = int(pq.ParquetFile(f).metadata.num_rows)
        outputs.append(OutputFile(path=rel, rows=rows, checksum=digest))
    m = Manifest(
        clip_id=report.clip_id, stage=key.stage, status=status, reason=report.reason,
        code_version=key.code_version, params_hash=key.params_hash,
        params=key.params if isinstance(key.params, dict) else {},
        inputs_hash=key.inputs_hash, inputs=dict(key.inputs), outputs=outputs,
        metrics=dict(report.metrics), notes=list(report.notes),
        error=None if error is None else str(error),
        recorded_at=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()))
    lake.write_json(manifest_path(lake, report.clip_id, key.stage), m.model_dump(mode="json"))
    return m


def load(lake: Lake, clip_id: str) -> list[Manifest]:
    """Every stage manifest of one clip, sorted by stage name."""
    files = lake.list_files(lake.path("manifests", clip_id), ".json")
    return sorted((_parse(lake, f) for f in files), key=lambda m: m.stage)


def clear(lake: Lake, clip_id: str) -> None:
    """Forget every manifest of a clip (a quarantined clip must be reprocessed from scratch)."""
    lake.delete_dir(lake.path("manifests", clip_id))
