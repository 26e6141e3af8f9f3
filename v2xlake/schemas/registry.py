"""The stage registry: the one definition of which stages a pipeline runs and in what order,
and where each stage package is.

A stage is one package. The standard ones are listed, in pipeline order, in
``STAGE_PACKAGES``; a package outside this repository adds itself with an entry point in the
group ``v2xlake.stages`` (``<stage name> = <package>``) and runs after the standard stages, in
the order of the entry points' names. Each package's ``__init__.py`` declares the tables the
stage owns (``DECLARATION``, a ``schemas.stage.StageDeclaration``); by the package shape
(docs/architecture.md, "Stage package shape") its parameters are ``<package>.config`` and its
Stage object is in ``<package>.stage``. Everything that needs the stage list derives it from
here: ``flows.stage_names`` (the Stage objects, imported by name), ``flows.params_model``
(one ``PipelineParams`` section per stage), ``schemas.tables.TABLE_OWNERS`` and the code
version of a stage (``storage.manifest``).

WHY names and packages first, declarations on demand: the no-op check and ``v2xlake params
show`` read the stage names on every call and must not import any stage package for them
(``tests/test_cli_ops.py``); a declaration imports only the package's ``__init__.py``
(pydantic), never its numeric modules. The packages are imported by name, so this module
(below storage and tasks) imports no stage statically.
"""

from __future__ import annotations

import functools
import importlib
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # imported where a declaration is read: the names need no pydantic
    from v2xlake.schemas.stage import StageDeclaration

#: The standard pipeline, in order: one package per stage, the stage named after the package.
STAGE_PACKAGES: tuple[str, ...] = tuple(
    f"v2xlake.tasks.{name}"
    for name in ("ingest", "qa", "anonymize", "deskew", "register", "annotate", "align"))
#: The entry-point group through which an installed package adds a stage.
ENTRY_POINT_GROUP = "v2xlake.stages"


@functools.cache
def stage_packages() -> dict[str, str]:
    """Stage name -> its package, in pipeline order: the standard stages, then those added
    by entry points (sorted by name, so every process runs them in the same order). A name
    given to two packages is an error: the stage that runs must not depend on which
    distribution the import system lists first."""
    from importlib.metadata import entry_points

    found = {package.rpartition(".")[2]: package for package in STAGE_PACKAGES}
    for ep in sorted(entry_points(group=ENTRY_POINT_GROUP), key=lambda e: e.name):
        if found.get(ep.name, ep.value) != ep.value:
            raise ValueError(f"stage {ep.name!r} is declared by {found[ep.name]} and, through "
                             f"the entry point group {ENTRY_POINT_GROUP}, by {ep.value}")
        found[ep.name] = ep.value
    return found


def stage_names() -> tuple[str, ...]:
    """Every registered stage, in pipeline order."""
    return tuple(stage_packages())


def package(name: str) -> str:
    """The package of stage ``name`` (KeyError: no such stage)."""
    return stage_packages()[name]


def declaration(name: str) -> StageDeclaration:
    """Stage ``name``'s declaration (imports its package's ``__init__.py`` only)."""
    from v2xlake.schemas.stage import StageDeclaration

    module = importlib.import_module(package(name))
    found = getattr(module, "DECLARATION", None)
    if not isinstance(found, StageDeclaration) or found.name != name:
        raise TypeError(f"{module.__name__} must define DECLARATION = StageDeclaration("
                        f"name={name!r}, owns=...), found {found!r}")
    return found


def stage_ref(name: str) -> tuple[str, str]:
    """(module, attribute) of stage ``name``'s Stage object."""
    return f"{package(name)}.stage", declaration(name).stage_object


@functools.cache
def table_owners() -> dict[tuple[str, str], str]:
    """(zone, table) -> the stage that owns it, from every stage's declaration; a table
    declared by two stages is an error (the lake's single-writer rule)."""
    owners: dict[tuple[str, str], str] = {}
    for name in stage_packages():
        for t in declaration(name).owns:
            key = (t.zone, t.name)
            if key in owners:
                raise ValueError(f"{t} is declared by stages {owners[key]!r} and {name!r}")
            owners[key] = name
    return owners


def refresh() -> None:
    """Forget what was found: a process that installs a stage package after the first look
    (a test putting one on ``sys.path``) sees it from the next call on."""
    importlib.invalidate_caches()
    stage_packages.cache_clear()
    table_owners.cache_clear()
