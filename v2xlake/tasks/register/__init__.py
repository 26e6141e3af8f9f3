"""Cross-agent LiDAR registration (main paper eq. 1a / 1b): numeric core, GICP backends,
quality control and the Fig. 5 bird's-eye view. The lake stage is :mod:`tasks.register.stage`."""

from v2xlake.tasks.register.backends import (
    Open3dBackend,
    RegistrationBackend,
    SmallGicpBackend,
    make_backend,
)
from v2xlake.tasks.register.bev import render_registration_bev
from v2xlake.tasks.register.config import GicpSection, QualitySection, RegisterConfig
from v2xlake.tasks.register.core import (
    PairResult,
    initial_transform,
    initial_transform_at,
    refine,
    transform_delta,
)
from v2xlake.tasks.register.voxel import voxel_downsample

__all__ = [
    "GicpSection",
    "Open3dBackend",
    "PairResult",
    "QualitySection",
    "RegisterConfig",
    "RegistrationBackend",
    "SmallGicpBackend",
    "initial_transform",
    "initial_transform_at",
    "make_backend",
    "refine",
    "render_registration_bev",
    "transform_delta",
    "voxel_downsample",
]
