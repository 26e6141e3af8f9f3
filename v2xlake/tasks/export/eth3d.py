"""ETH3D-style reconstruction package (CATS-V2V supplementary B.4, eq. 4-5).

Per (clip, agent)::

    <out>/<clip>/<agent>/images/<CAM>/<frame>.png            undistorted (new pinhole K)
    <out>/<clip>/<agent>/calibration_undistorted/cameras.txt PINHOLE, COLMAP text model
                                                 images.txt  world-to-camera qw..tz per image
                                                 points3D.txt (empty, must exist)
    <out>/<clip>/<agent>/lidar/map.ply                        deskewed scans in the world frame
    <out>/<clip>/<agent>/depth/<CAM>/<frame>.npy              float32 metres, 0 = no return
    <out>/<clip>/<agent>/depth_preview/<CAM>/<frame>.png      colourised, for eyes only
    <out>/<clip>/<agent>/images.csv                           image name, stamp (ns, relative)

Camera poses are ``T_world_cam(t) = T_world_ego(t) @ T_ego_cam`` with the ego pose
interpolated (eq. 2a-2c) at the image stamp. The map is every deskewed scan moved with
``T_world_ego(t0) @ T_ego_lidar`` (points inside boxes of moving objects removed, since they
smear), voxel-downsampled; depth maps project it into each image (eq. 4-5) with a z-buffer.
The paper builds its map with Fast-LIO2; here the INS poses play that role, so the depth maps
inherit the INS accuracy, and they are approximate supervision, as the paper says.

Pixel convention: COLMAP puts the centre of the top-left pixel at (0.5, 0.5), OpenCV at
(0, 0), so ``cx, cy`` in cameras.txt are OpenCV's + 0.5, and a point lands in pixel
``floor(u), floor(v)`` of COLMAP's projection.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
from pydantic import BaseModel, ConfigDict, Field

from v2xlake.schemas.errors import ClipError
from v2xlake.schemas.stage import StageReport
from v2xlake.storage.lake import Lake
from v2xlake.storage.reader import CameraCalib, iter_point_frames
from v2xlake.tasks.export.common import Undistorter, file_output, report_step
from v2xlake.tasks.geometry import apply, invert, matrix_to_quat
from v2xlake.tasks.reader import AgentData, ClipData, boxes_matrices, lidar_world_poses, load_clip


class Eth3dConfig(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")

    lidar_sensor: str = "LIDAR_TOP"
    agents: list[str] | None = None
    cameras: list[str] | None = None
    image_stride: int = Field(1, ge=1, description="every n-th camera frame")
    voxel_m: float = Field(0.05, ge=0, description="0 keeps every point")
    remove_moving_above_mps: float | None = 0.5  # None keeps points of moving objects
    depth_maps: bool = True
    min_depth_m: float = 0.5
    max_depth_m: float = 200.0


def depth_map(points_world: np.ndarray, T_cam_world: np.ndarray, fx: float, fy: float,
              cx_colmap: float, cy_colmap: float, width: int, height: int,
              min_depth: float = 0.5, max_depth: float = 1e9) -> np.ndarray:
    """Eq. 4-5 with a z-buffer: nearest depth per pixel, 0 where nothing projects."""
    pc = apply(T_cam_world, points_world)
    z = pc[:, 2]
    ok = (z > min_depth) & (z < max_depth)
    pc, z = pc[ok], z[ok]
    u = np.floor(fx * pc[:, 0] / z + cx_colmap).astype(np.int64)
    v = np.floor(fy * pc[:, 1] / z + cy_colmap).astype(np.int64)
    ok = (u >= 0) & (u < width) & (v >= 0) & (v < height)
    idx, z = v[ok] * width + u[ok], z[ok]
    out = np.zeros(width * height, np.float32)
    if len(idx):
        order = np.lexsort((z, idx))
        idx, z = idx[order], z[order]
        first = np.ones(len(idx), bool)
        first[1:] = idx[1:] != idx[:-1]
        out[idx[first]] = z[first]
    return out.reshape(height, width)


def depth_preview(depth: np.ndarray) -> np.ndarray:
    valid = depth > 0
    img = np.zeros((*depth.shape, 3), np.uint8)
    if valid.any():
        inv = np.zeros_like(depth)
        inv[valid] = 1.0 / depth[valid]
        lo, hi = np.percentile(inv[valid], [2, 98])
        g = np.clip((inv - lo) / max(hi - lo, 1e-9) * 255, 0, 255).astype(np.uint8)
        img = cv2.applyColorMap(g, cv2.COLORMAP_TURBO)
        img[~valid] = 0
    return img


def _map_points(lake: Lake, clip: ClipData, agent: AgentData, cfg: Eth3dConfig
                ) -> tuple[np.ndarray, np.ndarray]:
    sensor = agent.lidar_sensor(cfg.lidar_sensor)
    lf = agent.lidar[sensor]
    t0 = dict(zip(lf.frame_idx.tolist(), lf.points_t_ns.tolist(), strict=True))
    ann = agent.annotations
    chunks: list[np.ndarray] = []
    inten: list[np.ndarray] = []
    for fr in iter_point_frames(lake, clip.clip_id, agent.agent_id, sensor=sensor):
        if not agent.poses.covers(t0[fr.frame_idx]):
            continue
        keep = np.ones(len(fr.xyz), bool)
        if cfg.remove_moving_above_mps is not None and ann.num_rows:
            a = ann.filter(ann["frame_idx"].to_numpy() == fr.frame_idx)
            if a.num_rows:
                v = np.stack([np.nan_to_num(a[c].to_numpy(zero_copy_only=False), nan=np.inf)
                              for c in ("vx", "vy", "vz")], 1)
                moving = np.linalg.norm(v, axis=1) > cfg.remove_moving_above_mps
                B = invert(boxes_matrices(a))
                for k in np.flatnonzero(moving):
                    q = apply(B[k], fr.xyz)
                    half = np.array([a["l"][k].as_py(), a["w"][k].as_py(), a["h"][k].as_py()]) / 2
                    keep &= ~(np.abs(q) <= half).all(1)
        T = lidar_world_poses(agent, sensor, np.array([t0[fr.frame_idx]]), clip.clip_id)[0]
        chunks.append(apply(T, fr.xyz[keep]))
        inten.append(fr.intensity[keep])
    if not chunks:
        raise ClipError(clip.clip_id, "no deskewed scan inside pose coverage",
                        agent_id=agent.agent_id, stage="export_eth3d")
    xyz = np.concatenate(chunks)
    it = np.concatenate(inten).astype(np.float64)
    if it.size and it.max() > 1.0:
        it = it / 255.0
    if cfg.voxel_m > 0:
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
        pcd.colors = o3d.utility.Vector3dVector(np.repeat(np.clip(it, 0, 1)[:, None], 3, 1))
        pcd = pcd.voxel_down_sample(cfg.voxel_m)
        return np.asarray(pcd.points), np.asarray(pcd.colors)[:, 0]
    return xyz, it


def export_eth3d(lake: Lake, clip_ids: Sequence[str], out_dir: Path | str,
                 config: Eth3dConfig = Eth3dConfig()) -> StageReport:  # noqa: B008
    report = StageReport(stage="export_eth3d", clip_id=",".join(clip_ids))
    n_images = 0
    for cid in clip_ids:
        clip = load_clip(lake, cid)
        for aid in config.agents or list(clip.agents):
            if aid not in clip.agents:
                raise ClipError(cid, "unknown agent", agent_id=aid, stage="export_eth3d")
            n_images += _export_agent(lake, clip, clip.agents[aid], Path(out_dir), config,
                                      report)
    report.metrics["images"] = float(n_images)
    return report


def _export_agent(lake: Lake, clip: ClipData, agent: AgentData, out: Path, cfg: Eth3dConfig,
                  report: StageReport) -> int:
    base = out / clip.clip_id / agent.agent_id
    calib_dir = base / "calibration_undistorted"
    calib_dir.mkdir(parents=True, exist_ok=True)
    (base / "lidar").mkdir(exist_ok=True)
    xyz, inten = _map_points(lake, clip, agent, cfg)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
    pcd.colors = o3d.utility.Vector3dVector(np.repeat(np.clip(inten, 0, 1)[:, None], 3, 1))
    ply = base / "lidar" / "map.ply"
    o3d.io.write_point_cloud(str(ply), pcd, write_ascii=False)  # type: ignore[arg-type]
    report.outputs.append(file_output(ply, len(xyz)))
    cams = agent.cameras_calib()
    names = [c for c in (cfg.cameras or sorted(cams)) if c in cams and c in agent.cameras]
    cam_lines, img_lines, csv_lines = [], [], ["name,t_ns"]
    image_id = 0
    for cam_id, ch in enumerate(names, start=1):
        cam: CameraCalib = cams[ch]
        und = Undistorter(cam)
        K = und.K
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5
        cam_lines.append(f"{cam_id} PINHOLE {cam.width} {cam.height} {fx:.10g} {fy:.10g} "
                         f"{cx:.10g} {cy:.10g}")
        frames = agent.cameras[ch]
        sel = np.arange(0, len(frames), cfg.image_stride)
        sel = sel[agent.poses.covers(frames.stamp_ns[sel])]
        if len(sel) == 0:
            continue
        T_wc = agent.T_world_ego(frames.stamp_ns[sel], clip_id=clip.clip_id) @ cam.T_ego_sensor
        T_cw = invert(T_wc)
        for d in ("images", "depth", "depth_preview"):
            (base / d / ch).mkdir(parents=True, exist_ok=True)
        for k, j in enumerate(sel):
            image_id += 1
            name = f"{ch}/{int(frames.frame_idx[j]):06d}.png"
            (base / "images" / name).write_bytes(und.png(lake.read_blob("clean",
                                                                        frames.blob[j])))
            q = matrix_to_quat(T_cw[k, :3, :3])
            t = T_cw[k, :3, 3]
            img_lines.append(f"{image_id} {q[0]:.12g} {q[1]:.12g} {q[2]:.12g} {q[3]:.12g} "
                             f"{t[0]:.12g} {t[1]:.12g} {t[2]:.12g} {cam_id} {name}")
            img_lines.append("")
            csv_lines.append(f"{name},{int(frames.stamp_ns[j])}")
            if cfg.depth_maps:
                dm = depth_map(xyz, T_cw[k], fx, fy, cx, cy, cam.width, cam.height,
                               cfg.min_depth_m, cfg.max_depth_m)
                np.save(base / "depth" / name.replace(".png", ".npy"), dm)
                cv2.imwrite(str(base / "depth_preview" / name), depth_preview(dm))
            report_step(f"eth3d {clip.clip_id}/{agent.agent_id}/{ch}: images", k + 1, len(sel))
    (calib_dir / "cameras.txt").write_text(
        "# Camera list with one line of data per camera:\n"
        "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n" + "\n".join(cam_lines) + "\n")
    (calib_dir / "images.txt").write_text(
        "# Image list with two lines of data per image:\n"
        "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n"
        "#   POINTS2D[] as (X, Y, POINT3D_ID)\n" + "\n".join(img_lines) + "\n")
    (calib_dir / "points3D.txt").write_text(
        "# 3D point list with one line of data per point:\n"
        "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n")
    (base / "images.csv").write_text("\n".join(csv_lines) + "\n")
    for f in ("cameras.txt", "images.txt", "points3D.txt"):
        report.outputs.append(file_output(calib_dir / f))
    return image_id
