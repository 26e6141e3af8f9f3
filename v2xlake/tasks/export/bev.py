"""BEV rasters (CATS-V2V supplementary B.2): height, occupancy and intensity layers.

Points are the deskewed scans of every selected agent moved into the clip world frame with
the interpolated LiDAR pose at each scan start (``T_world_ego(t0) @ T_ego_lidar``), so all
passes share one grid. Layers: max z (height), point count > threshold (occupancy) and mean
intensity. Images are north-up: row 0 is the largest y.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from v2xlake.schemas.errors import ClipError
from v2xlake.schemas.stage import StageReport
from v2xlake.storage.lake import Lake
from v2xlake.storage.reader import iter_point_frames
from v2xlake.tasks.export.common import file_output, report_step
from v2xlake.tasks.geometry import apply
from v2xlake.tasks.reader import lidar_world_poses, load_clip


class BevConfig(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")

    resolution_m: float = Field(0.2, gt=0)
    margin_m: float = Field(40.0, ge=0, description="grid extends this far around trajectories")
    agents: list[str] | None = None  # None = every agent of the clip
    frame_stride: int = Field(1, ge=1)
    min_points: int = Field(1, ge=1, description="points per cell for 'occupied'")
    z_range: tuple[float, float] = Field((-5.0, 10.0), description=(
        "points kept, in metres relative to the ego height at the scan (world z is "
        "ellipsoidal height, so an absolute band would depend on the site)"))
    sensor: str = "LIDAR_TOP"


@dataclass
class BevGrid:
    """Accumulator over a fixed grid: x0/y1 = world coords of the top-left corner."""

    x0: float
    y1: float
    res: float
    width: int
    height: int

    def __post_init__(self) -> None:
        n = self.width * self.height
        self.count = np.zeros(n, np.int64)
        self.isum = np.zeros(n, np.float64)
        self.zmax = np.full(n, -np.inf)

    @classmethod
    def around(cls, xy_min: np.ndarray, xy_max: np.ndarray, res: float) -> BevGrid:
        x0 = float(np.floor(xy_min[0] / res) * res)
        y0 = float(np.floor(xy_min[1] / res) * res)
        w = int(np.ceil((xy_max[0] - x0) / res)) + 1
        h = int(np.ceil((xy_max[1] - y0) / res)) + 1
        return cls(x0, y0 + h * res, res, w, h)

    def add(self, xyz: np.ndarray, intensity: np.ndarray) -> None:
        col = np.floor((xyz[:, 0] - self.x0) / self.res).astype(np.int64)
        row = np.floor((self.y1 - xyz[:, 1]) / self.res).astype(np.int64)
        ok = (col >= 0) & (col < self.width) & (row >= 0) & (row < self.height)
        idx = row[ok] * self.width + col[ok]
        n = self.width * self.height
        self.count += np.bincount(idx, minlength=n)
        self.isum += np.bincount(idx, weights=intensity[ok], minlength=n)
        np.maximum.at(self.zmax, idx, xyz[ok, 2])

    def layers(self, min_points: int = 1) -> dict[str, np.ndarray]:
        shape = (self.height, self.width)
        cnt = self.count.reshape(shape)
        with np.errstate(invalid="ignore", divide="ignore"):
            inten = np.where(cnt > 0, self.isum.reshape(shape) / np.maximum(cnt, 1), np.nan)
        height = np.where(cnt > 0, self.zmax.reshape(shape), np.nan)
        return {"height": height.astype(np.float32), "occupancy": (cnt >= min_points),
                "intensity": inten.astype(np.float32), "count": cnt.astype(np.int32)}

    def meta(self) -> dict[str, object]:
        return {"resolution_m": self.res, "width": self.width, "height": self.height,
                "x_min": self.x0, "y_max": self.y1,
                "x_max": self.x0 + self.width * self.res, "y_min": self.y1 - self.height * self.res,
                "frame": "clip world (local ENU), north-up image",
                "pixel_of_xy": "col = floor((x - x_min) / res), row = floor((y_max - y) / res)"}


def to_png(layer: np.ndarray, kind: str) -> np.ndarray:
    """8-bit visualisation of a layer (height colourised, others grey)."""
    if kind == "occupancy":
        return (layer.astype(np.uint8) * 255)
    valid = np.isfinite(layer)
    out = np.zeros(layer.shape, np.uint8)
    if valid.any():
        lo, hi = np.percentile(layer[valid], [1, 99])
        out[valid] = np.clip((layer[valid] - lo) / max(hi - lo, 1e-6) * 254 + 1, 1, 255)
    if kind == "height":
        col = cv2.applyColorMap(out, cv2.COLORMAP_VIRIDIS)
        col[~valid] = 0
        return col
    return out


def accumulate(lake: Lake, clip_id: str, config: BevConfig,
               grid: BevGrid | None = None) -> tuple[BevGrid, int]:
    """Fuse the clip's deskewed scans into a grid (built around the trajectories if None)."""
    clip = load_clip(lake, clip_id)
    agents = config.agents or list(clip.agents)
    if grid is None:
        xy = np.concatenate([clip.agents[a].poses.xyz[:, :2] for a in agents])
        grid = BevGrid.around(xy.min(0) - config.margin_m, xy.max(0) + config.margin_m,
                              config.resolution_m)
    n = 0
    for aid in agents:
        if aid not in clip.agents:
            raise ClipError(clip_id, "unknown agent", agent_id=aid, stage="export_bev")
        agent = clip.agents[aid]
        sensor = agent.lidar_sensor(config.sensor)
        lf = agent.lidar[sensor]
        sel = lf.frame_idx[::config.frame_stride]
        t0 = dict(zip(lf.frame_idx.tolist(), lf.points_t_ns.tolist(), strict=True))
        for k, fr in enumerate(iter_point_frames(lake, clip_id, aid, sensor=sensor,
                                                 frames=sel.tolist()), start=1):
            T = lidar_world_poses(agent, sensor, np.array([t0[fr.frame_idx]]), clip_id)[0]
            w = apply(T, fr.xyz)
            z_ego = float(agent.T_world_ego(t0[fr.frame_idx], clip_id=clip_id)[0, 2, 3])
            dz = w[:, 2] - z_ego
            keep = (dz >= config.z_range[0]) & (dz <= config.z_range[1])
            grid.add(w[keep], fr.intensity[keep])
            n += int(keep.sum())
            report_step(f"bev {clip_id}/{aid}: scans", k, len(sel))
    return grid, n


def export_bev(lake: Lake, clip_id: str, out_dir: Path | str,
               config: BevConfig = BevConfig()) -> StageReport:  # noqa: B008
    out = Path(out_dir) / clip_id
    out.mkdir(parents=True, exist_ok=True)
    grid, n = accumulate(lake, clip_id, config)
    layers = grid.layers(config.min_points)
    report = StageReport(stage="export_bev", clip_id=clip_id)
    for name in ("height", "occupancy", "intensity"):
        npy = out / f"{name}.npy"
        np.save(npy, layers[name])
        png = out / f"{name}.png"
        cv2.imwrite(str(png), to_png(layers[name], name))
        report.outputs += [file_output(npy), file_output(png)]
        report.images.append(str(png))
    np.save(out / "count.npy", layers["count"])
    meta = out / "grid.json"
    meta.write_text(json.dumps({**grid.meta(), "clip_id": clip_id, "n_points": n,
                                "config": config.model_dump(mode="json")}, indent=2))
    report.outputs.append(file_output(meta))
    report.metrics = {"n_points": float(n), "occupied_cells": float(layers["occupancy"].sum()),
                      "width": float(grid.width), "height": float(grid.height)}
    return report
