"""The layering the architecture document promises (docs/architecture.md, Layers and Stage
package shape), checked on the source: a stage package never imports another stage's
package (what two stages share lives in a module below both, e.g. ``tasks/motion.py``,
``tasks/projection.py``), the lower layers never import the upper ones, and every stage
package has the same shape: ``config.py`` (pydantic only), ``stage.py`` (the only module
that touches the lake) and pure modules, all named in the package docstring."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

from v2xlake.schemas.registry import STAGE_PACKAGES

PACKAGE = Path(__file__).resolve().parents[1] / "v2xlake"
# the standard stages, from the one stage list (schemas/registry.py)
STAGES = tuple(p.rpartition(".")[2] for p in STAGE_PACKAGES)
# lower layer -> the packages it must not import (docs/architecture.md, Layers)
FORBIDDEN = {"schemas": ("v2xlake.storage", "v2xlake.tasks", "v2xlake.flows"),
             "storage": ("v2xlake.tasks", "v2xlake.flows"),
             "tasks": ("v2xlake.flows",),
             # the privacy audit, a tool over the lake and releases: below the flows
             "audit": ("v2xlake.flows",)}


# known exceptions still to fix (none now: the audit is its own package and takes the
# release-name rule from storage/releases.py)
NOT_YET_MOVED: set[str] = set()


# the stage packages not yet in the shape below (none: every stage has it)
SHAPE_PENDING: set[str] = set()
SHAPED = tuple(s for s in STAGES if s not in SHAPE_PENDING)
NUMERIC = ("numpy", "numba", "scipy", "pyarrow", "cv2", "open3d", "rosbags", "onnxruntime")
# what touches the lake: storage, and the shared clip reader built on it
LAKE = ("v2xlake.storage", "v2xlake.tasks.reader")
# pure modules that still hand out names which moved to their stage.py (a module
# ``__getattr__`` importing stage.py on first use), until the callers named there import
# them from stage.py; an entry that no longer imports stage.py must be dropped
FORWARDS_TO_STAGE: set[str] = set()


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


def _touches(mods: set[str], prefixes: tuple[str, ...]) -> bool:
    return any(m == p or m.startswith(f"{p}.") for m in mods for p in prefixes)


def test_stage_packages_have_one_shape() -> None:
    """config.py imports no numeric library; stage.py is the only module of the package that
    imports the lake (storage or the shared reader)."""
    bad = []
    for stage in SHAPED:
        pkg = PACKAGE / "tasks" / stage
        for need in ("config.py", "stage.py"):
            if not (pkg / need).is_file():
                bad.append(f"tasks/{stage} has no {need}")
        for p in sorted(pkg.rglob("*.py")):
            mods = _imports(p)
            if p.name == "config.py" and _touches(mods, NUMERIC):
                bad.append(f"tasks/{stage}/config.py imports a numeric library")
            if p.name == "config.py" and _touches(mods, ("v2xlake.tasks", "v2xlake.storage")) \
                    and not all(m.endswith(".config") for m in mods
                                if m.startswith(("v2xlake.tasks", "v2xlake.storage"))):
                bad.append(f"tasks/{stage}/config.py imports more than other config modules")
            if p.name != "stage.py" and _touches(mods, LAKE):
                bad.append(f"tasks/{stage}/{p.relative_to(pkg)} touches the lake")
    assert not bad, bad


def test_pure_modules_do_not_import_their_stage() -> None:
    """The numeric core sits below ``stage.py``: a pure module importing it would reach the
    lake through it (only the listed forwarders of moved names still do, lazily)."""
    found = set()
    for stage in SHAPED:
        pkg = PACKAGE / "tasks" / stage
        for p in sorted(pkg.rglob("*.py")):
            if p.name != "stage.py" and _touches(_imports(p), (f"v2xlake.tasks.{stage}.stage",)):
                found.add(f"{stage}/{p.relative_to(pkg)}")
    assert found - FORWARDS_TO_STAGE == set(), found
    assert FORWARDS_TO_STAGE - found == set(), "no longer forwards: drop it from FORWARDS_TO_STAGE"


def test_stage_package_docstrings_name_their_files() -> None:
    """A package docstring that names a file the package lacks, or leaves one out, misleads
    the next reader (qa's and annotate's once described files they did not have)."""
    bad = []
    for stage in SHAPED:
        pkg = PACKAGE / "tasks" / stage
        doc = ast.get_docstring(ast.parse((pkg / "__init__.py").read_text())) or ""
        files = {p.name for p in pkg.glob("*.py") if p.name != "__init__.py"}
        named = {w.strip("`,.:;()") for w in doc.split() if w.strip("`,.:;()").endswith(".py")}
        bad += [f"tasks/{stage}: docstring does not name {f}" for f in sorted(files - named)]
        bad += [f"tasks/{stage}: docstring names {f}, not in the package"
                for f in sorted(named - files)]
    assert not bad, bad


def test_config_modules_import_light() -> None:
    """``v2xlake params show`` imports the stages' config modules: none may pull in a
    numeric library (seconds on two cores), through the package or itself."""
    code = ("import sys\n"
            + "".join(f"import v2xlake.tasks.{s}.config\n" for s in SHAPED)
            + f"print(sorted(m for m in sys.modules if m.split('.')[0] in {NUMERIC!r}))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, cwd=PACKAGE.parent)
    assert out.stdout.strip() == "[]", out.stdout
