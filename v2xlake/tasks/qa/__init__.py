"""The qa stage: numeric core in core.py, the lake stage in stage.py."""
