"""Temporal alignment (Sec. 5): box geometry, methods, metrics, overlay, the stage; camera
projection is the shared :mod:`v2xlake.tasks.projection` (anonymize uses it too)."""
