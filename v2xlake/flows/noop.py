"""The no-op check before Prefect: which clips have every chosen stage current.

WHY: a re-run of processed clips cost 17-29 s on two cores (#26), nearly all of it fixed
cost (Prefect's temporary server, the flow and task runs, importing every stage) for an
answer the manifests already hold. ``current_summaries`` gives it first, with the flow's own
check (``bookkeeping.key_from_facts`` + ``manifest.current``: the same key from the same
inputs, parameters and code), and without importing Prefect or the stages; the CLI starts
Prefect only for the clips it leaves (``None``), and not at all when there are none.

What would need the stage modules is remembered, per stage and code version (the hash of
the stage package's source closure, computed from the files without importing them), in
``$V2XLAKE_HOME/cache/noop-facts.json``: the stage's declared input and tables, its
effective parameters for a given (run parameters, clip ``params:`` block), and ingest's
list of input files per clip.yaml text (with the stat of the folders they were listed from,
so an added or removed bag file is seen). A miss is filled by importing the stage once, the
slow way, with the flow's own functions (``params.for_stage``, ``ingest.clip_inputs``), so
a hit gives what the flow would compute. A plugin pipeline (``module:ATTR``) is imported.

Not done here, on purpose: sweeping dead runs' staging folders and refreshing the catalog
(the flow does both when it runs; a clip that is current changed nothing).
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import json
import os
import tempfile
import threading
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from v2xlake.flows.settings import v2xlake_home

if TYPE_CHECKING:  # imported where used: a remembered answer needs none of them (0.6 s)
    from v2xlake.flows.bookkeeping import StageFacts
    from v2xlake.storage.lake import Lake

CACHE_VERSION = 1
_LOCK = threading.Lock()


def cache_path() -> Path:
    return Path(os.environ.get("V2XLAKE_NOOP_CACHE", v2xlake_home() / "cache" /
                               "noop-facts.json"))


def _digest(data: Any) -> str:
    text = json.dumps(data, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:32]


class FactsCache:
    """The JSON file of remembered facts; written back (atomically) only when it grew."""

    def __init__(self, path: Path | None = None) -> None:
        self.path = path or cache_path()
        self.data: dict[str, Any] = {}
        self.dirty = False
        try:
            loaded = json.loads(self.path.read_text())
            if isinstance(loaded, dict) and loaded.get("version") == CACHE_VERSION:
                self.data = loaded
        except (OSError, ValueError):
            pass
        self.data.setdefault("version", CACHE_VERSION)

    def get(self, section: str, key: str) -> Any:
        return self.data.get(section, {}).get(key)

    def put(self, section: str, key: str, value: Any) -> None:
        self.data.setdefault(section, {})[key] = value
        self.dirty = True

    def save(self) -> None:
        if not self.dirty:
            return
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(dir=self.path.parent, prefix=".noop-", suffix=".json")
            with os.fdopen(fd, "w") as f:
                json.dump(self.data, f)
            os.replace(tmp, self.path)
            self.dirty = False
        except OSError:  # a cache that cannot be written only costs time
            pass


_FLOWS = Path(__file__).resolve().parent


@functools.cache
def flows_code() -> str:
    """Hash of the flow modules that turn parameters into a stage's config (part of every
    remembered config's key, beside the stage's own code version)."""
    import pydantic

    from v2xlake.storage import manifest

    files = [_FLOWS / f for f in ("params.py", "params_model.py", "noop.py", "stage_names.py",
                                  "bookkeeping.py")] + [_FLOWS.parent / "schemas" / "clip.py"]
    return f"{pydantic.VERSION}+{manifest.code_hash(files)}"


def cached_section(cache: FactsCache, name: str, code: str, params: dict[str, Any],
                   own: dict[str, Any] | None, stage: Callable[[], Any]) -> Any:
    """Section ``name`` of the effective parameters as JSON data, remembered per (its code
    version, the flow modules' code, the run's parameters, the clip's block): the run's
    section (``own`` None, as ``params show`` prints it) or, for a stage, what the flow
    gives it (``PipelineParams.for_stage(stage, own)``). A miss validates the whole
    ``params`` the flow's way (importing every config model once)."""
    key = "@".join((name, code, flows_code(), _digest(params),
                    "-" if own is None else _digest(own)))
    hit = cache.get("configs", key)
    if hit is None:
        from v2xlake.flows.params import parse_params

        run = parse_params(params)
        hit = (run.model_dump(mode="json")[name] if own is None
               else run.for_stage(stage(), own).model_dump(mode="json"))
        cache.put("configs", key, hit)
    return hit


def load_code_memo(cache: FactsCache) -> None:
    """Seed ``storage.manifest``'s per-process memo of code versions from the cache file.

    Computing a stage's code version parses its source closure (0.3 s a stage, 2-3 s for
    all on a loaded machine); the memo re-checks every remembered entry by the (mtime,
    size) of its files and folders before using it (``manifest.code_version``), so an entry
    from an earlier process is as safe as one from this process."""
    from v2xlake.storage import manifest

    for k, (files, stamp, version) in (cache.data.get("code") or {}).items():
        stage, paths = json.loads(k)
        key = (stage, None if paths is None else tuple(paths))
        manifest._CODE_MEMO.setdefault(
            key, ([Path(f) for f in files], tuple(tuple(x) for x in stamp), version))


def save_code_memo(cache: FactsCache) -> None:
    """The memo's entries of this process into the cache file (written if they changed)."""
    from v2xlake.storage import manifest

    have = cache.data.get("code") or {}
    for (stage, paths), (files, stamp, version) in list(manifest._CODE_MEMO.items()):
        k = json.dumps([stage, None if paths is None else list(paths)])
        entry = [[str(f) for f in files], [list(x) for x in stamp], version]
        if have.get(k) != entry:
            cache.put("code", k, entry)


def _stat(p: Path) -> list[int]:
    try:
        st = p.stat()
        return [st.st_mtime_ns, st.st_size, st.st_ino]
    except OSError:
        return [-1, -1, -1]


class Checker:
    """The no-op check for one set of (stages, run parameters, pipeline)."""

    def __init__(self, stages: Sequence[str] | None, params: dict[str, Any] | None,
                 pipeline: str | None, cache: FactsCache | None = None) -> None:
        self.cache = cache or FactsCache()
        load_code_memo(self.cache)
        self.params = params or {}
        self.pipeline = pipeline
        self._plugin: dict[str, Any] | None = None
        names = self._pipeline_names()
        if stages:
            unknown = [s for s in stages if s not in names]
            if unknown:
                raise ValueError(f"unknown stage(s) {unknown}; known: {names}")
            names = [n for n in names if n in stages]
        self.names = names
        self.code = {n: self._code_version(n) for n in names}
        self.facts = {n: self._facts(n) for n in names}

    # ------------------------------------------------------------ the stages, unimported
    def _pipeline_names(self) -> list[str]:
        if not self.pipeline:
            from v2xlake.flows.stage_names import STAGE_NAMES

            return list(STAGE_NAMES)
        from v2xlake.flows.stage_names import resolve_pipeline  # a plugin: imported anyway

        self._plugin = {s.name: s for s in resolve_pipeline(self.pipeline)}
        return list(self._plugin)

    def _stage(self, name: str) -> Any:
        if self._plugin is not None:
            return self._plugin[name]
        from v2xlake.flows.stage_names import registry_stage

        return registry_stage(name)

    def _code_version(self, name: str) -> str:
        from v2xlake.storage import manifest

        if self._plugin is None:
            return manifest.code_version(name)
        from v2xlake.flows.bookkeeping import facts_of

        paths = facts_of(self._plugin[name]).code_paths
        return manifest.code_version(name, None if paths is None else list(paths))

    def _facts(self, name: str) -> StageFacts:
        from v2xlake.flows.bookkeeping import StageFacts

        if self._plugin is not None:
            from v2xlake.flows.bookkeeping import facts_of

            return facts_of(self._plugin[name])
        key = f"{name}@{self.code[name]}"
        hit = self.cache.get("facts", key)
        if hit is None:
            from v2xlake.flows.bookkeeping import facts_of

            f = facts_of(self._stage(name))
            hit = {"input": f.input, "reads": [list(r) for r in f.reads]}
            self.cache.put("facts", key, hit)
        return StageFacts(name, hit["input"], tuple((z, t) for z, t in hit["reads"]), None)

    def _config(self, name: str, own: dict[str, Any]) -> Any:
        """The stage's effective parameters as the flow computes them."""
        return cached_section(self.cache, name, self.code[name], self.params, own,
                              lambda: self._stage(name))

    def _ingest_inputs(self, clip_dir: Path, code: str) -> list[Path]:
        """``tasks.ingest.clip_inputs(dir)[1]``, remembered per (code, folder, clip.yaml
        text) and re-listed when a folder it listed changed."""
        text = (clip_dir / "clip.yaml").read_bytes()
        key = f"{code}@{clip_dir}@{hashlib.sha256(text).hexdigest()[:32]}"
        hit = self.cache.get("ingest_inputs", key)
        if hit is not None and all(_stat(Path(d)) == st for d, st in hit["dirs"]):
            return [Path(p) for p in hit["files"]]
        from v2xlake.tasks.ingest import clip_inputs

        files = list(clip_inputs(clip_dir)[1])
        dirs = sorted({str(clip_dir), *(str(f.parent) for f in files)})
        self.cache.put("ingest_inputs", key, {"files": [str(f) for f in files],
                                              "dirs": [[d, _stat(Path(d))] for d in dirs]})
        return files

    def _clip_yaml(self, d: Path) -> tuple[str, dict[str, Any]] | None:
        """(clip id, ``params:`` block) as ``peek_clip_id`` and ``params.clip_params`` read
        them, remembered per clip.yaml content (parsing one takes ~10-20 ms); None when the
        id is not a valid clip id (the flow will say why)."""
        try:
            text = (d / "clip.yaml").read_bytes()
        except OSError:
            return None
        key = f"{flows_code()}@{hashlib.sha256(text).hexdigest()[:32]}"
        hit = self.cache.get("clip_yaml", key)
        if hit is None:
            from v2xlake.flows.params import clip_params
            from v2xlake.flows.stage_names import peek_clip_id
            from v2xlake.storage.lake import CLIP_ID

            cid = peek_clip_id(d)
            hit = {"clip_id": cid if CLIP_ID.fullmatch(cid) else None,
                   "params": clip_params(d) if CLIP_ID.fullmatch(cid) else {}}
            self.cache.put("clip_yaml", key, hit)
        return None if hit["clip_id"] is None else (hit["clip_id"], hit["params"])

    # ------------------------------------------------------------ the check
    def check(self, lake: Lake, clip_dir: str | Path) -> dict[str, Any] | None:
        """The clip's summary (every stage ``cached``) when all chosen stages are current,
        else None (the flow must run; also for a clip folder that cannot be read)."""
        from v2xlake.flows.bookkeeping import cached_report, key_from_facts

        d = Path(clip_dir).resolve()
        ident = self._clip_yaml(d)
        if ident is None or not self.names:
            return None
        clip_id, own = ident
        outcomes = []
        for name in self.names:
            facts = self.facts[name]
            try:
                config = self._config(name, own)
                files: list[Path] | None = None
                if facts.input == "clip_dir":
                    files = (self._ingest_inputs(d, self.code[name]) if facts.code_paths is None
                             else _plugin_files(d))
                key = key_from_facts(lake, clip_id, facts, config, files)
                report = cached_report(lake, clip_id, name, key)
            except Exception:  # whatever fails here, the flow will say properly
                return None
            if report is None:
                return None
            outcomes.append({"stage": name, "status": "cached", "seconds": 0.0,
                             "report": report.model_dump(mode="json")})
        return {"clip_dir": str(d), "clip_id": clip_id, "status": "ok", "error": None,
                "quarantine_report": None, "stages": outcomes}


def _plugin_files(d: Path) -> list[Path]:
    from v2xlake.flows.bookkeeping import plugin_input_files

    return plugin_input_files(d)


@contextlib.contextmanager
def _code_versions_as_of(checker: Checker) -> Iterator[None]:
    """The stages' code versions as the checker found them at its start, for the whole
    batch: ``manifest.code_version`` re-stats a stage's whole source closure on every call
    (7 calls per clip, a third of the check at 1,000 clips); an edit during the check is
    seen by the next one (the flow itself re-checks before it skips a stage)."""
    known = {(n, None if checker.facts[n].code_paths is None
              else tuple(str(p) for p in checker.facts[n].code_paths or ())): v
             for n, v in checker.code.items()}
    from v2xlake.storage import manifest

    real = manifest.code_version

    def as_of(stage: str, code_paths: Sequence[str | Path] | None = None) -> str:
        key = (stage, None if code_paths is None else tuple(str(p) for p in code_paths))
        return known[key] if key in known else real(stage, code_paths)

    manifest.code_version = as_of
    try:
        yield
    finally:
        manifest.code_version = real


# ------------------------------------------------------------ remembered answers
# WHY: the check above needs the lake, manifest and bookkeeping modules (pydantic models,
# NumPy, pyarrow: 0.6-0.9 s of imports) for an answer that is the same as long as nothing it
# read changed. So a clip found current is remembered, per (lake, clip folder, stages, run
# parameters), with the stat (device, inode, size, mtime) of every file and folder the check
# read: clip.yaml, ingest's input files and their folders, the clip's manifests, every file
# and folder of the tables its stages read, their recorded outputs, each stage's source
# closure and the flow modules; plus the v2xlake and pydantic versions. The same stat test
# ``storage.statcache`` trusts for checksums. A file changed less than ``RACY_S`` before the
# check began is not trusted (its stat may not show a later edit): that answer is not
# remembered. Local lakes only. A plugin pipeline (``module:ATTR``) is remembered with its
# module's file and its stages' source files, the code the flow's key hashes for it.

ANSWERS_VERSION = 1
RACY_S = 2.0


def answers_dir() -> Path:
    """One small JSON file per remembered clip answer, beside the facts cache."""
    p = cache_path()
    return p.parent / f"{p.stem}-answers"


def _env_versions() -> list[str]:
    from importlib import metadata

    out = []
    for dist in ("v2xlake", "pydantic"):
        try:
            out.append(metadata.version(dist))
        except metadata.PackageNotFoundError:
            out.append("-")
    return out


def _answer_file(lake: str, clip_dir: Path, stages: Sequence[str] | None,
                 params: dict[str, Any] | None, pipeline: str | None) -> Path | None:
    """Where the answer for this question is remembered; None: not remembered (a lake URI)."""
    if "://" in lake:
        return None
    key = _digest([os.path.abspath(lake), str(clip_dir), list(stages) if stages else None,
                   params or {}, pipeline])
    return answers_dir() / f"{key}.json"


def _stat_of(path: str, seen: dict[str, list[int] | None]) -> list[int] | None:
    if path not in seen:
        try:
            st = os.stat(path)
            seen[path] = [st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns]
        except OSError:
            seen[path] = None
    return seen[path]


def _remembered(file: Path, seen: dict[str, list[int] | None],
                env: list[str]) -> dict[str, Any] | None:
    try:
        memo = json.loads(file.read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(memo, dict) or memo.get("v") != ANSWERS_VERSION or memo.get("env") != env:
        return None
    for path, stamp in zip(memo["paths"], memo["stamps"], strict=True):
        if _stat_of(path, seen) != stamp:
            return None
    summary: dict[str, Any] = memo["summary"]
    return summary


def _read_paths(checker: Checker, lake: Lake, clip_dir: Path,
                summary: dict[str, Any]) -> list[str]:
    """Every file and folder whose content the check of this clip depended on."""
    from v2xlake.storage import manifest

    clip_id = summary["clip_id"]
    paths = {str(clip_dir), str(clip_dir / "clip.yaml")}
    if checker.pipeline:
        import sys

        module = sys.modules[checker.pipeline.partition(":")[0]]
        paths.add(str(module.__file__))
    for name in checker.names:
        facts = checker.facts[name]
        if facts.input == "clip_dir":
            files = (checker._ingest_inputs(clip_dir, checker.code[name])
                     if facts.code_paths is None else _plugin_files(clip_dir))
            paths.update(str(f) for f in files)
            paths.update(str(f.parent) for f in files)
        for zone, table in facts.reads:
            root = lake.table_dir(zone, table, clip_id)
            paths.add(root)
            for top, subdirs, names in os.walk(root):
                paths.update(os.path.join(top, x) for x in (*subdirs, *names))
        memo = manifest._CODE_MEMO.get(
            (name, None if facts.code_paths is None else tuple(map(str, facts.code_paths))))
        if memo is None:  # not known as this process computed it: do not remember
            raise LookupError(name)
        paths.update(str(f) for f in memo[0])
        paths.update(str(f.parent) for f in memo[0])
    mdir = lake.path("manifests", clip_id)
    paths.add(mdir)
    paths.update(os.path.join(mdir, f) for f in os.listdir(mdir))
    for o in summary["stages"]:
        for out in (o["report"] or {}).get("outputs") or []:
            rel = out["path"]
            paths.add(rel if rel.startswith(lake.base) else lake.path(rel))
    paths.update(str(_FLOWS / f) for f in ("params.py", "params_model.py", "noop.py",
                                           "stage_names.py", "bookkeeping.py"))
    paths.add(str(_FLOWS.parent / "schemas" / "clip.py"))
    return sorted(paths)


def _remember(file: Path, paths: list[str], env: list[str], summary: dict[str, Any],
              since_ns: int) -> None:
    """Write the answer unless a file it read changed too recently to trust its stat."""
    seen: dict[str, list[int] | None] = {}
    stamps = [_stat_of(p, seen) for p in paths]
    if any(st is not None and st[3] >= since_ns - int(RACY_S * 1e9) for st in stamps):
        return
    try:
        file.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=file.parent, prefix=".answer-", suffix=".json")
        with os.fdopen(fd, "w") as f:
            json.dump({"v": ANSWERS_VERSION, "env": env, "paths": paths, "stamps": stamps,
                       "summary": summary}, f)
        os.replace(tmp, file)
    except OSError:  # an answer that cannot be remembered only costs time
        pass


def current_summaries(clip_dirs: Sequence[str | Path], lake: str,
                      stages: Sequence[str] | None = None,
                      params: dict[str, Any] | None = None, pipeline: str | None = None
                      ) -> list[dict[str, Any] | None]:
    """For each clip folder: its summary when every chosen stage is current, else None.

    ``params`` is the run's parameters as given (a mapping, e.g. a ``--params`` file's
    YAML), not yet validated. A lake that does not exist yet: every clip must run.
    Remembered answers whose files are unchanged come first; the others are checked."""
    dirs = [Path(d).resolve() for d in clip_dirs]
    files = [_answer_file(lake, d, stages, params, pipeline) for d in dirs]
    env = _env_versions() if any(files) else []
    seen: dict[str, list[int] | None] = {}
    out: list[dict[str, Any] | None] = [
        None if f is None else _remembered(f, seen, env) for f in files]
    todo = [i for i, a in enumerate(out) if a is None]
    if todo:
        for i, summary in zip(todo, _check([dirs[i] for i in todo], lake, stages, params,
                                           pipeline, [files[i] for i in todo], env),
                              strict=True):
            out[i] = summary
    return out


def _check(dirs: list[Path], lake: str, stages: Sequence[str] | None,
           params: dict[str, Any] | None, pipeline: str | None,
           files: list[Path | None], env: list[str]) -> list[dict[str, Any] | None]:
    """The check itself (the flow's key and manifests), remembering what it finds current."""
    import time

    from v2xlake.storage.lake import Lake

    the_lake = Lake(lake, create=False)
    if not the_lake.looks_like_lake():
        return [None] * len(dirs)
    since = time.time_ns()
    with _LOCK:
        checker = Checker(stages, params, pipeline)
        try:
            with _code_versions_as_of(checker):
                out = [checker.check(the_lake, d) for d in dirs]
            for d, f, summary in zip(dirs, files, out, strict=True):
                if summary is not None and f is not None and the_lake.is_local:
                    with contextlib.suppress(LookupError, OSError):
                        _remember(f, _read_paths(checker, the_lake, d, summary), env,
                                  summary, since)
            return out
        finally:
            save_code_memo(checker.cache)
            checker.cache.save()
