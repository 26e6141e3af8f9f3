"""Annotate stage: make the clip's 3D boxes complete and consistent (main paper Sec. 3.4).

* ``num_lidar_pts``: the real number of deskewed points inside each box (what nuScenes'
  detection evaluation filters on), counted on clean ``lidar_points_deskewed``, i.e. in the
  same L0 frame the boxes are annotated in, and stored in annotate's own
  ``annotations_world`` (clean ``annotations`` belongs to anonymize and is never rewritten).
* ``instances``: one row per global instance id across agents and frames (category,
  count, agents, first / last time, links); a global id that changes category is an error.
* links: a linked instance (a trailer towed by a car) must exist in the clip, and where
  both are annotated in the same scan, be close to the box that links to it.
* ``annotations_world``: the boxes in the clip's local ENU frame, via
  ``T_world_ego(t0) T_ego_lidar`` at the scan start t0, for the exports.
* cross-agent consistency (V2V4Real-style): the same global id annotated by two agents at
  (nearly) the same time must coincide in the world frame; the median distance after
  pose-based registration, and after the refined registration where the ``registrations``
  table has accepted transforms, are reported.

This module is the stage's lake I/O and its ``Stage`` object; the numeric helpers are pure
functions in ``consistency.py`` (``world_boxes``, ``cross_agent_distances``, ``check_links``)
and the parameters are ``config.py``.
"""

from __future__ import annotations

from collections import defaultdict

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from v2xlake.schemas.arrow import rows_to_table
from v2xlake.schemas.errors import ClipError
from v2xlake.schemas.stage import OutputFile, Stage, StageReport, tables
from v2xlake.schemas.tables import AnnotationWorldRow, InstanceRow
from v2xlake.storage.lake import Lake
from v2xlake.storage.reader import CLIP_TABLES, iter_point_frames
from v2xlake.tasks.annotate import DECLARATION
from v2xlake.tasks.annotate.config import AnnotateConfig
from v2xlake.tasks.annotate.consistency import check_links, cross_agent_distances, world_boxes
from v2xlake.tasks.geometry import apply, count_points_in_boxes, transform
from v2xlake.tasks.reader import AgentData, load_posed_clip

STAGE = "annotate"
OWNS = ("annotations_world", "instances")


def _fail(clip_id: str, reason: str, *, agent_id: str | None = None,
          path: str | None = None) -> ClipError:
    return ClipError(clip_id, reason, stage=STAGE, agent_id=agent_id, path=path)


def _t0_per_row(agent: AgentData, sensor: str, frames: np.ndarray, clip_id: str) -> np.ndarray:
    lf = agent.lidar[sensor]
    t0_of = dict(zip(lf.frame_idx.tolist(), lf.t_start_ns.tolist(), strict=True))
    missing = sorted({int(f) for f in frames} - set(t0_of))
    if missing:
        raise _fail(clip_id, f"annotations name LiDAR frames {missing[:5]} that "
                    "lidar_frames does not have", agent_id=agent.agent_id)
    return np.array([t0_of[int(f)] for f in frames], dtype=np.int64)


def _registration_distances(
    lake: Lake, clip_id: str, ann_l0: dict[str, pa.Table], min_fitness: float,
    max_dt_ns: int,
) -> np.ndarray | None:
    """Same-id distances after mapping the other agent's boxes with the refined T_L1_L2."""
    reg = lake.read_table("clean", "registrations", clip_id=clip_id)
    if reg.num_rows == 0:
        return None
    out: list[float] = []
    for r in reg.to_pylist():
        if not r["accepted"] or r["fitness"] < min_fitness:
            continue
        a_ref, a_oth, fi = r["agent_ref"], r["agent_other"], int(r["frame_idx"])
        if a_ref not in ann_l0 or a_oth not in ann_l0:
            continue
        ta, tb = ann_l0[a_ref], ann_l0[a_oth]
        ta = ta.filter(pc.equal(ta["frame_idx"], fi))
        tb = tb.filter(pc.equal(tb["frame_idx"], fi))
        if ta.num_rows == 0 or tb.num_rows == 0:
            continue
        T = transform(np.array([r["tx"], r["ty"], r["tz"]]),
                      np.array([r["qw"], r["qx"], r["qy"], r["qz"]]))
        ib = {i: k for k, i in enumerate(tb["instance_id"].to_pylist())}
        for k, inst in enumerate(ta["instance_id"].to_pylist()):
            j = ib.get(inst)
            if j is None:
                continue
            ca = np.array([ta[c][k].as_py() for c in ("cx", "cy", "cz")])
            cb = apply(T, np.array([[tb[c][j].as_py() for c in ("cx", "cy", "cz")]]))[0]
            dt = (int(ta["t_ns"][k].as_py()) - int(tb["t_ns"][j].as_py()))
            if abs(dt) > max_dt_ns:
                continue
            v = [tb[c][j].as_py() for c in ("vx", "vy", "vz")]
            if all(x is not None for x in v):
                cb = cb + (T[:3, :3] @ np.array(v, dtype=float)) * dt * 1e-9
            out.append(float(np.linalg.norm(ca - cb)))
    return np.asarray(out, dtype=np.float64)


