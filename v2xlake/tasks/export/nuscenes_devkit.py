"""Make nuscenes-devkit 1.2.0's ``render_sample`` work under NumPy 2.

The devkit's ``NuScenesExplorer.render_ego_centric_map`` (the map underlay that
``NuScenes.render_sample`` and ``render_sample_data`` draw under every LiDAR view) calls
``int()`` on the 1-element arrays that ``MapMask.to_pixel_coords`` returns; NumPy 2 (2.4 in
the shipped environment) refuses that (``TypeError: only 0-dimensional arrays can be
converted to Python scalars``), for the real nuScenes as for ours. Nothing in the data can
avoid it, so :func:`fix_render_for_numpy2` replaces that one method with the devkit's own
code, changed only where it takes the pixel coordinates' first element.

The method below is adapted from nuscenes-devkit 1.2.0 (``nuscenes/nuscenes.py``,
``NuScenesExplorer.render_ego_centric_map``), Copyright 2018 Motional, licensed under the
Apache License, Version 2.0 (http://www.apache.org/licenses/LICENSE-2.0).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

_PATCHED = "_v2xlake_numpy2_fix"


def _render_ego_centric_map(self: Any, sample_data_token: str, axes_limit: float = 40,
                            ax: Any = None) -> None:
    """Render the map centred on the ego pose (devkit 1.2.0, pixel coordinates fixed)."""
    import matplotlib.pyplot as plt
    from PIL import Image
    from pyquaternion import Quaternion

    def crop_image(image: np.ndarray, x_px: int, y_px: int, axes_limit_px: int) -> np.ndarray:
        x_min = int(x_px - axes_limit_px)
        x_max = int(x_px + axes_limit_px)
        y_min = int(y_px - axes_limit_px)
        y_max = int(y_px + axes_limit_px)
        return image[y_min:y_max, x_min:x_max]

    sd_record = self.nusc.get("sample_data", sample_data_token)
    sample = self.nusc.get("sample", sd_record["sample_token"])
    scene = self.nusc.get("scene", sample["scene_token"])
    log = self.nusc.get("log", scene["log_token"])
    map_ = self.nusc.get("map", log["map_token"])
    map_mask = map_["mask"]
    pose = self.nusc.get("ego_pose", sd_record["ego_pose_token"])

    px, py = map_mask.to_pixel_coords(pose["translation"][0], pose["translation"][1])
    scaled_limit_px = int(axes_limit * (1.0 / map_mask.resolution))
    mask_raster = map_mask.mask()
    # the fix: the first (only) element of each coordinate array, not the array
    cropped = crop_image(mask_raster, int(np.ravel(px)[0]), int(np.ravel(py)[0]),
                         int(scaled_limit_px * math.sqrt(2)))

    ypr_rad = Quaternion(pose["rotation"]).yaw_pitch_roll
    yaw_deg = -math.degrees(ypr_rad[0])
    rotated_cropped = np.array(Image.fromarray(cropped).rotate(yaw_deg))
    ego_centric_map = crop_image(rotated_cropped, int(rotated_cropped.shape[1] / 2),
                                 int(rotated_cropped.shape[0] / 2), scaled_limit_px)
    if ax is None:
        _, ax = plt.subplots(1, 1, figsize=(9, 9))
    ego_centric_map[ego_centric_map == map_mask.foreground] = 125
    ego_centric_map[ego_centric_map == map_mask.background] = 255
    ax.imshow(ego_centric_map, extent=[-axes_limit, axes_limit, -axes_limit, axes_limit],
              cmap="gray", vmin=0, vmax=255)


def require_devkit() -> None:
    """Fail with the way to install nuscenes-devkit when it is missing. It is no dependency
    of v2xlake: every release pins ``numpy<2`` (or older matplotlib / Shapely), which cannot
    resolve beside the NumPy 2 that pyarrow needs; the project's install puts it beside the
    venv (``.venv/test-oracles``), where it runs fine on NumPy 2 for what is used here."""
    try:
        import nuscenes  # noqa: F401
    except ImportError as e:
        raise ImportError(
            "nuscenes-devkit is not installed: it is optional (it pins numpy<2). Install it "
            "beside the environment with `pip install --no-deps --target .venv/test-oracles "
            "-r requirements-oracles.lock` and put that folder on PYTHONPATH, or "
            "`pip install --no-deps nuscenes-devkit pyquaternion`") from e


def fix_render_for_numpy2() -> bool:
    """Install the fixed map underlay in the devkit (idempotent). Returns True when it was
    needed: the devkit's own method fails under this NumPy."""
    require_devkit()
    from nuscenes.nuscenes import NuScenesExplorer

    if getattr(NuScenesExplorer.render_ego_centric_map, _PATCHED, False):
        return True
    try:
        int(np.zeros(1, np.int32))  # what the devkit does with a pixel coordinate
        return False  # NumPy < 2.x still converts a 1-element array: nothing to fix
    except TypeError:
        pass
    setattr(_render_ego_centric_map, _PATCHED, True)
    NuScenesExplorer.render_ego_centric_map = _render_ego_centric_map
    return True
