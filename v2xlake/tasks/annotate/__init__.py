"""The annotate stage: ``config.py`` its parameters, ``consistency.py`` the checks on arrays
(world-frame boxes, cross-agent distances, links), ``stage.py`` the lake I/O and the
``ANNOTATE`` Stage object."""

from __future__ import annotations

from v2xlake.schemas.stage import StageDeclaration, tables

# what the registry reads without importing the stage (schemas/registry.py)
DECLARATION = StageDeclaration(
    name="annotate",
    owns=tables("clean", "annotations_world", "instances"))
