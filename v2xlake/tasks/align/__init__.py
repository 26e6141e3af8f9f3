"""Temporal alignment (Sec. 5): ``config.py`` its parameters, ``methods.py`` the three methods,
``boxes.py`` box geometry, ``metrics.py`` scores against true boxes, ``overlay.py`` the
picture (all pure, on arrays), ``stage.py`` the lake I/O and the ``ALIGN`` Stage object.
Camera projection is the shared :mod:`v2xlake.tasks.projection` (anonymize uses it too)."""

from __future__ import annotations

from v2xlake.schemas.stage import StageDeclaration, tables

# what the registry reads without importing the stage (schemas/registry.py)
DECLARATION = StageDeclaration(
    name="align",
    owns=tables("clean", "alignments"))
