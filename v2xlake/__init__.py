"""v2xlake: cooperative-perception driving recordings into a queryable, releasable lake.

The repository keeps its layers at the top level (``schemas/``, ``tasks/``, ``storage/``,
``flows/``, see DESIGN.md); this package maps them as ``v2xlake.schemas`` etc. (relative
symlinks in the source tree, real folders in a built wheel), so installing v2xlake claims one
import name only, never ``tasks`` or ``schemas`` in a user's environment.
"""

from importlib import metadata as _metadata

try:
    __version__ = _metadata.version("v2xlake")
except _metadata.PackageNotFoundError:  # a source tree that was never installed
    __version__ = "0+unknown"

__all__ = ["__version__"]
