"""Align stage: stamp-, frame- and target-based LiDAR-camera temporal alignment (Sec. 5).

For every agent, LiDAR frame and camera this stage decides which camera frame goes with the
scan (stamp / frame) or with each annotated object in it (target), writes that decision to
the clean ``alignments`` table, and, when the true 2D boxes are known (simulated clips:
``truth/boxes2d.parquet``), measures each method like the paper's Tab. 4: the annotated 3D
boxes projected with the method vs the true 2D boxes of the associated image (average IoU,
Recall@IoU 0.3/0.5/0.7, mean centre offset in pixels; also per camera and split into
static / moving objects). One overlay PNG per agent (the frame and camera with the most true
boxes) shows the three methods' boxes, the true boxes and the LiDAR points on the images the
methods chose (two panels when the stamp method chose another image than the frame method).

The numeric core is ``methods.py`` (the three methods), ``boxes.py``, ``metrics.py`` and
``overlay.py`` (pure, on arrays), the parameters ``config.py``; this module reads and writes the
lake and defines ``ALIGN``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pyarrow as pa
from pydantic import BaseModel

from v2xlake.schemas.arrow import rows_to_table
from v2xlake.schemas.calibration import CameraIntrinsics, DistortionModel
from v2xlake.schemas.errors import ClipError
from v2xlake.schemas.stage import OutputFile, Stage, StageReport, tables
from v2xlake.schemas.tables import AlignmentRow
from v2xlake.storage.files import read_parquet
from v2xlake.storage.lake import Lake
from v2xlake.storage.reader import CLIP_TABLES, CameraCalib, iter_point_frames
from v2xlake.tasks.align import DECLARATION
from v2xlake.tasks.align.boxes import BoxArray
from v2xlake.tasks.align.config import AlignConfig, AssociationConfig
from v2xlake.tasks.align.methods import (
    METHODS,
    Association,
    CameraStream,
    LidarScan,
    align_frame,
    align_stamp,
    align_target,
    compensate_points,
    estimate_velocities,
    object_points,
)
from v2xlake.tasks.align.metrics import center_offset_px, summarize
from v2xlake.tasks.align.overlay import OverlayBoxes, Panel, render_overlay
from v2xlake.tasks.geometry import apply, compose, invert, iou_xyxy
from v2xlake.tasks.interpolate import PoseCoverageError
from v2xlake.tasks.projection import Camera, points_in_fov, project_points
from v2xlake.tasks.reader import AgentData, load_posed_clip

STAGE = "align"


# ------------------------------------------------------------------------------ truth
TruthKey = tuple[str, str, int, str]  # agent, camera, camera frame_idx, instance


def load_truth_boxes(truth_dir: Path, min_px: float = 0.0, min_pixels: int = 0,
                     box: Literal["amodal", "visible"] = "amodal") -> dict[TruthKey, np.ndarray]:
    """True 2D object boxes per (agent, camera, camera frame index, instance).

    Reads the simulator's ``truth/boxes2d.parquet`` (kind "object" rows). The amodal box
    (the whole object's extent, clipped to the image) is what a projected 3D box should
    match; the visible box (unoccluded pixels) is kept as an option. Objects with fewer
    than ``min_pixels`` visible pixels or a visible side under ``min_px`` are left out, as
    a labeller would not draw them.
    """
    path = Path(truth_dir) / "boxes2d.parquet"
    if not path.exists():
        raise FileNotFoundError(f"no true 2D boxes at {path}")
    t = read_parquet(path)
    names = set(t.column_names)
    cam_col = next((c for c in ("camera", "sensor") if c in names), None)
    agent_col = next((c for c in ("agent_id", "agent") if c in names), None)
    if cam_col is None or agent_col is None or not {"frame_idx", "instance_id"} <= names:
        raise ValueError(f"{path}: unexpected columns {sorted(names)}")
    cols = t.to_pydict()
    n = t.num_rows
    kind = cols.get("kind", ["object"] * n)
    npx = cols.get("n_pixels", [None] * n)
    amodal = {"ax0", "ay0", "ax1", "ay1"} <= names and box == "amodal"
    out: dict[TruthKey, np.ndarray] = {}
    for i in range(n):
        if kind[i] != "object" or cols["instance_id"][i] is None:
            continue
        if npx[i] is not None and npx[i] < min_pixels:
            continue
        vis = np.array([cols[c][i] for c in ("x0", "y0", "x1", "y1")], dtype=np.float64)
        if min(vis[2] - vis[0], vis[3] - vis[1]) < min_px:
            continue
        b = vis
        if amodal:
            am = np.array([cols[c][i] for c in ("ax0", "ay0", "ax1", "ay1")], dtype=np.float64)
            if np.all(np.isfinite(am)) and am[2] > am[0] and am[3] > am[1]:
                b = am
        key = (str(cols[agent_col][i]), str(cols[cam_col][i]), int(cols["frame_idx"][i]),
               str(cols["instance_id"][i]))
        out[key] = b
    return out


# ------------------------------------------------------------------------------ helpers
def _intrinsics(c: CameraCalib) -> CameraIntrinsics:
    model = c.distortion_model or "none"
    dist = list(c.distortion)
    if model == "none" or not any(dist):
        model, dist = "none", []
    return CameraIntrinsics(
        width=int(c.width), height=int(c.height), fx=float(c.K[0, 0]), fy=float(c.K[1, 1]),
        cx=float(c.K[0, 2]), cy=float(c.K[1, 2]), distortion_model=DistortionModel(model),
        distortion=dist,
    )


def _boxes_of(ann: pa.Table) -> BoxArray:
    def col(name: str) -> np.ndarray:
        return np.asarray(ann[name].to_numpy(zero_copy_only=False), dtype=np.float64)

    vel = np.stack([
        np.asarray([np.nan if v is None else v for v in ann[c].to_pylist()], dtype=np.float64)
        for c in ("vx", "vy", "vz")
    ], axis=1) if ann.num_rows else np.zeros((0, 3))
    return BoxArray(
        instance_id=np.asarray(ann["instance_id"].to_pylist(), dtype=object),
        center=np.stack([col("cx"), col("cy"), col("cz")], 1),
        size=np.stack([col("w"), col("l"), col("h")], 1),
        quat=np.stack([col("qw"), col("qx"), col("qy"), col("qz")], 1),
        t_ns=ann["t_ns"].to_numpy().astype(np.int64),
        velocity=vel,
    )


_EMPTY_BOXES = BoxArray(np.zeros(0, object), np.zeros((0, 3)), np.ones((0, 3)),
                        np.zeros((0, 4)), np.zeros(0, np.int64), np.zeros((0, 3)))


@dataclass
class _Eval:
    iou: list[float] = field(default_factory=list)
    offset: list[float] = field(default_factory=list)


@dataclass
class _OverlayPick:
    score: tuple[int, int] = (-1, -1)
    data: dict[str, Any] | None = None


def _fill_velocities(agent: AgentData, lidar_sensor: str, ann: pa.Table,
                     clip_id: str) -> dict[int, np.ndarray]:
    """Velocity (L0 axes) per annotation row index of this agent, from its track where the
    annotation has none; rows with a velocity keep it."""
    if ann.num_rows == 0:
        return {}
    boxes = _boxes_of(ann)
    frames = ann["frame_idx"].to_numpy().astype(np.int64)
    lf = agent.lidar[lidar_sensor]
    t0_of = dict(zip(lf.frame_idx.tolist(), lf.t_start_ns.tolist(), strict=True))
    T_el = agent.sensors[lidar_sensor].T_ego_sensor
    t0 = np.array([t0_of[int(f)] for f in frames], dtype=np.int64)
    T_w_l0 = agent.T_world_ego(t0, clip_id=clip_id) @ T_el
    cw = np.einsum("mij,mj->mi", T_w_l0[:, :3, :3], boxes.center) + T_w_l0[:, :3, 3]
    v_w = estimate_velocities(boxes.instance_id, boxes.t_ns, cw)
    v_l0 = np.einsum("mji,mj->mi", T_w_l0[:, :3, :3], v_w)  # R^T v
    out: dict[int, np.ndarray] = {}
    missing = ~np.isfinite(boxes.velocity).all(axis=1)
    for r in np.flatnonzero(missing):
        out[int(r)] = v_l0[r]
    return out


# ------------------------------------------------------------------------------ stage
def run_align(lake: Lake, clip_id: str, config: AlignConfig = AlignConfig(),  # noqa: B008
              truth_dir: Path | None = None) -> StageReport:
    """Associate camera frames with LiDAR frames / objects by the three methods; evaluate."""
    clip = load_posed_clip(lake, clip_id, STAGE, "associating camera and LiDAR frames "
                           "across agents needs their poses")
    if isinstance(clip, StageReport):
        return clip
    params = config.association
    truth = (load_truth_boxes(truth_dir, config.truth.min_box_px, config.truth.min_pixels,
                              config.truth.box) if truth_dir else None)
    report = StageReport(stage=STAGE, clip_id=clip_id)
    evals: dict[str, _Eval] = {m: _Eval() for m in METHODS}
    max_dt = int(config.association.max_camera_dt_ms * 1e6)
    n_skipped = 0

    for aid, agent in clip.agents.items():
        if config.lidar_sensor not in agent.lidar:
            report.notes.append(f"{aid}: no {config.lidar_sensor} frames, skipped")
            continue
        if config.lidar_sensor not in agent.sensors:
            raise ClipError(clip_id, f"no calibration for {config.lidar_sensor}",
                            agent_id=aid, stage=STAGE)
        T_el = agent.sensors[config.lidar_sensor].T_ego_sensor
        streams: list[CameraStream] = []
        for name, calib in sorted(agent.cameras_calib().items()):
            if config.cameras is not None and name not in config.cameras:
                continue
            frames = agent.cameras.get(name)
            if frames is None or len(frames) == 0:
                continue
            try:
                intr = _intrinsics(calib)
            except ValueError as e:
                raise ClipError(clip_id, f"camera {name} intrinsics: {e}", agent_id=aid,
                                stage=STAGE) from e
            streams.append(CameraStream(Camera(name, intr, calib.T_ego_sensor),
                                        frames.frame_idx, frames.stamp_ns.astype(np.int64)))
        if not streams:
            report.notes.append(f"{aid}: no camera frames, skipped")
            continue
        lf = agent.lidar[config.lidar_sensor]
        t0_of = dict(zip(lf.frame_idx.tolist(), lf.t_start_ns.tolist(), strict=True))
        period = int(np.median(np.diff(lf.t_start_ns))) if len(lf) > 1 else 100_000_000
        ann = agent.annotations
        if ann.num_rows:
            ann = ann.filter(pa.compute.equal(ann["sensor"], config.lidar_sensor))
        try:
            vel_fill = (_fill_velocities(agent, config.lidar_sensor, ann, clip_id)
                        if config.association.velocity_from_track and ann.num_rows else {})
        except ClipError as e:
            raise ClipError(clip_id, e.reason, agent_id=aid, stage=STAGE) from e
        ann_frames = ann["frame_idx"].to_numpy().astype(np.int64) if ann.num_rows else \
            np.zeros(0, np.int64)
        rows: list[AlignmentRow] = []
        pick = _OverlayPick()
        for pf in iter_point_frames(lake, clip_id, aid, sensor=config.lidar_sensor):
            if pf.frame_idx not in t0_of:
                continue
            t0 = int(t0_of[pf.frame_idx])
            scan = LidarScan(pf.frame_idx, t0, pf.xyz.astype(np.float64), pf.t_ns, period)
            sel = np.flatnonzero(ann_frames == pf.frame_idx)
            boxes = _EMPTY_BOXES
            if sel.size:
                boxes = _boxes_of(ann.take(sel))
                vel = boxes.velocity.copy()
                for k, r in enumerate(sel):
                    if int(r) in vel_fill:
                        vel[k] = vel_fill[int(r)]
                boxes = replace(boxes, velocity=vel)
            obj_idx = object_points(scan, boxes, params) if len(boxes) else None
            for st in streams:
                try:
                    res = {
                        "stamp": align_stamp(scan, boxes, st, T_el),
                        "frame": align_frame(scan, boxes, st, agent.poses, T_el, params),
                        "target": align_target(scan, boxes, st, agent.poses, T_el, params,
                                               obj_idx),
                    }
                except PoseCoverageError as e:
                    n_skipped += 1
                    report.notes.append(f"{aid} frame {pf.frame_idx} {st.camera.name}: {e}")
                    continue
                rows.extend(_rows_and_eval(clip_id, aid, scan, boxes, st, res, truth, evals,
                                           max_dt, pick))
        if rows:
            table = rows_to_table(AlignmentRow, list[BaseModel](rows))
            path, n = lake.write_table("clean", "alignments", table, clip_id=clip_id,
                                       agent_id=aid, name="part")
            report.outputs.append(OutputFile(path=path, rows=n))
        if config.overlay and pick.data is not None:
            report.images.append(_write_overlay(lake, clip_id, aid, agent, T_el, pick.data,
                                                params))

    for name, ev in sorted(evals.items()):
        if not ev.iou:
            continue
        summary = summarize(np.array(ev.iou), np.array(ev.offset))
        if name not in METHODS:  # per camera: the headline numbers only
            summary = {k: summary[k] for k in ("mean_iou", "center_offset_px", "n_boxes")}
        for key, v in summary.items():
            report.metrics[f"{name}.{key}"] = v
    report.metrics["n_skipped_pose_coverage"] = float(n_skipped)
    if truth is None:
        report.notes.append("no truth_dir: associations written, no Tab. 4 evaluation")
    return report


def _rows_and_eval(
    clip_id: str, aid: str, scan: LidarScan, boxes: BoxArray, st: CameraStream,
    res: dict[str, Association], truth: dict[TruthKey, np.ndarray] | None,
    evals: dict[str, _Eval], max_dt: int, pick: _OverlayPick,
) -> list[AlignmentRow]:
    rows: list[AlignmentRow] = []
    cam = st.camera.name
    per_method: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    for m, a in res.items():
        m_boxes = len(boxes)
        t_cam = st.stamp_ns[a.frame_pos] if m_boxes else np.zeros(0, np.int64)
        ok = np.abs(t_cam - a.points_t_ns) <= max_dt if m_boxes else np.zeros(0, bool)
        iou = np.full(m_boxes, np.nan)
        off = np.full(m_boxes, np.nan)
        has_truth = np.zeros(m_boxes, bool)
        if truth is not None:
            for k in range(m_boxes):
                key = (aid, cam, int(st.frame_idx[a.frame_pos[k]]), str(boxes.instance_id[k]))
                tb = truth.get(key)
                if tb is None or not ok[k]:
                    continue
                has_truth[k] = True
                iou[k] = iou_xyxy(a.boxes2d[k], tb, paired=True)[0]
                off[k] = center_offset_px(a.boxes2d[k], tb)[0]
                v = boxes.velocity[k]
                motion = "moving" if np.isfinite(v).all() and np.linalg.norm(v) > 0.5 \
                    else "static"
                for ev in (evals[m], evals.setdefault(f"{m}.{cam}", _Eval()),
                           evals.setdefault(f"{m}.{motion}", _Eval())):
                    ev.iou.append(float(iou[k]))
                    ev.offset.append(float(off[k]))
        per_method[m] = (iou, off, has_truth)
        if m in ("stamp", "frame"):
            pos, t_assoc = a.scan_frame_pos, a.scan_points_t_ns
            if abs(int(st.stamp_ns[pos]) - t_assoc) > max_dt:
                continue
            sel = has_truth
            rows.append(AlignmentRow(
                clip_id=clip_id, agent_id=aid, lidar_frame_idx=scan.frame_idx, camera=cam,
                method=m, instance_id=None, camera_frame_idx=int(st.frame_idx[pos]),
                camera_t_ns=int(st.stamp_ns[pos]), points_t_ns=t_assoc,
                mean_iou=float(iou[sel].mean()) if sel.any() else None,
                center_offset_px=float(np.nanmean(off[sel]))
                if sel.any() and np.isfinite(off[sel]).any() else None,
            ))
        else:
            visible = np.isfinite(a.boxes2d[:, 0]) | has_truth
            for kk in np.flatnonzero(visible & ok):
                k = int(kk)
                pos = int(a.frame_pos[k])
                rows.append(AlignmentRow(
                    clip_id=clip_id, agent_id=aid, lidar_frame_idx=scan.frame_idx, camera=cam,
                    method=m, instance_id=str(boxes.instance_id[k]),
                    camera_frame_idx=int(st.frame_idx[pos]), camera_t_ns=int(st.stamp_ns[pos]),
                    points_t_ns=int(a.points_t_ns[k]),
                    mean_iou=float(iou[k]) if has_truth[k] else None,
                    center_offset_px=float(off[k]) if np.isfinite(off[k]) else None,
                ))
    # overlay candidate: the image the frame method chose, scored by truth boxes on it
    fr, sp = res["frame"], res["stamp"]
    if len(boxes):
        n_truth = int(per_method["frame"][2].sum())
        n_vis = int(np.isfinite(fr.boxes2d[:, 0]).sum())
        score = (n_truth, n_vis)
        if score > pick.score and n_vis > 0:

            def truth_on(img_idx: int) -> np.ndarray:
                tbs = [] if truth is None else [
                    truth[(aid, cam, img_idx, str(i))] for i in boxes.instance_id
                    if (aid, cam, img_idx, str(i)) in truth]
                return np.array(tbs, dtype=np.float64).reshape(-1, 4)

            f_img = int(st.frame_idx[fr.scan_frame_pos])
            s_img = int(st.frame_idx[sp.scan_frame_pos])
            target = res["target"].boxes2d[res["target"].frame_pos == fr.scan_frame_pos]
            empty = np.zeros((0, 4))
            panels = [(f_img, OverlayBoxes(truth_on(f_img), sp.boxes2d if s_img == f_img
                                           else empty, fr.boxes2d, target))]
            if s_img != f_img:
                panels.insert(0, (s_img, OverlayBoxes(truth_on(s_img), sp.boxes2d, empty,
                                                      empty)))
            pick.score = score
            pick.data = {
                "camera": cam, "lidar_frame_idx": scan.frame_idx, "panels": panels,
                "scan": scan, "stream": st, "frame_pos": fr.scan_frame_pos,
                "stamp_pos": sp.scan_frame_pos,
                "width": st.camera.intrinsics.width, "height": st.camera.intrinsics.height,
            }
    return rows


def _overlay_points(scan: LidarScan, st: CameraStream, agent: AgentData, T_el: np.ndarray,
                    pos: int, compensate: bool, params: AssociationConfig) -> np.ndarray:
    """(K, 3) u, v, depth of the scan's points in this camera's view (Fig. 10 style).

    ``compensate``: ego-motion compensated from t0 to the image's stamp (frame-based);
    otherwise the deskewed points as they are (t0), as the stamp method pairs them.
    """
    T_cam_lidar = compose(invert(st.camera.T_ego_cam), T_el)
    fov = points_in_fov(scan.xyz, T_cam_lidar, st.camera.intrinsics, params.fov_near_m)
    xyz = scan.xyz[fov]
    if compensate and xyz.size:
        xyz = compensate_points(xyz, agent.poses, T_el, scan.t0_ns, int(st.stamp_ns[pos]))
    cam = apply(T_cam_lidar, xyz)
    uv, front = project_points(cam, st.camera.intrinsics, params.fov_near_m)
    ok = front & np.isfinite(uv).all(axis=1)
    return np.concatenate([uv[ok], cam[ok, 2:3]], axis=1)


def _write_overlay(lake: Lake, clip_id: str, aid: str, agent: AgentData, T_el: np.ndarray,
                   d: dict[str, Any], params: AssociationConfig) -> str:
    cam = d["camera"]
    frames = agent.cameras[cam]
    panels = []
    f_img = int(d["stream"].frame_idx[d["frame_pos"]])
    for img_idx, boxes in d["panels"]:
        image: bytes | None = None
        where = np.flatnonzero(frames.frame_idx == img_idx)
        if where.size:
            try:
                image = lake.read_blob("clean", frames.blob[int(where[0])])
            except OSError:
                image = None
        is_frame = img_idx == f_img
        try:
            pts = _overlay_points(d["scan"], d["stream"], agent, T_el,
                                  d["frame_pos"] if is_frame else d["stamp_pos"], is_frame,
                                  params)
        except PoseCoverageError:
            pts = np.zeros((0, 3))
        title = f"{aid} {cam} lidar #{d['lidar_frame_idx']} image #{img_idx}"
        panels.append(Panel(image, d["width"], d["height"], boxes, title, pts))
    path = lake.path("clean", "images", clip_id, f"alignment_{aid}_{cam}.png")
    lake.write_bytes(path, render_overlay(panels))
    return path


ALIGN = Stage(
    name=DECLARATION.name, config_model=AlignConfig,
    # load_clip reads the clip record (storage.reader.CLIP_TABLES)
    reads=tables("clean", *CLIP_TABLES, "lidar_points_deskewed"),
    owns=DECLARATION.owns, run=run_align,
    doc="stamp-, frame- and target-based LiDAR-camera temporal alignment (Sec. 5)")