def run_annotate(lake: Lake, clip_id: str,
                 config: AnnotateConfig = AnnotateConfig()) -> StageReport:  # noqa: B008
    """Fill num_lidar_pts, write instances and world-frame boxes, validate links."""
    report = StageReport(stage=STAGE, clip_id=clip_id)
    ann_all = lake.read_table("clean", "annotations", clip_id=clip_id)
    if ann_all.num_rows == 0:
        return StageReport.not_applicable(STAGE, clip_id, "the clip has no annotations")
    clip = load_posed_clip(lake, clip_id, STAGE, "world-frame boxes and instance tracks "
                           "need poses; the annotations stay as delivered")
    if isinstance(clip, StageReport):
        return clip
    sensor = config.lidar_sensor
    by_agent: dict[str, pa.Table] = {}
    world_tables: dict[str, pa.Table] = {}
    cols_world: dict[str, list[np.ndarray]] = defaultdict(list)
    n_empty = 0
    n_unseen = 0
    for aid in sorted(set(ann_all["agent_id"].to_pylist())):
        if aid not in clip.agents:
            raise _fail(clip_id, "annotations name an agent the clip does not have",
                        agent_id=aid)
        agent = clip.agents[aid]
        t = ann_all.filter(pc.equal(ann_all["agent_id"], aid))
        t = t.sort_by([("frame_idx", "ascending"), ("instance_id", "ascending")])
        if set(t["sensor"].to_pylist()) != {sensor}:
            raise _fail(clip_id, f"annotations must be in the {sensor} frame, got sensors "
                        f"{sorted(set(t['sensor'].to_pylist()))}", agent_id=aid)
        if sensor not in agent.sensors or sensor not in agent.lidar:
            raise _fail(clip_id, f"annotated sensor {sensor} has no calibration / frames",
                        agent_id=aid)
        frames = t["frame_idx"].to_numpy().astype(np.int64)
        center = np.stack([t[c].to_numpy() for c in ("cx", "cy", "cz")], 1).astype(float)
        size = np.stack([t[c].to_numpy() for c in ("w", "l", "h")], 1).astype(float)
        quat = np.stack([t[c].to_numpy() for c in ("qw", "qx", "qy", "qz")], 1).astype(float)
        vel = np.stack([np.array([np.nan if x is None else x for x in t[c].to_pylist()], float)
                        for c in ("vx", "vy", "vz")], 1)
        counts = np.zeros(t.num_rows, dtype=np.int64)
        seen: set[int] = set()
        try:
            for pf in iter_point_frames(lake, clip_id, aid, sensor=sensor,
                                        frames=sorted(set(frames.tolist()))):
                rows = np.flatnonzero(frames == pf.frame_idx)
                counts[rows] = count_points_in_boxes(pf.xyz, center[rows], size[rows],
                                                     quat[rows], config.count_margin_m)
                seen.add(pf.frame_idx)
        except ClipError as e:
            raise _fail(clip_id, e.reason, agent_id=aid, path=e.path) from e
        unseen = sorted(set(frames.tolist()) - seen)
        if unseen:  # deskew skipped them (e.g. INS coverage at the clip edge): keep as given
            report.notes.append(f"{aid}: no deskewed points for annotated frames {unseen}; "
                                "num_lidar_pts left as annotated there")
            n_unseen += len(unseen)
        old = t["num_lidar_pts"].to_pylist()
        filled = [old[k] if int(frames[k]) not in seen else int(counts[k])
                  for k in range(t.num_rows)]
        n_empty += sum(1 for k in range(t.num_rows) if int(frames[k]) in seen and counts[k] == 0)
        t = t.set_column(t.schema.get_field_index("num_lidar_pts"), "num_lidar_pts",
                         pa.array(filled, pa.int64()))
        by_agent[aid] = t
        # world frame
        t0 = _t0_per_row(agent, sensor, frames, clip_id)
        T_w_l0 = agent.T_world_ego(t0, clip_id=clip_id) @ agent.sensors[sensor].T_ego_sensor
        wb = world_boxes(T_w_l0, center, quat, vel)
        w = t
        for k, c in enumerate(("cx", "cy", "cz")):
            w = w.set_column(w.schema.get_field_index(c), c, pa.array(wb.center[:, k]))
        for k, c in enumerate(("qw", "qx", "qy", "qz")):
            w = w.set_column(w.schema.get_field_index(c), c, pa.array(wb.quat[:, k]))
        for k, c in enumerate(("vx", "vy", "vz")):
            v = wb.velocity[:, k]
            w = w.set_column(w.schema.get_field_index(c), c,
                             pa.array(v, mask=~np.isfinite(v), type=pa.float64()))
        world_tables[aid] = w
        cols_world["instance_id"].append(np.asarray(t["instance_id"].to_pylist(), dtype=object))
        cols_world["agent"].append(np.full(t.num_rows, aid, dtype=object))
        cols_world["t_ns"].append(t["t_ns"].to_numpy().astype(np.int64))
        cols_world["center"].append(wb.center)
        cols_world["velocity"].append(wb.velocity)

    # ---- validation across the clip
    full = pa.concat_tables(list(by_agent.values()))
    inst_arr = np.asarray(full["instance_id"].to_pylist(), dtype=object)
    cats = full["category"].to_pylist()
    cat_of: dict[str, set[str]] = defaultdict(set)
    for i, c in zip(inst_arr, cats, strict=True):
        cat_of[str(i)].add(c)
    bad = {i: sorted(c) for i, c in cat_of.items() if len(c) > 1}
    if bad:
        raise _fail(clip_id, f"global instance ids with more than one category: "
                    f"{dict(list(bad.items())[:5])}")
    unknown, far, n_absent = check_links(
        np.asarray(full["agent_id"].to_pylist(), dtype=object),
        full["frame_idx"].to_numpy(), inst_arr, full["links"].to_pylist(),
        np.stack([full[c].to_numpy() for c in ("cx", "cy", "cz")], 1),
        full["l"].to_numpy(), config.links.max_gap_m,
    )
    if unknown:
        raise _fail(clip_id, "; ".join(unknown[:5]))
    if far and config.links.policy == "error":
        raise _fail(clip_id, "linked objects too far apart: " + "; ".join(far[:5]))
    report.notes.extend(far[:20])
    report.metrics["links.n_far"] = float(len(far))
    report.metrics["links.n_target_not_in_scan"] = float(n_absent)

    # ---- outputs
    for aid, w in world_tables.items():
        w = rows_to_table(AnnotationWorldRow, w.to_pylist())  # validated, typed
        path, n = lake.write_table("clean", "annotations_world", w, clip_id=clip_id,
                                   agent_id=aid, name="part")
        report.outputs.append(OutputFile(path=path, rows=n))
    inst_rows: list[InstanceRow] = []
    links_of: dict[str, set[str]] = defaultdict(set)
    for i, lk in zip(inst_arr, full["links"].to_pylist(), strict=True):
        links_of[str(i)].update(lk or [])
    agent_arr = np.asarray(full["agent_id"].to_pylist(), dtype=object)
    t_arr = full["t_ns"].to_numpy()
    for inst in sorted(cat_of):
        m = inst_arr == inst
        inst_rows.append(InstanceRow(
            clip_id=clip_id, instance_id=inst, category=next(iter(cat_of[inst])),
            n_annotations=int(m.sum()), agents=sorted(set(agent_arr[m].tolist())),
            first_t_ns=int(t_arr[m].min()), last_t_ns=int(t_arr[m].max()),
            links=sorted(links_of[inst]),
        ))
    path, n = lake.write_table("clean", "instances", rows_to_table(InstanceRow, inst_rows),
                               clip_id=clip_id, name="part")
    report.outputs.append(OutputFile(path=path, rows=n))

    # ---- cross-agent consistency
    max_dt = int(config.cross_agent.max_dt_ms * 1e6)
    d = cross_agent_distances(
        np.concatenate(cols_world["instance_id"]), np.concatenate(cols_world["agent"]),
        np.concatenate(cols_world["t_ns"]), np.concatenate(cols_world["center"]),
        np.concatenate(cols_world["velocity"]), max_dt)
    report.metrics["cross_agent.n_pairs"] = float(d.size)
    if d.size:
        report.metrics["cross_agent.median_dist_m"] = float(np.median(d))
        report.metrics["cross_agent.p90_dist_m"] = float(np.percentile(d, 90))
    dr = _registration_distances(lake, clip_id, by_agent,
                                 config.cross_agent.registration_min_fitness, max_dt)
    if dr is not None and dr.size:
        report.metrics["cross_agent.n_pairs_registered"] = float(dr.size)
        report.metrics["cross_agent.median_dist_registered_m"] = float(np.median(dr))
    report.metrics["n_annotations"] = float(full.num_rows)
    report.metrics["n_instances"] = float(len(inst_rows))
    report.metrics["n_boxes_without_points"] = float(n_empty)
    report.metrics["n_frames_without_points"] = float(n_unseen)
    pts = np.array([x for x in full["num_lidar_pts"].to_pylist() if x is not None], float)
    report.metrics["mean_lidar_pts"] = float(pts.mean()) if pts.size else 0.0
    return report


ANNOTATE = Stage(
    name=DECLARATION.name, config_model=AnnotateConfig,
    # load_clip reads the clip record (storage.reader.CLIP_TABLES), less what annotate writes
    reads=tables("clean", *(t for t in CLIP_TABLES if t not in OWNS), "lidar_points_deskewed"),
    owns=DECLARATION.owns, run=run_annotate,
    doc="points per box, global instances, world-frame boxes, link and cross-agent checks")
