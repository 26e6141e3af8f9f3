"""v2xlake: cooperative-perception driving recordings into a queryable, releasable lake.

The layers are sub-packages of this one folder: ``v2xlake.schemas`` (data contracts),
``v2xlake.storage`` (all I/O), ``v2xlake.tasks`` (one package per stage) and
``v2xlake.flows`` (Prefect orchestration and the CLI); a checkout, an editable install and a
wheel hold the same files, and installing v2xlake claims one import name only.
"""

from importlib import metadata as _metadata
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # the API is imported on first use: ``import v2xlake.tasks...`` stays light
    from v2xlake.api import CoopDataset, Lake, open

try:
    __version__ = _metadata.version("v2xlake")
except _metadata.PackageNotFoundError:  # a source tree that was never installed
    __version__ = "0+unknown"

__all__ = ["CoopDataset", "Lake", "__version__", "open"]


def __getattr__(name: str) -> Any:
    if name in ("open", "Lake", "CoopDataset"):
        from v2xlake import api

        return getattr(api, name)
    raise AttributeError(f"module 'v2xlake' has no attribute {name!r}")
