"""Ingest: a clip folder (clip.yaml + one bag per agent) -> landing copy + raw-zone tables.

``config.py`` its parameters, ``clipdir.py`` the clip folder (clip.yaml, the files it names,
the landing rule), ``stage.py`` the lake I/O and the ``INGEST`` Stage object; the other
modules decode bags and messages into arrays and rows.

The names below are imported on first use: importing ``tasks.ingest.config`` (``v2xlake
params show``) must not import the decoders (NumPy, numba, rosbags) through this package.
"""

from __future__ import annotations

import importlib
from typing import Any

_WHERE = {"IngestConfig": "config", "clip_inputs": "clipdir", "run_ingest": "stage"}
__all__ = sorted(_WHERE)


def __getattr__(name: str) -> Any:
    if name not in _WHERE:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{_WHERE[name]}"), name)
