"""The annotate stage: boxes made complete and consistent (num_lidar_pts, instances, world
frame, links)."""

from v2xlake.schemas.stage import Stage, tables
from v2xlake.tasks.annotate.core import AnnotateConfig, run_annotate

ANNOTATE = Stage(
    name="annotate", config_model=AnnotateConfig,
    reads=tables("clean", "clips", "agents", "ego_poses", "calibrated_sensors", "lidar_frames",
                 "annotations", "lidar_points_deskewed", "deskew_frames", "registrations",
                 "calibration_refined"),
    owns=tables("clean", "annotations_world", "instances"), run=run_annotate,
    doc="points per box, global instances, world-frame boxes, link and cross-agent checks")
