"""Ingest: a clip folder (clip.yaml + one bag per agent) -> landing copy + raw-zone tables.

``config.py`` its parameters, ``clipdir.py`` the clip folder (clip.yaml, the files it names,
the landing rule), ``stage.py`` the lake I/O and the ``INGEST`` Stage object. The others read
bags and turn messages into arrays and rows, no lake: ``bagopen.py`` opens a bag,
``payloads.py`` reads ROS 2 payloads in place, ``rawmsg.py`` parses the bulky messages from
their wire format, ``pointcloud.py`` decodes points, ``images.py`` camera images,
``ins.py`` IMU and GNSS, ``pose.py`` the agent's pose track, ``calibration.py`` tf_static and
CameraInfo, ``annotations.py`` the annotation file, ``rows.py`` row-model helpers.

The names below are imported on first use: importing ``tasks.ingest.config`` (``v2xlake
params show``) must not import the decoders (NumPy, numba, rosbags) through this package.
"""

from __future__ import annotations

import importlib
from typing import Any

from v2xlake.schemas.stage import INGEST_TABLES, StageDeclaration, tables

# what the registry reads without importing the stage (schemas/registry.py)
DECLARATION = StageDeclaration(
    name="ingest",
    owns=tables("raw", *INGEST_TABLES))


_WHERE = {"IngestConfig": "config", "clip_inputs": "clipdir", "run_ingest": "stage"}
__all__ = sorted(_WHERE)


def __getattr__(name: str) -> Any:
    if name not in _WHERE:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{_WHERE[name]}"), name)
