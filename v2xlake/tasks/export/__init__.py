"""Format conversion from the clean zone (issue 6): nuScenes, ETH3D-style, ROS 2 bags,
OpenCOOD / V2V4Real, BEV rasters and scene-transfer pairs. Exports read only ``clean``."""

from v2xlake.tasks.export.bev import BevConfig, export_bev
from v2xlake.tasks.export.eth3d import Eth3dConfig, export_eth3d
from v2xlake.tasks.export.nuscenes import NuScenesExportConfig, detection_eval, export_nuscenes
from v2xlake.tasks.export.opencood import OpenCoodConfig, export_opencood
from v2xlake.tasks.export.rosbag import RosbagExportConfig, convert_bag, export_rosbag
from v2xlake.tasks.export.scene_transfer import SceneTransferConfig, export_scene_transfer

__all__ = [
    "BevConfig",
    "Eth3dConfig",
    "NuScenesExportConfig",
    "OpenCoodConfig",
    "RosbagExportConfig",
    "SceneTransferConfig",
    "convert_bag",
    "detection_eval",
    "export_bev",
    "export_eth3d",
    "export_nuscenes",
    "export_opencood",
    "export_rosbag",
    "export_scene_transfer",
]
