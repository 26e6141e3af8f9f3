"""Numeric core of temporal alignment: box geometry, projection, methods, metrics, overlay."""
