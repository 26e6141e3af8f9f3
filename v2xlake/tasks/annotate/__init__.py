"""The annotate stage: ``config.py`` its parameters, ``consistency.py`` the checks on arrays
(world-frame boxes, cross-agent distances, links), ``stage.py`` the lake I/O and the
``ANNOTATE`` Stage object."""
