"""Every export format behind one :class:`v2xlake.schemas.stage.Exporter` shape.

The format modules keep the signatures natural to each format (per clip for BEV rasters
and ROS bags, over many clips with splits for nuScenes and OpenCOOD); this module is the
one place that adapts them, so the release flow and the CLI call every format alike and
a format's parameters are one config model, settable like a stage's.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pydantic import BaseModel

from v2xlake.schemas.stage import StageReport
from v2xlake.storage.lake import Lake
from v2xlake.tasks.export.bev import BevConfig, export_bev
from v2xlake.tasks.export.common import report_step
from v2xlake.tasks.export.eth3d import Eth3dConfig, export_eth3d
from v2xlake.tasks.export.nuscenes import NuScenesExportConfig, export_nuscenes
from v2xlake.tasks.export.opencood import OpenCoodConfig, export_opencood
from v2xlake.tasks.export.rosbag import RosbagExportConfig, export_rosbag
from v2xlake.tasks.export.scene_transfer import SceneTransferConfig, export_scene_transfer


@dataclass(frozen=True)
class FormatExporter:
    """Adapter from one format's entry point to the common ``Exporter`` call."""

    name: str
    config_model: type[BaseModel]
    call: Callable[[Lake, list[str], Path, Any, dict[str, str] | None], list[StageReport]]

    def export(self, lake: Lake, clip_ids: list[str], out: str | Path, config: BaseModel,
               splits: dict[str, str] | None = None) -> list[StageReport]:
        cfg = self.config_model.model_validate(
            config.model_dump() if isinstance(config, BaseModel) else config or {})
        return self.call(lake, list(clip_ids), Path(out), cfg, splits)


def _nuscenes(lake: Lake, ids: list[str], out: Path, cfg: NuScenesExportConfig,
              splits: dict[str, str] | None) -> list[StageReport]:
    if splits:
        cfg = cfg.model_copy(update={"splits": dict(splits)})
    return [export_nuscenes(lake, ids, out, cfg)]


def _opencood(lake: Lake, ids: list[str], out: Path, cfg: OpenCoodConfig,
              splits: dict[str, str] | None) -> list[StageReport]:
    return [export_opencood(lake, ids, out, splits=dict(splits) if splits else None, config=cfg)]


def _eth3d(lake: Lake, ids: list[str], out: Path, cfg: Eth3dConfig,
           splits: dict[str, str] | None) -> list[StageReport]:
    return [export_eth3d(lake, ids, out, cfg)]


def _scene_transfer(lake: Lake, ids: list[str], out: Path, cfg: SceneTransferConfig,
                    splits: dict[str, str] | None) -> list[StageReport]:
    return [export_scene_transfer(lake, ids, out, cfg)]


def _per_clip(fmt: str, ids: list[str], one: Callable[[str], StageReport]) -> list[StageReport]:
    """A per-clip format over several clips, one progress step per clip done."""
    reports = []
    for n, cid in enumerate(ids, start=1):
        reports.append(one(cid))
        report_step(f"{fmt}: clips", n, len(ids))
    return reports


def _bev(lake: Lake, ids: list[str], out: Path, cfg: BevConfig,
         splits: dict[str, str] | None) -> list[StageReport]:
    return _per_clip("bev", ids, lambda cid: export_bev(lake, cid, out, cfg))


def _rosbag(lake: Lake, ids: list[str], out: Path, cfg: RosbagExportConfig,
            splits: dict[str, str] | None) -> list[StageReport]:
    return _per_clip("rosbag", ids, lambda cid: export_rosbag(lake, cid, None, out, config=cfg))


EXPORTERS: dict[str, FormatExporter] = {e.name: e for e in (
    FormatExporter("nuscenes", NuScenesExportConfig, _nuscenes),
    FormatExporter("eth3d", Eth3dConfig, _eth3d),
    FormatExporter("rosbag", RosbagExportConfig, _rosbag),
    FormatExporter("opencood", OpenCoodConfig, _opencood),
    FormatExporter("bev", BevConfig, _bev),
    FormatExporter("scene-transfer", SceneTransferConfig, _scene_transfer),
)}
