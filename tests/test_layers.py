"""The layering the architecture document promises (docs/architecture.md, Layers), checked on
the source: a stage package never imports another stage's package (what two stages share
lives in a module below both, e.g. ``tasks/motion.py``, ``tasks/projection.py``), and the
lower layers never import the upper ones."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "v2xlake"
STAGES = ("ingest", "qa", "anonymize", "deskew", "register", "annotate", "align")
# lower layer -> the packages it must not import (docs/architecture.md, Layers)
FORBIDDEN = {"schemas": ("v2xlake.storage", "v2xlake.tasks", "v2xlake.flows"),
             "storage": ("v2xlake.tasks", "v2xlake.flows"),
             "tasks": ("v2xlake.flows",)}


# the privacy audit is a tool, not the anonymize stage, and checks release names with the
# release flow's rule; it is to become its own package (issue #24, item 4)
NOT_YET_MOVED = {"tasks/anonymize/audit.py imports v2xlake.flows.release"}


def _imports(path: Path) -> set[str]:
    """Every module a file imports, lazily inside functions too; not those under
    ``if TYPE_CHECKING:`` (annotations only, nothing is imported at run time)."""
    tree = ast.parse(path.read_text())
    typing_only = {id(n) for node in ast.walk(tree) if isinstance(node, ast.If)
                   and isinstance(node.test, ast.Name) and node.test.id == "TYPE_CHECKING"
                   for n in ast.walk(node)}
    out: set[str] = set()
    for node in ast.walk(tree):
        if id(node) in typing_only:
            continue
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module)
            out.update(f"{node.module}.{a.name}" for a in node.names)
    return out


def test_no_stage_imports_another_stage() -> None:
    bad = []
    for stage in STAGES:
        others = tuple(f"v2xlake.tasks.{s}" for s in STAGES if s != stage)
        for p in (PACKAGE / "tasks" / stage).rglob("*.py"):
            for m in _imports(p):
                if m.startswith(others) and (m in others or m.startswith(tuple(
                        f"{o}." for o in others))):
                    bad.append(f"{p.relative_to(PACKAGE)} imports {m}")
    assert not bad, bad


def test_lower_layers_do_not_import_upper_ones() -> None:
    bad = {f"{p.relative_to(PACKAGE)} imports {'.'.join(m.split('.')[:3])}"
           for layer, upper in FORBIDDEN.items() for p in (PACKAGE / layer).rglob("*.py")
           for m in _imports(p) if m.startswith(upper)}
    assert bad - NOT_YET_MOVED == set(), bad
    assert NOT_YET_MOVED - bad == set(), "fixed: drop it from NOT_YET_MOVED"
