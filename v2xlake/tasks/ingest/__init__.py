"""Ingest: a clip folder (clip.yaml + one bag per agent) -> landing copy + raw-zone tables."""

from v2xlake.tasks.ingest.run import IngestConfig, clip_inputs, run_ingest

__all__ = ["IngestConfig", "clip_inputs", "run_ingest"]
