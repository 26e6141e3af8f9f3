"""v2xlake: cooperative-perception driving recordings into a queryable, releasable lake.

The repository keeps its layers at the top level (``schemas/``, ``tasks/``, ``storage/``,
``flows/``, see DESIGN.md); this package maps them as ``v2xlake.schemas`` etc. (relative
symlinks in the source tree, real folders in a built wheel), so installing v2xlake claims one
import name only, never ``tasks`` or ``schemas`` in a user's environment.
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
