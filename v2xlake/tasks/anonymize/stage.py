"""The anonymize stage: the raw zone -> the clean zone (blurred images, relative time,
local ENU); the only way data reaches the clean zone."""

from v2xlake.schemas.stage import Stage, tables
from v2xlake.schemas.tables import INGEST_TABLES, RAW_ONLY_TABLES
from v2xlake.tasks.anonymize.run import AnonymizeConfig, run_anonymize

_CLEAN = tuple(t for t in INGEST_TABLES if t not in RAW_ONLY_TABLES)

ANONYMIZE = Stage(
    name="anonymize", config_model=AnonymizeConfig,
    reads=tables("raw", *INGEST_TABLES, "qa_checks"),
    owns=tables("clean", *_CLEAN, "qa_checks", "anonymization_audit"),
    run=run_anonymize, atomic=False,  # stages the whole clean zone and publishes it itself
    doc="faces and plates blurred, time made relative, positions made local")
