"""The stage registry by name, and what the flow reads from a clip folder before any stage,
without importing Prefect or any stage module.

WHY a module of its own: the stage modules import NumPy, SciPy, Open3D, numba (4-8 s on two
cores) and Prefect takes 2 s more; the no-op check (``flows.noop``) and ``v2xlake params show
--stage X`` must answer before either is imported. The stage list itself is
``schemas.registry`` (its one definition); ``flows.pipeline.STAGES`` imports the Stage
objects it names.
"""

from __future__ import annotations

import functools
import importlib
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import yaml

from v2xlake.schemas import registry


def __getattr__(name: str) -> Any:
    """``STAGE_NAMES`` (every registered stage, in pipeline order) from the one stage list
    (``schemas.registry``) when asked: it costs no stage import."""
    if name == "STAGE_NAMES":
        return registry.stage_names()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def resolve_pipeline(pipeline: str | None = None) -> tuple[Any, ...]:
    """The stages to run: ``flows.pipeline.STAGES``, or another tuple of Stage objects
    named as ``module:ATTRIBUTE`` (test doubles and plugins that Dask workers and deployment
    processes must import by name). Any import error propagates: nothing is skipped."""
    from v2xlake.schemas.stage import Stage

    if not pipeline:
        return tuple(registry_stage(n) for n in registry.stage_names())
    mod, _, attr = pipeline.partition(":")
    found = getattr(importlib.import_module(mod), attr)
    if not isinstance(found, tuple | list) or not all(isinstance(s, Stage) for s in found):
        raise TypeError(f"pipeline {pipeline!r} is not a sequence of Stage objects")
    return tuple(found)


def select(stages: Sequence[Any], names: Iterable[str] | None) -> list[Any]:
    """Keep the pipeline order; unknown names are an error (typos must not pass silently)."""
    if not names:
        return list(stages)
    wanted = list(names)
    known = [s.name for s in stages]
    unknown = [n for n in wanted if n not in known]
    if unknown:
        raise ValueError(f"unknown stage(s) {unknown}; known: {known}")
    return [s for s in stages if s.name in wanted]


def registry_stage(name: str) -> Any:
    """One registered stage's Stage object (imports that stage's module only)."""
    mod, attr = registry.stage_ref(name)
    return getattr(importlib.import_module(mod), attr)


UNREADABLE = "_unreadable-"  # no clip id starts with "_": these never name a real clip


@functools.lru_cache(maxsize=64)
def parse_clip_yaml(text: str) -> Any:
    """``schemas.clip.load_yaml(text)``, once per distinct text (a large clip.yaml takes
    ~10 ms; the clip id and the ``params:`` block are both read from it). Callers must not
    modify the result."""
    from v2xlake.schemas.clip import load_yaml

    return load_yaml(text)


def peek_clip_id(clip_dir: str | Path) -> str:
    """The clip id from clip.yaml; when it has none (unreadable, invalid), a name that
    cannot be any clip's id (``_unreadable-<folder>``): a broken delivery in a folder named
    like an existing clip must never be taken for it."""
    from v2xlake.storage.lake import CLIP_ID

    path = Path(clip_dir) / "clip.yaml"
    try:
        data = parse_clip_yaml(path.read_text())
        cid = data.get("clip_id") if isinstance(data, dict) else None
        if isinstance(cid, str) and CLIP_ID.fullmatch(cid):
            return cid
    except (OSError, yaml.YAMLError, UnicodeDecodeError):
        pass
    return UNREADABLE + Path(clip_dir).resolve().name
