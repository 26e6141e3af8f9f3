"""The deskew stage (``stage.py``: config, chunks, the lake). Its numeric core, per-point motion
compensation, is :mod:`v2xlake.tasks.motion`, shared with register (re-deskew) and align."""
