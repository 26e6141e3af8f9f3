"""The QA stage: sync and completeness checks of the raw zone against each sensor's model."""

from v2xlake.schemas.stage import Stage, tables
from v2xlake.tasks.qa.core import QaConfig, run_qa

QA = Stage(
    name="qa", config_model=QaConfig,
    reads=tables("raw", "clips", "agents", "sensors", "calibrated_sensors", "lidar_frames",
                 "camera_frames", "ins", "ego_poses", "imu", "gnss"),
    owns=tables("raw", "qa_checks"), run=run_qa,
    doc="timing, gaps and coverage checks; an error-severity finding quarantines the clip")
