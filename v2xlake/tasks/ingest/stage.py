"""The ingest stage: a clip folder (bags + clip.yaml) -> the raw zone."""

from v2xlake.schemas.stage import Stage, tables
from v2xlake.schemas.tables import INGEST_TABLES
from v2xlake.tasks.ingest.run import IngestConfig, run_ingest

INGEST = Stage(
    name="ingest", config_model=IngestConfig, input="clip_dir",
    reads=(), owns=tables("raw", *INGEST_TABLES), run=run_ingest, atomic=False,
    doc="bags -> raw tables (points with per-point time, images, poses, calibration)")
