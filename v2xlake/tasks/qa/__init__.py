"""The qa stage: ``config.py`` its thresholds, ``timing.py`` the checks on stamp arrays (PPS
grids, jitter, rates, dropped frames, pose coverage), ``stage.py`` the lake I/O (reads the
raw zone, writes ``qa_checks``) and the ``QA`` Stage object."""

from __future__ import annotations

from v2xlake.schemas.stage import StageDeclaration, tables

# what the registry reads without importing the stage (schemas/registry.py)
DECLARATION = StageDeclaration(
    name="qa",
    owns=tables("raw", "qa_checks"))
