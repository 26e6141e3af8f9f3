"""The deskew stage: ``config.py`` its parameters, ``coverage.py`` which scans a pose track
can compensate (on arrays), ``stage.py`` the lake I/O (chunks, the output tables) and the
``DESKEW`` Stage object. Its numeric core, per-point motion compensation, is
:mod:`v2xlake.tasks.motion`, shared with register (re-deskew) and align."""

from __future__ import annotations

from v2xlake.schemas.stage import StageDeclaration, tables

# what the registry reads without importing the stage (schemas/registry.py)
DECLARATION = StageDeclaration(
    name="deskew",
    owns=tables("clean", "lidar_points_deskewed", "deskew_frames"))
