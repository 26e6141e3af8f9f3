"""The flow's side of the bookkeeping: manifest keys, quarantine, catalog access.

Stages only compute and write tables; the flow decides whether a stage must run
(``v2xlake.storage.manifest``: inputs -> parameters -> code, with upstream stages' recorded outputs
as inputs), records the manifest afterwards, quarantines a clip on ``ClipError``
(``v2xlake.storage.quarantine`` + forgetting its manifests so a fixed clip reprocesses from scratch)
and refreshes / queries the DuckDB catalog.
"""

from __future__ import annotations

import inspect
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pyarrow as pa
from pydantic import BaseModel

from v2xlake.schemas.stage import Stage, StageReport
from v2xlake.storage import manifest
from v2xlake.storage.lake import Lake

log = logging.getLogger("v2xlake.flows")



# ---------------------------------------------------------------- cache (storage.manifest)
@dataclass(frozen=True)
class StageFacts:
    """What the manifest key of a stage needs to know about it: its name, whether it reads
    the clip folder, the tables it reads, and whether it is a standard stage (code version
    from its package) or a plugin (its own source file). ``flows.noop`` keeps these per
    code version so that it need not import the stage."""

    name: str
    input: str
    reads: tuple[tuple[str, str], ...]
    code_paths: tuple[str, ...] | None  # None: a standard stage


def facts_of(stage: Stage[Any]) -> StageFacts:
    import sys

    from v2xlake.schemas import registry

    # the registry's own object (``flows.pipeline.STAGES``)? Its module is imported if so:
    # a test double named like a standard stage must not import the real one to find out
    mod, attr = (registry.stage_ref(stage.name) if stage.name in registry.stage_packages()
                 else ("", ""))
    standard = getattr(sys.modules.get(mod), attr, None) is stage
    code_paths: tuple[str, ...] | None = None
    if not standard:  # a plugin or test double: hash its own source file
        src = inspect.getsourcefile(stage.run)
        code_paths = (src,) if src else ()
    return StageFacts(stage.name, stage.input, tuple((t.zone, t.name) for t in stage.reads),
                      code_paths)


def stage_key(lake: Lake, clip_id: str, stage: Stage[Any], config: BaseModel,
              clip_dir: Path | None) -> manifest.StageKey:
    """storage.manifest's key: what the stage reads (files or tables), parameters, code."""
    facts = facts_of(stage)
    input_files: list[Path] | None = None
    if facts.input == "clip_dir" and clip_dir is not None:
        if facts.code_paths is None:
            from v2xlake.tasks.ingest import clip_inputs

            input_files = list(clip_inputs(clip_dir)[1])
        else:
            input_files = plugin_input_files(clip_dir)
    return key_from_facts(lake, clip_id, facts, config, input_files)


def plugin_input_files(clip_dir: Path | str) -> list[Path]:
    """A plugin that reads the clip folder: every file in it."""
    return sorted(p for p in Path(clip_dir).rglob("*") if p.is_file())


def key_from_facts(lake: Lake, clip_id: str, facts: StageFacts, config: Any,
                   input_files: list[Path] | None) -> manifest.StageKey:
    """The key itself; ``config`` a model or its ``model_dump(mode="json")`` (same hash)."""
    return manifest.stage_key(lake, clip_id, facts.name, config, input_files=input_files,
                              read_tables=list(facts.reads),
                              code_paths=None if facts.code_paths is None
                              else list(facts.code_paths))


def cached_report(lake: Lake, clip_id: str, stage: str,
                  key: manifest.StageKey) -> StageReport | None:
    """The recorded result when the stage is current (same key, outputs still there)."""
    m = manifest.current(lake, clip_id, stage, key)
    if m is None:
        return None
    images = [lake.path(o.path) if not o.path.startswith(lake.base) else o.path
              for o in m.outputs if o.path.endswith(".png")]
    status = "not_applicable" if m.status == "not_applicable" else "done"
    return StageReport(stage=stage, clip_id=clip_id, status=status, reason=m.reason,
                       outputs=m.outputs, metrics=m.metrics, notes=m.notes, images=images)


def record(lake: Lake, report: StageReport, key: manifest.StageKey) -> None:
    manifest.record(lake, report, key, report.status)


def processed_clip_ids(lake: Lake) -> set[str]:
    """Clips the lake has seen (with manifests or quarantined): the landing scan skips them."""
    seen = set()
    for zone in ("manifests", "quarantine"):
        root = lake.path(zone)
        for f in lake.list_files(root, ".json"):
            rel = f[len(root):].strip("/")
            seen.add(rel.split("/", 1)[0])
    return seen


# ---------------------------------------------------------------- quarantine
def quarantine(lake: Lake, clip_id: str, error: Exception, *, stage: str,
               remove_data: bool = True) -> str:
    """v2xlake.storage.quarantine (report, raw/clean removed) + forget the clip's manifests.

    ``remove_data=False`` (a delivery that failed at ingest): only the report is written.
    Ingest publishes nothing until it succeeds, and what the lake holds under that id may
    be another delivery's, which a broken or hostile clip.yaml must never delete."""
    from v2xlake.storage.quarantine import quarantine as storage_quarantine
    from v2xlake.storage.quarantine import report_path

    with lake.clip_lock(clip_id):
        report = storage_quarantine(lake, clip_id, error, stage=stage,
                                    zones=("raw", "clean") if remove_data else ())
        if remove_data:
            manifest.clear(lake, clip_id)
    return report_path(lake, report["report_id"])


# ---------------------------------------------------------------- catalog
def refresh_catalog(lake: Lake) -> None:
    """Re-scan the lake's tables (new tables become views; rewrites catalog.duckdb)."""
    from v2xlake.storage.catalog import Catalog

    with Catalog(lake):  # __init__ refreshes
        pass


def query(lake: Lake, sql: str) -> pa.Table:
    """The project's own SQL over the lake's catalog (views over the Parquet files)."""
    from v2xlake.storage.catalog import Catalog

    with Catalog(lake, read_only=True) as cat:
        return cat.query(sql)


def user_query(lake: Lake, sql: str) -> pa.Table:
    """A user's SQL: one SELECT on a locked-down, read-only connection (storage.catalog)."""
    from v2xlake.storage.catalog import Catalog

    with Catalog(lake, read_only=True) as cat:
        return cat.user_query(sql)
