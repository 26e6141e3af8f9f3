"""The stage registry: which stages a clip goes through, in order, as data.

WHY data and not calls: the stage modules are written in parallel and some may be missing
on a given checkout; the flow runs every stage whose module imports and says clearly which
ones it skipped. Tests (and deployments) can swap the registry for another list of
``name=module:function`` strings without touching the flow, and because stages are named by
import path, Dask workers and deployment processes resolve them the same way.

A stage function is called as ``fn(lake, target)`` where ``target`` is the clip folder for
stages whose ``input`` is ``"clip_dir"`` (ingest) and the clip id for all others; it returns
a :class:`v2xlake.schemas.stage.StageReport`. Its parameters are the default of its ``config``
argument (a pydantic model), whose JSON enters the cache key.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any, Literal

StageInput = Literal["clip_dir", "clip_id"]


@dataclass(frozen=True)
class StageSpec:
    """One stage: its name, where its entry point lives, and what it takes."""

    name: str
    target: str  # "package.module:function"
    input: StageInput = "clip_id"

    @classmethod
    def parse(cls, text: str) -> StageSpec:
        """``name=module:function[@clip_dir]`` (the form used in flow parameters)."""
        name, _, rest = text.partition("=")
        target, _, inp = rest.partition("@")
        if not name or ":" not in target:
            raise ValueError(f"stage spec {text!r} is not name=module:function[@clip_dir]")
        kind: StageInput = "clip_dir" if inp == "clip_dir" else "clip_id"
        return cls(name=name, target=target, input=kind)

    def format(self) -> str:
        return f"{self.name}={self.target}" + ("@clip_dir" if self.input == "clip_dir" else "")

    @property
    def module(self) -> str:
        return self.target.partition(":")[0]

    def load(self) -> Callable[..., Any]:
        """Import the entry point (raises ImportError / AttributeError when unavailable)."""
        mod, _, attr = self.target.partition(":")
        fn = getattr(importlib.import_module(mod), attr)
        if not callable(fn):
            raise TypeError(f"{self.target} is not callable")
        return fn


DEFAULT_STAGES: tuple[StageSpec, ...] = (
    StageSpec("ingest", "v2xlake.tasks.ingest:run_ingest", "clip_dir"),
    StageSpec("qa", "v2xlake.tasks.qa.core:run_qa"),
    StageSpec("anonymize", "v2xlake.tasks.anonymize:run_anonymize"),
    StageSpec("deskew", "v2xlake.tasks.deskew.stage:run_deskew"),
    StageSpec("register", "v2xlake.tasks.register.stage:run_register"),
    StageSpec("annotate", "v2xlake.tasks.annotate.core:run_annotate"),
    StageSpec("align", "v2xlake.tasks.align.stage:run_align"),
)
STAGE_NAMES = tuple(s.name for s in DEFAULT_STAGES)


def resolve_registry(registry: Sequence[str] | None) -> list[StageSpec]:
    return [StageSpec.parse(s) for s in registry] if registry else list(DEFAULT_STAGES)


def select(specs: Sequence[StageSpec], names: Iterable[str] | None) -> list[StageSpec]:
    """Keep the registry order; unknown names are an error (typos must not pass silently)."""
    if not names:
        return list(specs)
    wanted = list(names)
    known = {s.name for s in specs}
    unknown = [n for n in wanted if n not in known]
    if unknown:
        raise ValueError(f"unknown stage(s) {unknown}; known: {sorted(known)}")
    return [s for s in specs if s.name in wanted]


@dataclass(frozen=True)
class Availability:
    spec: StageSpec
    error: str | None  # None: importable

    @property
    def ok(self) -> bool:
        return self.error is None


def check_available(specs: Sequence[StageSpec]) -> list[Availability]:
    out = []
    for spec in specs:
        try:
            spec.load()
            out.append(Availability(spec, None))
        except Exception as exc:  # ImportError, AttributeError, a broken module: all "missing"
            out.append(Availability(spec, f"{type(exc).__name__}: {exc}"))
    return out
